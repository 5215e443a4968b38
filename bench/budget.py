"""How close ``udan-train --calibrate``'s projection comes to the run it projects.

For each value learner (UDAN, VDN, IQL), a small queue run (3-6 agents on a 12x12 map, 30-step
episodes, 8 environments, 4 updates a rollout) is first calibrated, then trained for real in the
same process: the projected seconds against the run's own recorded seconds, their ratio, and a
verdict (PASS when within ``TOLERANCE`` of the real time), with the load average at the start of
each run. A slow test asserts VDN's and IQL's verdicts (tests/test_magent_training.py, which also
tests the counts behind the projection exactly). UDAN's is measured, not asserted: its rollouts
and updates cost more as its scorer learns which agents lead (on this run they rise by about a
third and fall back), which no measurement before the run sees. Prints one JSON object.

    .venv/bin/python -P bench/budget.py > out/bench/budget.json
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
from pathlib import Path

from udan.budget import calibrate
from udan.checkpoint import load_checkpoint
from udan.train import TrainConfig, train

#: How far the projection may be from the real run, as a share of the real run's seconds.
TOLERANCE = 0.3
#: Environment steps of each run (a dozen rollouts and their updates; a longer run drifts further
#: from its calibration as a UDAN learns to form more groups).
STEPS = 2_880
SMALL_RUN = {
    "env": "magent/queue",
    "agents": "3-6",
    "obstacles": 0,
    "map_size": 12,
    "max_steps": 30,
    "n_envs": 8,
    "batch_episodes": 8,
    "updates_per_rollout": 4,
    "buffer_episodes": 16,
    "hidden": 16,
    "attn_dim": 8,
    "mix_dim": 8,
    "leader_explore": 0.3,
    "checkpoint_every": 1e9,
}


def measure(algo: str, folder: Path) -> dict:
    """The projection and the real run of the small queue run with ``algo``."""
    cfg = TrainConfig(algo=algo, steps=STEPS, out=str(folder / algo), **SMALL_RUN)
    load = os.getloadavg()[0]
    budget = calibrate(cfg)
    real = load_checkpoint(train(cfg, log=lambda *a, **k: None))["progress"]["seconds"]
    off = budget["projected_seconds"] / real - 1
    return {
        "algo": algo,
        "projected_seconds": round(budget["projected_seconds"], 2),
        "real_seconds": round(real, 2),
        "projection_off_by": round(off, 3),
        "load_average": load,
        "verdict": "PASS" if abs(off) <= TOLERANCE else "FAIL",
    }


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        runs = [measure(algo, Path(tmp)) for algo in ("udan", "vdn", "iql")]
    print(json.dumps({"steps": STEPS, "tolerance": TOLERANCE, "runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
