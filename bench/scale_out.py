"""Scale-out: environment steps per second of ``udan-train --workers 2`` against one process.

**Rollouts** (the target: ≥ 1.6 on a 2-core machine). ``magent/pursuit`` with 16 agents, 16
episodes of 300 steps per rollout, a fresh UDAN network acting (epsilon 0.05). Blocks alternate
in one run, A B A B ...:

* A, one process: the workers' own code (:class:`udan.distributed.RolloutWorker`) here, each
  rollout added to a replay, as ``udan-train`` does between its updates;
* B, ``--workers 2``: two Ray workers play at once (:class:`udan.distributed.RayPool`); this
  process adds each rollout to a replay and asks that worker again at once, as the learner does.

Each block counts ``--rollouts`` rollouts per worker after one warm-up rollout each; B's clock
stops when its last counted rollout arrives (those still in flight finish, uncounted, before the
next A). The ratio B/A of the blocks' steps per second comes with its 95 % interval
(``bench/tools/compare.py``'s: Welch t on the logs).

**The learner's costs** (for docs/scaling.md): one update's seconds (median of three, on
batches of the episodes the blocks played), adding one rollout to the replay, the bytes of a
rollout and of the weights. **Projection**, on paper from these: the single learner's ceiling
(it runs the updates one process would run for each rollout), how many workers reach it, and at
8, 32 and 128 workers the steps per second and the data into and out of the learner.

**Training** (reported, no target). ``udan.train.train`` itself, one process and
``--workers 2`` alternately, ``--train-steps`` steps each: wall time (Ray's start included), the
run's own clock, and the learner's busy share (updates over the run's time, from the workers'
ledger in the checkpoint). Where that share is near 1, the learner sets the pace and more
workers cannot shorten the run. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import importlib.util
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from udan.checkpoint import load_checkpoint
from udan.distributed import RayPool, RolloutWorker, WorkerLost
from udan.train import EpisodeReplay, TrainConfig, build, train, update

TARGET = 1.6
EPSILON = 0.05
#: Updates (and replay additions) timed for the learner's costs; their median is reported.
TIMED = 3
#: Worker counts of the projection.
SCALES = (8, 32, 128)
#: The learner is said to set the pace when its updates take more than this share of the run.
LEARNER_BOUND = 0.8

_tools = Path(__file__).resolve().parent / "tools" / "compare.py"
_spec = importlib.util.spec_from_file_location("compare", _tools)
compare = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(compare)


def one_process(
    worker: RolloutWorker, replay: EpisodeReplay, weights: dict, count: int
) -> tuple[float, float]:
    """Steps per second of ``count`` rollouts played here, and per second of this process's
    CPU time (what a worker with a core of its own would play, whatever the machine's load)."""
    started, cpu, steps = time.perf_counter(), time.process_time(), 0
    for _ in range(count):
        played = worker.play(weights, EPSILON)
        replay.add(played.episodes)
        steps += played.steps
    return steps / (time.perf_counter() - started), steps / (time.process_time() - cpu)


def two_workers(pool: RayPool, replay: EpisodeReplay, shared, count: int) -> tuple[float, list]:
    """Steps per second of ``count`` rollouts per worker from the pool's workers, and each
    counted rollout's own rate (its worker's steps per second)."""
    slots = len(pool.serials)
    started, steps, rates = time.perf_counter(), 0, []
    for slot in range(slots):
        pool.submit(slot, shared, EPSILON)
    while len(rates) < count * slots:
        got = pool.next(timeout=600)
        if got is None or isinstance(got[1], WorkerLost):
            raise RuntimeError(f"a worker gave no rollout: {got}")
        slot, played = got
        pool.submit(slot, shared, EPSILON)  # busy to the end of the block
        replay.add(played.episodes)
        steps += played.steps
        rates.append(played.steps / played.seconds)
    rate = steps / (time.perf_counter() - started)
    for _ in range(slots):  # the rollouts still in flight, uncounted
        pool.next(timeout=600)
    return rate, rates


def rollout_blocks(cfg: TrainConfig, pairs: int, count: int) -> tuple[dict, dict]:
    """The rollout blocks' figures, and the learner's costs measured on what they played."""
    env, model = build(dataclasses.replace(cfg, n_envs=1))
    replay = EpisodeReplay.for_run(cfg, env, model.spec, max(4 * cfg.n_envs, cfg.batch_episodes))
    rollout_bytes = sum(a.nbytes for a in replay.data.values()) // replay.capacity * cfg.n_envs
    weights = model.state_dict()
    here = RolloutWorker(cfg, model.spec, serial=2)
    pool = RayPool(dataclasses.replace(cfg, workers=2), rollout_bytes)
    try:
        pool.start(model.spec, 2, first_serial=0)
        shared = pool.share(weights)
        one_process(here, replay, weights, 1)  # warm-up: first calls, allocations
        two_workers(pool, replay, shared, 1)
        a, a_cpu, b, per_worker = [], [], [], []
        for _ in range(pairs):
            rate, cpu_rate = one_process(here, replay, weights, count)
            a.append(rate)
            a_cpu.append(cpu_rate)
            rate, rates = two_workers(pool, replay, shared, count)
            b.append(rate)
            per_worker += rates
    finally:
        pool.close()
    ratio = compare.ratio_ci(a, b)
    rollouts = {
        "one_process_steps_per_s": [round(x) for x in a],
        "one_process_steps_per_cpu_s": round(statistics.median(a_cpu)),
        "workers_2_steps_per_s": [round(x) for x in b],
        "per_worker_steps_per_s": round(statistics.median(per_worker)),
        "ratio": ratio["ratio"],
        "ratio_ci95": ratio["ci95"],
        "target": TARGET,
        "verdict": "PASS" if ratio["ratio"] >= TARGET else "FAIL",
    }
    return rollouts, learner_costs(cfg, model, replay, here, rollout_bytes)


def learner_costs(cfg, model, replay, worker, rollout_bytes) -> dict:
    """What one rollout costs the learner: adding it to the replay, and the updates it earns
    (median of ``TIMED`` updates on batches of the episodes played); the bytes moved."""
    played = worker.play(model.state_dict(), EPSILON)
    adds = [timed(lambda: replay.add(played.episodes)) for _ in range(TIMED)]
    target, optim = copy.deepcopy(model), torch.optim.Adam(model.parameters(), lr=cfg.lr)
    rng = np.random.default_rng(0)
    update(model, target, optim, replay.sample(cfg.batch_episodes, rng), cfg)  # warm-up
    updates = []
    for _ in range(TIMED):
        batch = replay.sample(cfg.batch_episodes, rng)
        updates.append(timed(lambda b=batch: update(model, target, optim, b, cfg)))
    weights = sum(v.numel() * v.element_size() for v in model.state_dict().values())
    return {
        "update_s": round(statistics.median(wall for wall, _ in updates), 4),
        "update_cpu_s": round(statistics.median(cpu for _, cpu in updates), 4),
        "updates_per_rollout": cfg.updates_per_rollout / cfg.update_every,
        "add_rollout_s": round(statistics.median(wall for wall, _ in adds), 4),
        "add_rollout_cpu_s": round(statistics.median(cpu for _, cpu in adds), 4),
        "rollout_steps": played.steps,
        "rollout_mb": round(rollout_bytes / 1e6, 2),
        "weights_mb": round(weights / 1e6, 3),
    }


def timed(fn) -> tuple[float, float]:
    """Wall and CPU seconds of ``fn()``."""
    started, cpu = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - started, time.process_time() - cpu


def projections(rollouts: dict, learner: dict) -> dict:
    """:func:`projection` from the wall-clock figures (as measured, under this run's load) and
    from the CPU-time ones (each process with a core of its own)."""
    return {
        "wall": projection(
            rollouts["per_worker_steps_per_s"],
            learner["update_s"],
            learner["add_rollout_s"],
            learner,
        ),
        "free_cores": projection(
            rollouts["one_process_steps_per_cpu_s"],
            learner["update_cpu_s"],
            learner["add_rollout_cpu_s"],
            learner,
        ),
    }


def projection(per_worker: float, update_s: float, add_s: float, learner: dict) -> dict:
    """On paper: the single learner's ceiling (it runs the updates one process would run for
    every rollout), the workers that reach it, and at 8, 32 and 128 workers the throughput and
    what flows into and out of the learner."""
    per_rollout = learner["updates_per_rollout"] * update_s + add_s
    ceiling = learner["rollout_steps"] / per_rollout
    mb_per_step = learner["rollout_mb"] / learner["rollout_steps"]
    rows = {}
    for workers in SCALES:
        steps = min(workers * per_worker, ceiling)
        rows[workers] = {
            "steps_per_s": round(steps),
            "learner_bound": workers * per_worker > ceiling,
            "rollouts_in_mb_per_s": round(steps * mb_per_step, 1),
            "weights_out_mb_per_s": round(  # a copy with each rollout asked for
                learner["weights_mb"] * steps / learner["rollout_steps"], 3
            ),
        }
    return {
        "learner_ceiling_steps_per_s": round(ceiling),
        "workers_at_the_ceiling": round(ceiling / per_worker, 2),
        "at": rows,
    }


def training_blocks(cfg: TrainConfig, steps: int, pairs: int) -> dict:
    runs: dict[int, list[dict]] = {0: [], 2: []}
    for _ in range(pairs):
        for workers in runs:
            with tempfile.TemporaryDirectory(prefix="scale-out-") as folder:
                run_cfg = dataclasses.replace(
                    cfg, steps=steps, workers=workers, out=f"{folder}/run", checkpoint_every=1e12
                )
                started = time.perf_counter()
                ckpt = load_checkpoint(train(run_cfg, log=_quiet))
                wall = time.perf_counter() - started
            ledger = ckpt.get("workers") or {}
            seconds = ckpt["progress"]["seconds"]
            runs[workers].append(
                {
                    "wall_s": round(wall, 1),
                    "run_s": round(seconds, 1),
                    "updates": ckpt["progress"]["updates"],
                    "learner_busy_share": round(ledger["learning"] / seconds, 3)
                    if ledger
                    else None,
                }
            )
    wall = compare.ratio_ci([r["wall_s"] for r in runs[2]], [r["wall_s"] for r in runs[0]])
    run = compare.ratio_ci([r["run_s"] for r in runs[2]], [r["run_s"] for r in runs[0]])
    busy = min(r["learner_busy_share"] for r in runs[2])
    return {
        "steps": steps,
        "one_process": runs[0],
        "workers_2": runs[2],
        "speed_up_wall": wall["ratio"],
        "speed_up_wall_ci95": wall["ci95"],
        "speed_up_run": run["ratio"],
        "speed_up_run_ci95": run["ci95"],
        "learner_bound": busy > LEARNER_BOUND,
        "verdict": "reported (no target): "
        + (
            f"the learner sets the pace (busy {busy:.0%} of the run)"
            if busy > LEARNER_BOUND
            else f"the rollouts set the pace (learner busy {busy:.0%})"
        ),
    }


def _quiet(*args: object, **kwargs: object) -> None:
    pass


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="magent/pursuit")
    parser.add_argument("--agents", default="16")
    parser.add_argument("--obstacles", default="0")
    parser.add_argument("--updates-per-rollout", type=int, default=4, help="as udan-train's")
    parser.add_argument("--n-envs", type=int, default=16, help="episodes per rollout")
    parser.add_argument("--max-steps", type=int, default=0, help="0: the task's own (300)")
    parser.add_argument("--map-size", type=int, default=0, help="0: the task's own")
    parser.add_argument("--pairs", type=int, default=5, help="A B pairs of rollout blocks")
    parser.add_argument("--rollouts", type=int, default=2, help="rollouts per worker per block")
    parser.add_argument(
        "--train-steps", type=int, default=28_800, help="steps per training run (0: none)"
    )
    parser.add_argument("--train-pairs", type=int, default=2, help="A B pairs of trainings")
    parser.add_argument("--buffer-episodes", type=int, default=64, help="the trainings' replay")
    args = parser.parse_args()
    cfg = TrainConfig(
        env=args.env,
        agents=args.agents,
        obstacles=args.obstacles,
        updates_per_rollout=args.updates_per_rollout,
        n_envs=args.n_envs,
        max_steps=args.max_steps,
        map_size=args.map_size,
        buffer_episodes=args.buffer_episodes,
    )
    load_before = os.getloadavg()[0]
    result = {
        "benchmark": "scale_out",
        "conditions": {
            "env": cfg.env,
            "agents": cfg.agents,
            "episodes_per_rollout": cfg.n_envs,
            "episode_steps": build(dataclasses.replace(cfg, n_envs=1))[0].config.max_steps,
            "cpus": os.cpu_count(),
            "load_average_before": round(load_before, 2),
        },
    }
    result["rollouts"], result["learner"] = rollout_blocks(cfg, args.pairs, args.rollouts)
    result["projection"] = projections(result["rollouts"], result["learner"])
    if args.train_steps:
        result["training"] = training_blocks(cfg, args.train_steps, args.train_pairs)
    result["conditions"]["load_average_after"] = round(os.getloadavg()[0], 2)
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
