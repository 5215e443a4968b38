"""Exported-policy latency for ``make bench``: onnxruntime vs torch eager, one JSON on stdout.

Uses ``models/find_water/checkpoint.pt`` when it exists (hidden 64, what the demo runs);
otherwise trains a throwaway checkpoint of the default width in a temporary folder, which is as
good for timing (latency does not depend on how well a policy plays). Also runs the 1000-agent
parity check that the unit tests leave out.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import tempfile
from pathlib import Path

# Run as a script, this file's folder heads sys.path and its name would shadow the package.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import onnx  # noqa: E402
import torch  # noqa: E402

from udan.checkpoint import load_model  # noqa: E402
from udan.export.bench import bench  # noqa: E402
from udan.export.cli import sha256  # noqa: E402
from udan.export.graph import build_graph  # noqa: E402
from udan.export.metadata import build_metadata  # noqa: E402
from udan.export.verify import verify  # noqa: E402
from udan.train import TrainConfig, train  # noqa: E402

MODEL = Path(__file__).resolve().parent.parent / "models" / "find_water" / "checkpoint.pt"


def main() -> int:
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        checkpoint = MODEL
        if not MODEL.is_file():
            cfg = TrainConfig(steps=400, n_envs=4, batch_episodes=4, out=str(Path(tmp) / "run"))
            checkpoint = train(cfg, log=lambda *a, **k: None)
        model, ckpt = load_model(checkpoint)
        meta = build_metadata(ckpt, dataclasses.asdict(model.spec), sha256(checkpoint))
        onnx_model = build_graph(model, meta)
        policy = Path(tmp) / "policy.onnx"
        onnx.save(onnx_model, str(policy))
        parity = verify(onnx_model, model, sizes=(5, 1000), steps=3)
        figures = bench(policy, model)
    figures["checkpoint"] = str(checkpoint) if checkpoint == MODEL else "throwaway (400 steps)"
    figures["parity"] = parity.to_dict()
    print(json.dumps(figures, indent=1))
    return 0 if parity.ok else 1


if __name__ == "__main__":
    sys.exit(main())
