"""Decision latency of the edge: state -> all commands ready (masking, grouping, inference, safety).

The edge's own :class:`udan.edge.decide.DecisionStep` with the bundled find_water policy, fed the
cells an arena episode would show the camera, and the world stepped with the commands it returns (so
the groups, joins and recurrent state evolve as on cars); also split into the steps that form
groups (two graph calls, every ``group_interval`` steps) and those that keep them. Two sizes: the
9x9 arena with 5 cars, and 1,000 simulated agents on a 100x100 surround arena (the same network;
the observation only normalises row and column by the larger grid). One onnxruntime thread.
The steps come one right after another (warm caches); for 5 cars also after 50 ms of sleep
each, as on cars, plain and with the runtime's rehearsal (``decision_ms_after_idle``).
Garbage is collected as the runtime does: frozen at start, then between steps, never inside
one (:mod:`udan.edge.pauses`). Prints one JSON object.
"""

from __future__ import annotations

import gc
import json
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

from udan.edge.decide import DecisionStep
from udan.edge.fleet import FleetState
from udan.edge.pauses import collect_between_steps, freeze_garbage
from udan.envs.arena import ArenaBatch, ArenaConfig
from udan.envs.rules import OBSTACLE, WALL, WATER
from udan.export.runtime import OnnxPolicy
from udan.models import bundled_policy

MODEL = bundled_policy()
TARGETS_P99_MS = {5: 0.5, 1000: 10.0}
KINDS = {"obstacle": OBSTACLE, "wall": WALL, "water": WATER}
IDLE_S = 0.05  # between decisions in the after-idle case
ANALYSIS_S = 0.002  # from a rehearsal to the decision: the deciding frame's analysis


def _percentiles(samples_ns: list[int]) -> dict[str, float]:
    ms = np.asarray(samples_ns) / 1e6
    return {
        "median": round(float(np.median(ms)), 4),
        "p99": round(float(np.percentile(ms, 99)), 4),
        "max": round(float(ms.max()), 4),
    }


def run(
    config: ArenaConfig, steps: int, seed: int = 0, idle_s: float = 0.0, rehearse: bool = False
) -> dict:
    """Decide ``steps`` times, stepping the world with the commands; episodes restart at the end.

    ``idle_s``: sleep this long before each decision, as the edge waits ~200 ms for the cars'
    moves (the caches go cold); ``rehearse``: then rehearse the last step and wait 2 ms, as the
    runtime does while the deciding frame is analysed."""
    world = ArenaBatch(config, 1, seed=seed)
    decide = DecisionStep(OnnxPolicy(MODEL), config.task, config.spec)
    total: list[int] = []
    by_kind: dict[str, list[int]] = {"forming_groups": [], "keeping_groups": []}
    spans: dict[str, list[int]] = {"masking": [], "inference": [], "safety": []}
    fresh = True
    freeze_garbage()
    gc.disable()  # as the runtime: collections between steps, never inside one
    try:
        for i in range(steps + 5):
            if fresh:
                world.reset()
                decide.reset()
                static = {
                    k: frozenset(map(tuple, np.argwhere(world.layout[0] == c).tolist()))
                    for k, c in KINDS.items()
                }
            if config.task == "surround":
                static["target"] = frozenset({tuple(world.target[0].tolist())})
            slots = {int(s) + 1: int(s) for s in np.flatnonzero(world.present[0])}
            cells = {car: tuple(world.pos[0, s].tolist()) for car, s in slots.items()}
            if idle_s:
                time.sleep(idle_s)
            if rehearse:  # as the runtime: the last step, or a new episode's first step
                decide.rehearse() or decide.rehearse(slots, cells, static)
                time.sleep(ANALYSIS_S)
            t0 = time.perf_counter_ns()
            decision = decide.decide(
                FleetState(slots, set(slots) if fresh else set(), cells, static)
            )
            elapsed = time.perf_counter_ns() - t0
            if i >= 5:  # warm-up
                total.append(elapsed)
                by_kind["forming_groups" if decision.formed else "keeping_groups"].append(elapsed)
                for name, value in decision.spans_ns.items():
                    spans[name].append(value)
            commands = np.full(world.slots, 4)
            commands[list(slots.values())] = np.minimum(decision.commands, 4)
            _, _, done = world.step(commands[None])
            fresh = bool(done[0])
            collect_between_steps(i)  # as the runtime, after the dispatch
    finally:
        gc.enable()
    agents = config.agents[1]
    p99 = _percentiles(total)["p99"]
    return {
        "agents": agents,
        "grid": [config.height, config.width],
        "task": config.task,
        "steps": steps,
        "decision_ms": _percentiles(total),
        "decision_ms_by_step": {kind: _percentiles(v) for kind, v in by_kind.items() if v},
        "spans_ms": {name: _percentiles(v) for name, v in spans.items()},
        "target_p99_ms": TARGETS_P99_MS[agents],
        "met": p99 <= TARGETS_P99_MS[agents],
    }


def main() -> int:
    five = ArenaConfig(task="find_water", agents=(5, 5), obstacles=(0, 9))
    small = run(five, steps=2000)
    small["decision_ms_after_idle"] = {
        "idle_ms": IDLE_S * 1e3,
        "plain": run(five, steps=200, idle_s=IDLE_S)["decision_ms"],
        "rehearsed": run(five, steps=200, idle_s=IDLE_S, rehearse=True)["decision_ms"],
    }
    large = run(
        ArenaConfig(
            task="surround", agents=(1000, 1000), obstacles=(200, 200), height=100, width=100
        ),
        steps=1000,
    )
    print(json.dumps({"threads": 1, "sizes": [small, large]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
