"""Decision latency of the edge against the bare inference it wraps, one JSON object.

A decision step is state -> every command ready: masking, grouping, the graph calls and the
safety filter (:class:`udan.edge.decide.DecisionStep` with the bundled find_water policy). The
*bare call* is the graph call alone, onnxruntime and nothing else: after every decision the
policy runs the call of a step that keeps its groups once more on what that decision bound
(its observations, state and groups; :meth:`udan.export.runtime.OnnxPolicy.rerun`). Decisions
and bare calls alternate (A B A B ...), so both meet the same machine, and the targets are the
ratios of the two distributions, printed with a 95 % interval (a bootstrap over blocks of
consecutive steps): they hold on any machine. The same ratios of the thread's CPU time
(``decision_over_bare_call_cpu``, no target) leave out the time the process waited for a
core, which is most of a loaded machine's tail.

The decision step is fed the cells an arena episode would show the camera, and the world is
stepped with the commands it returns (so groups, joins and recurrent state evolve as on cars);
its latency is also split into the steps that form groups (every ``group_interval`` steps: the
neighbour table, a scoring call and the groups before the call that acts) and those that keep
them. Three sizes: the 9x9 arena with 5 cars, and 64 and 1,000 agents on surround arenas at
the same density of agents (the same network; the observation only normalises row and column
by the larger grid). One onnxruntime thread. The steps come one right after another (warm
caches); for 5 cars also after 50 ms of sleep each, as on cars, plain and with the runtime's
rehearsal (``decision_ms_after_idle``). Garbage is collected as the runtime does: frozen at
start, then between steps, never inside one (:mod:`udan.edge.pauses`).
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
#: agents -> the most a decision step may cost, as a ratio to the bare call, by statistic
TARGETS = {5: {"p99": 3.0}, 1000: {"p99": 1.5, "median": 1.3}}
KINDS = {"obstacle": OBSTACLE, "wall": WALL, "water": WATER}
WARM_UP = 5  # steps not counted: the first calls' allocations are not what a running edge pays
IDLE_S = 0.05  # between decisions in the after-idle case
ANALYSIS_S = 0.002  # from a rehearsal to the decision: the deciding frame's analysis
BLOCK = 50  # consecutive steps resampled together for the ratios' intervals
RESAMPLES = 2000
QUANTILES = (("median", 0.5), ("p99", 0.99))


def _percentiles(samples_ns: list[int]) -> dict[str, float]:
    ms = np.asarray(samples_ns) / 1e6
    return {
        "median": round(float(np.median(ms)), 4),
        "p99": round(float(np.percentile(ms, 99)), 4),
        "max": round(float(ms.max()), 4),
    }


def _ratio(decisions: np.ndarray, bare: np.ndarray, q: float) -> dict:
    """Decision over bare call at quantile ``q``, with a 95 % interval from resampling blocks of
    ``BLOCK`` consecutive (decision, bare call) pairs: the machine's slow stretches stay whole."""
    value = np.quantile(decisions, q) / np.quantile(bare, q)
    blocks = np.arange(0, len(decisions) - BLOCK + 1, BLOCK)
    rng = np.random.default_rng(0)
    draws = rng.choice(blocks, (RESAMPLES, len(blocks)))[..., None] + np.arange(BLOCK)
    draws = draws.reshape(RESAMPLES, -1)
    spread = np.quantile(decisions[draws], q, axis=1) / np.quantile(bare[draws], q, axis=1)
    low, high = np.quantile(spread, [0.025, 0.975])
    return {"value": round(float(value), 3), "ci95": [round(float(low), 3), round(float(high), 3)]}


def _world_cells(world: ArenaBatch, task: str) -> dict[str, frozenset[tuple[int, int]]]:
    static = {
        kind: frozenset(map(tuple, np.argwhere(world.layout[0] == code).tolist()))
        for kind, code in KINDS.items()
    }
    if task == "surround":
        static["target"] = frozenset({tuple(world.target[0].tolist())})
    return static


def run(
    config: ArenaConfig, steps: int, seed: int = 0, idle_s: float = 0.0, rehearse: bool = False
) -> dict:
    """Decide ``steps`` times, stepping the world with the commands, each decision followed by
    a bare call; episodes restart at the end.

    ``idle_s``: sleep this long before each decision, as the edge waits ~200 ms for the cars'
    moves (the caches go cold); ``rehearse``: then rehearse the last step and wait 2 ms, as the
    runtime does while the deciding frame is analysed."""
    world = ArenaBatch(config, 1, seed=seed)
    policy = OnnxPolicy(MODEL)
    decide = DecisionStep(policy, config.task, config.spec)
    total: list[int] = []
    bare: list[int] = []
    cpu: dict[str, list[int]] = {"decision": [], "bare": []}
    by_kind: dict[str, list[int]] = {"forming_groups": [], "keeping_groups": []}
    spans: dict[str, list[int]] = {}
    fresh = True
    freeze_garbage()
    gc.disable()  # as the runtime: collections between steps, never inside one
    try:
        for i in range(steps + WARM_UP):
            if fresh:
                world.reset()
                decide.reset()
                static = _world_cells(world, config.task)
            elif config.task == "surround":
                static = {**static, "target": _world_cells(world, config.task)["target"]}
            slots = {int(s) + 1: int(s) for s in np.flatnonzero(world.present[0])}
            cells = {car: tuple(world.pos[0, s].tolist()) for car, s in slots.items()}
            if idle_s:
                time.sleep(idle_s)
            if rehearse:  # as the runtime: the last step, or a new episode's first step
                decide.rehearse() or decide.rehearse(slots, cells, static)
                time.sleep(ANALYSIS_S)
            state = FleetState(slots, set(slots) if fresh else set(), cells, static)
            c0, t0 = time.thread_time_ns(), time.perf_counter_ns()
            decision = decide.decide(state)
            c1, t1 = time.thread_time_ns(), time.perf_counter_ns()
            policy.rerun()
            c2, t2 = time.thread_time_ns(), time.perf_counter_ns()
            if i >= WARM_UP:
                total.append(t1 - t0)
                bare.append(t2 - t1)
                cpu["decision"].append(c1 - c0)
                cpu["bare"].append(c2 - c1)
                by_kind["forming_groups" if decision.formed else "keeping_groups"].append(t1 - t0)
                for name, value in decision.spans_ns.items():
                    spans.setdefault(name, []).append(value)
            commands = np.full(world.slots, 4)
            commands[list(slots.values())] = np.minimum(decision.commands, 4)
            _, _, done = world.step(commands[None])
            fresh = bool(done[0])
            collect_between_steps(i)  # as the runtime, after the dispatch
    finally:
        gc.enable()
    agents = config.agents[1]
    decisions, calls = np.asarray(total), np.asarray(bare)
    ratios = {q: _ratio(decisions, calls, p) for q, p in QUANTILES}
    on_cpu = [np.asarray(cpu["decision"]), np.asarray(cpu["bare"])]
    for stat, limit in TARGETS.get(agents, {}).items():
        ratios[stat].update(target=limit, met=ratios[stat]["value"] <= limit)
    row = {
        "agents": agents,
        "grid": [config.height, config.width],
        "task": config.task,
        "steps": steps,
        "decision_ms": _percentiles(total),
        "bare_call_ms": _percentiles(bare),
        "decision_over_bare_call": ratios,
        "decision_over_bare_call_cpu": {q: _ratio(*on_cpu, p)["value"] for q, p in QUANTILES},
        "decision_ms_by_step": {kind: _percentiles(v) for kind, v in by_kind.items() if v},
        "spans_ms": {name: _percentiles(v) for name, v in spans.items()},
    }
    if agents in TARGETS:
        row["met"] = all(ratios[stat]["met"] for stat in TARGETS[agents])
    return row


def surround(agents: int, side: int, obstacles: int) -> ArenaConfig:
    """A surround arena with a fixed number of agents and obstacles."""
    return ArenaConfig(
        task="surround",
        agents=(agents, agents),
        obstacles=(obstacles, obstacles),
        height=side,
        width=side,
    )


def main() -> int:
    five = ArenaConfig(task="find_water", agents=(5, 5), obstacles=(0, 9))
    small = run(five, steps=2000)
    small["decision_ms_after_idle"] = {
        "idle_ms": IDLE_S * 1e3,
        "plain": run(five, steps=200, idle_s=IDLE_S)["decision_ms"],
        "rehearsed": run(five, steps=200, idle_s=IDLE_S, rehearse=True)["decision_ms"],
    }
    middle = run(surround(64, 26, 14), steps=1000)
    large = run(surround(1000, 100, 200), steps=1000)
    sizes = [small, middle, large]
    met = all(row["met"] for row in sizes if "met" in row)
    print(json.dumps({"threads": 1, "met": met, "sizes": sizes}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
