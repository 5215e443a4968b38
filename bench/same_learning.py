"""Same learning: does find_water trained with ``--workers 2`` reach the committed model's score?

The run to compare is the committed model's own command (every setting its checkpoint records)
with ``--workers 2``; without its checkpoint this prints that command and the verdict "not run".
Both checkpoints play the card's table (1-5 agents, 0-9 obstacles, 100 episodes per cell, seed
0: the same layouts for both). Pooled over every episode: each model's mean with its 95 %
interval, and the paired difference (workers minus committed) with its interval. PASS when the
workers' mean is at or above the lower end of the committed model's interval: it reaches the
committed score within its CI. ``--workers N`` plays the cells on Ray (the same numbers).
Prints one JSON object.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
from contextlib import nullcontext
from pathlib import Path

import numpy as np

from udan.checkpoint import load_checkpoint, load_model
from udan.evaluate import CheckpointPolicy, evaluate, mean_ci
from udan.train import EARLIER_DEFAULTS, TrainConfig

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = ROOT / "models" / "find_water" / "checkpoint.pt"
RUN = Path("runs/find_water_workers2")
#: Settings that say where and how a run is spread, not what it learns.
PLACE = ("out", "workers", "address", "checkpoint_every")


def command(config: dict, out: Path) -> str:
    """``udan-train`` with every setting of ``config`` that is not today's default, then
    ``--workers 2`` into ``out``."""
    defaults = dataclasses.asdict(TrainConfig())
    flags = []
    for key, default in defaults.items():
        value = config.get(key, EARLIER_DEFAULTS.get(key, default))
        if key not in PLACE and value != default:
            flags += [
                f"--{key.replace('_', '-')}",
                f"{value:.0f}" if key == "steps" else str(value),
            ]
    return shlex.join(["udan-train", *flags, "--workers", "2", "--out", str(out)])


def scores(path: Path, runner) -> np.ndarray:
    """Every episode's average agent score on the card's table, cell by cell."""
    model, _ = load_model(path)
    cells = evaluate(
        "arena/find_water", CheckpointPolicy(model), (1, 5), (0, 9), 100, 0, runner=runner
    )
    return np.concatenate([cell.scores for cell in cells])


def summary(values: np.ndarray) -> dict:
    mean, half = mean_ci(values)
    return {"mean": round(mean, 3), "ci95": [round(mean - half, 3), round(mean + half, 3)]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, default=RUN / "checkpoint.pt")
    parser.add_argument("--committed", type=Path, default=COMMITTED)
    parser.add_argument("--workers", type=int, default=0, help="Ray workers for the cells")
    args = parser.parse_args()
    committed = load_checkpoint(args.committed)
    result = {
        "benchmark": "same_learning",
        "committed": str(args.committed),
        "command": command(committed["config"], args.checkpoint.parent),
    }
    if not args.checkpoint.is_file():
        json.dump({**result, "verdict": f"not run: no {args.checkpoint}"}, sys.stdout, indent=2)
        print()
        return 0
    trained = load_checkpoint(args.checkpoint)
    if trained["progress"]["steps"] < committed["progress"]["steps"]:
        raise SystemExit(f"{args.checkpoint} has fewer steps than the committed model")
    if args.workers:
        from udan.cluster import ray_map, ray_session

        session, runner = ray_session(args.workers), ray_map
    else:
        session, runner = nullcontext(), None
    with session:
        reference, workers = scores(args.committed, runner), scores(args.checkpoint, runner)
    before, after = summary(reference), summary(workers)
    result |= {
        "steps": trained["progress"]["steps"],
        "workers_ledger": trained.get("workers"),
        "committed_score": before,
        "workers_score": after,
        "difference": summary(workers - reference),
        "verdict": "PASS" if after["mean"] >= before["ci95"][0] else "FAIL",
        "reading": "the intervals are over evaluation episodes; a run with workers is not "
        "reproducible, like a run with another seed, and training runs differ by more than "
        "these intervals (not measured here)",
    }
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
