"""One ``.pt`` file per run: weights, resolved config, observation spec, env name, progress.

Loading never unpickles arbitrary objects (``weights_only=True``) and turns every way a file
can be wrong into :class:`CheckpointError`, which the CLIs report in one line with exit code 2.
"""

from __future__ import annotations

import dataclasses
import zipfile
from pathlib import Path
from typing import Any

import torch

from udan.envs import code_spec

FORMAT = "udan-checkpoint"
FORMAT_VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint that is missing, unreadable, from another format, or does not fit."""


def save_checkpoint(
    path: Path, model, target, optim, cfg, env, progress: dict, rng: dict, extra: dict | None = None
) -> None:
    """Write atomically (temp file + rename), so an interrupted save never corrupts a run.

    ``target`` may be None (on-policy learners); ``extra`` holds algorithm-specific entries
    (e.g. COMA's critic) under keys of their own.
    """
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "algo": model.spec.algo,
        "env": cfg.env,
        "obs_spec": env.spec.to_dict(),
        "model_spec": dataclasses.asdict(model.spec),
        "config": dataclasses.asdict(cfg),
        "weights": model.state_dict(),
        "target_weights": None if target is None else target.state_dict(),
        "optimizer": optim.state_dict(),
        "progress": dict(progress),
        "rng": rng,
        **(extra or {}),
    }
    tmp = path.with_suffix(".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """The checkpoint's dict, or :class:`CheckpointError` saying what is wrong with the file."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, EOFError, OSError, zipfile.BadZipFile, ValueError, KeyError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CheckpointError(f"{path} is not a readable checkpoint ({first[:120]})") from None
    except Exception as err:  # torch's unpickler raises assorted types on foreign pickles
        raise CheckpointError(f"{path} is not a udan checkpoint ({type(err).__name__})") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a udan checkpoint")
    if ckpt.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint format {ckpt.get('format_version')} is not {FORMAT_VERSION}"
        )
    version = code_spec(ckpt["obs_spec"]).version
    if ckpt["obs_spec"].get("version") != version:
        raise CheckpointError(
            f"{path}: observation spec v{ckpt['obs_spec'].get('version')} does not match this "
            f"code's v{version}"
        )
    return ckpt


def load_model(path: str | Path):
    """(model in eval mode, checkpoint dict) from a checkpoint file."""
    from udan.learner import ALGOS, ModelSpec, MultiAgentQ

    ckpt = load_checkpoint(path)
    if ckpt["algo"] not in ALGOS:
        raise CheckpointError(f"{path}: unknown algo {ckpt['algo']!r}")
    model = MultiAgentQ(ModelSpec(**ckpt["model_spec"]))
    try:
        model.load_state_dict(ckpt["weights"])
    except RuntimeError as err:
        raise CheckpointError(f"{path}: weights do not fit the model ({str(err)[:120]})") from None
    model.eval()
    return model, ckpt
