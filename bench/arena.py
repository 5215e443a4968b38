"""Arena core throughput (agent-steps/s, observations included) and MAgent2's engine for reference.

Both run on one core in the same process and run, random actions, observations read every
step: the arena at B x 5 agents, MAgent2 on a 45x45 map with the same agent density and view
radius as the arena. Prints one JSON object.
"""

from __future__ import annotations

import json
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

from udan.envs import make_vec

TARGET_AGENT_STEPS_PER_S = 1_000_000


def arena_throughput(task: str, batch: int, seconds: float) -> dict:
    """Random-action agent-steps per second of the vectorised core, auto-resetting episodes."""
    env = make_vec(f"arena/{task}", batch=batch, seed=0, agents=(5, 5), obstacles=(0, 9))
    env.reset()
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 5, size=(64, batch, env.slots))
    agent_steps, steps, t0 = 0, 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        _, _, done = env.step(actions[steps % 64])
        agent_steps += int(env.present.sum())
        steps += 1
        if done.any():
            env.reset(done)
    elapsed = time.perf_counter() - t0
    return {
        "task": task,
        "batch": batch,
        "agents_per_arena": 5,
        "steps": steps,
        "agent_steps_per_s": round(agent_steps / elapsed),
        "step_ms": round(1000 * elapsed / steps, 3),
    }


def magent_throughput(map_size: int, seconds: float) -> dict:
    """MAgent2's C++ engine, one group, random moves, observations read every step."""
    import magent2
    from magent2 import gridworld as gw

    n_agents = round(5 / 81 * (map_size - 2) ** 2)
    cfg = gw.Config()
    cfg.set({"map_width": map_size, "map_height": map_size, "embedding_size": 10})
    kind = cfg.register_agent_type(
        "car",
        {
            "width": 1,
            "length": 1,
            "hp": 10,
            "speed": 1,
            "view_range": gw.CircleRange(3),
            "attack_range": gw.CircleRange(0),
        },
    )
    cfg.add_group(kind)
    engine = magent2.GridWorld(cfg)
    engine.set_seed(0)
    handle = engine.get_handles()[0]
    engine.reset()
    engine.add_agents(handle, method="random", n=n_agents)
    n_actions = engine.get_action_space(handle)[0]
    rng = np.random.default_rng(0)
    agent_steps, steps, t0 = 0, 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        n = engine.get_num(handle)
        engine.set_action(handle, rng.integers(0, n_actions, size=n, dtype=np.int32))
        engine.step()
        engine.get_observation(handle)
        engine.clear_dead()
        agent_steps += n
        steps += 1
    elapsed = time.perf_counter() - t0
    return {
        "map_size": map_size,
        "agents": n_agents,
        "steps": steps,
        "agent_steps_per_s": round(agent_steps / elapsed),
    }


def main() -> int:
    seconds = float(os.environ.get("BENCH_SECONDS", "5"))
    arena = [
        arena_throughput(task, batch, seconds)
        for task in ("find_water", "surround")
        for batch in (1024, 4096)
    ]
    magent = magent_throughput(45, seconds)
    best = max(r["agent_steps_per_s"] for r in arena)
    result = {
        "benchmark": "arena_core",
        "target_agent_steps_per_s": TARGET_AGENT_STEPS_PER_S,
        "arena": arena,
        "magent2_engine": magent,
        "best_arena_agent_steps_per_s": best,
        "arena_over_magent2": round(best / magent["agent_steps_per_s"], 2),
        "meets_target": best >= TARGET_AGENT_STEPS_PER_S,
    }
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
