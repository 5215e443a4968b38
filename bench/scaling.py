"""How UDAN's and QMIX's costs grow with the number of agents (pursuit-sized 100x100 grid).

For N in 10, 100, 1000: one acting step for the whole fleet (encode, leaders, groups, messages,
Q) and one training update on a batch of whole episodes, on synthetic data of the arena's
observation size. QMIX's global state is the map pooled to 20x20 cells (3 planes), as the MAgent
scenarios' ``state()`` gives. One torch thread. Prints one JSON object.
"""

from __future__ import annotations

import copy
import json
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import torch

from udan.envs.grouping import form_groups
from udan.learner import Actor, ModelSpec, MultiAgentQ
from udan.train import TrainConfig, update

OBS_DIM, MAP, STATE_DIM = 155, 100, 3 * 20 * 20
EPISODES, STEPS = 2, 10


def synthetic(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    cells = rng.choice(MAP * MAP, size=n, replace=False)
    pos = np.stack([cells // MAP, cells % MAP], -1)
    obs = (rng.random((n, OBS_DIM)) < 0.1).astype(np.float32)
    return pos, obs


def median_seconds(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def measure(algo: str, n: int, rng: np.random.Generator) -> dict:
    spec = ModelSpec(
        algo=algo,
        obs_dim=OBS_DIM,
        n_actions=5,
        state_dim=STATE_DIM if algo == "qmix" else 0,
        mix_agents=n if algo == "qmix" else 0,
    )
    torch.manual_seed(0)
    model = MultiAgentQ(spec)
    pos, obs = synthetic(n, rng)
    present = np.ones((1, n), bool)
    actor = Actor(model, 1, n)
    fresh = np.zeros((1, n), bool)
    act_s = median_seconds(lambda: actor.act(obs[None], present, pos[None], fresh), 7)

    t1 = STEPS + 1
    groups = np.full((EPISODES, t1, n, spec.group_size), -1, np.int16)
    n_groups = []
    for e in range(EPISODES):
        for t in range(t1):
            g = form_groups(pos, present[0], rng.random(n), spec.group_size, 0.7)
            groups[e, t, : len(g)] = g
            n_groups.append(len(g))
    batch = {
        "obs": np.broadcast_to(obs, (EPISODES, t1, n, OBS_DIM)).astype(np.float16),
        "state": rng.random((EPISODES, t1, spec.state_dim)).astype(np.float16),
        "actions": rng.integers(0, 5, (EPISODES, STEPS, n)).astype(np.int8),
        "rewards": rng.random((EPISODES, STEPS, n)).astype(np.float32),
        "present": np.ones((EPISODES, t1, n), bool),
        "fresh": np.zeros((EPISODES, t1, n), bool),
        "pos": np.broadcast_to(pos, (EPISODES, t1, n, 2)).astype(np.int16),
        "groups": groups,
    }
    cfg = TrainConfig(algo=algo)
    target = copy.deepcopy(model)
    optim = torch.optim.Adam(model.parameters(), lr=1e-4)
    update_s = median_seconds(lambda: update(model, target, optim, batch, cfg), 3)
    return {
        "algo": algo,
        "agents": n,
        "parameters": sum(p.numel() for p in model.parameters()),
        "groups_per_step": round(float(np.mean(n_groups)), 1),
        "act_step_ms": round(1000 * act_s, 2),
        "update_ms": round(1000 * update_s, 1),
        "update_ms_per_agent": round(1000 * update_s / n, 3),
    }


def main() -> int:
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    rows = [measure(algo, n, rng) for algo in ("udan", "qmix") for n in (10, 100, 1000)]
    growth = {}
    for algo in ("udan", "qmix"):
        r = {row["agents"]: row for row in rows if row["algo"] == algo}
        growth[algo] = {
            "update_1000_over_100": round(r[1000]["update_ms"] / r[100]["update_ms"], 2),
            "act_1000_over_100": round(r[1000]["act_step_ms"] / r[100]["act_step_ms"], 2),
        }
    json.dump(
        {
            "benchmark": "scaling",
            "grid": MAP,
            "episodes_per_update": EPISODES,
            "steps_per_episode": STEPS,
            "rows": rows,
            "growth_x10_agents": growth,
        },
        sys.stdout,
        indent=2,
    )
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
