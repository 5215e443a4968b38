"""The bundled policies (``udan.models``), shipped as package data so that every command finds
them from any working folder, from a source checkout and from an installed wheel alike.

The wheel carries each task's ``policy.onnx``; checkpoints, the baselines, plots and model cards
stay in the repository.
"""

from __future__ import annotations

import atexit
from contextlib import ExitStack
from importlib.resources import as_file, files
from pathlib import Path

#: The policy ``udan-edge --sim``, ``udan-hil run`` and the demo drive cars with by default.
DEFAULT_POLICY = "find_water"

# An installed package is a folder, so ``as_file`` hands back the file itself; from a zip it would
# extract a copy, which must outlive the call: kept until the process exits.
_extracted = ExitStack()
atexit.register(_extracted.close)


def bundled_policy(name: str = DEFAULT_POLICY) -> Path:
    """The file of the bundled ONNX policy of task ``name`` (``find_water``, ``surround``);
    ``FileNotFoundError`` naming it if there is none."""
    resource = files(__name__).joinpath(name, "policy.onnx")
    if not resource.is_file():
        raise FileNotFoundError(f"no bundled policy {name!r}")
    return _extracted.enter_context(as_file(resource))
