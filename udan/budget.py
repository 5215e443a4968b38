"""A budget before a run: ``udan-train ... --calibrate`` plays a short stretch of the planned run
(its rollouts, its updates on a replay of the planned batches, a checkpoint save) and projects
what the whole run costs, so a run's card can state its budget before it starts.

The projection counts what :func:`udan.train.train` does: one rollout per ``n_envs`` episodes,
``updates_per_rollout`` updates every ``update_every`` rollouts once the replay holds a batch,
and a checkpoint (weights and the whole replay) every ``checkpoint_every`` steps. Costs are
measured at the start of training: a UDAN model that later forms more groups pays more per
update than at calibration (docs/algorithm.md says by how much it was off).
"""

from __future__ import annotations

import copy
import math
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from udan.envs import EnvConfigError
from udan.train import EpisodeReplay, TrainConfig, build, rollout, training_actor, update

#: Updates timed at least, after the first (which pays one-time costs and is not counted).
TIMED_UPDATES = 3
#: Rollouts timed at least (more when the first batch needs more episodes), after a first one
#: that pays one-time costs and is not counted.
MEASURED_ROLLOUTS = 2
#: Least wall time spent timing rollouts, and updates: quick ones are timed more often, so a
#: short burst of other load on the machine does not decide a small run's projection.
LEAST_TIMED_S = 1.0


class TimedEnv:
    """The environment batch with its ``step`` calls timed (everything else passes through)."""

    def __init__(self, env) -> None:
        self.env, self.seconds = env, 0.0

    def __getattr__(self, name: str):
        return getattr(self.env, name)

    def step(self, actions: np.ndarray):
        started = time.perf_counter()
        out = self.env.step(actions)
        self.seconds += time.perf_counter() - started
        return out


def planned_counts(cfg: TrainConfig, max_steps: int) -> dict[str, int]:
    """Rollouts, updates and checkpoints of a whole run of ``cfg`` (as the training loop has
    them)."""
    per_rollout = cfg.n_envs * max_steps
    rollouts = math.ceil(cfg.steps / per_rollout)
    first = math.ceil(cfg.batch_episodes / cfg.n_envs)  # the first rollout with a full batch
    rounds = sum(1 for r in range(first, rollouts + 1) if r % cfg.update_every == 0)
    checkpoints = math.ceil(rollouts * per_rollout / cfg.checkpoint_every)
    return {
        "rollouts": rollouts,
        "updates": rounds * cfg.updates_per_rollout,
        "checkpoints": checkpoints,
    }


def _seconds_per_call(play: Callable[[], None], least: int) -> tuple[float, int]:
    """Wall seconds per call of ``play``, called at least ``least`` times and for at least
    ``LEAST_TIMED_S``; and how many calls that took."""
    calls, started = 0, time.perf_counter()
    while calls < least or time.perf_counter() - started < LEAST_TIMED_S:
        play()
        calls += 1
    return (time.perf_counter() - started) / calls, calls


def calibrate(cfg: TrainConfig) -> dict:
    """Measure the cost of ``cfg``'s rollouts, updates and checkpoint saves; project the run."""
    if cfg.algo == "coma":
        raise EnvConfigError("--calibrate measures the value learners' loop; coma has its own")
    torch.set_num_threads(cfg.torch_threads)
    env, model = build(cfg)
    target = copy.deepcopy(model)
    optim = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    max_steps = env.config.max_steps
    shape = (max_steps, env.slots, env.spec.size, cfg.group_size, model.spec.state_dim)
    rollouts = max(math.ceil(cfg.batch_episodes / cfg.n_envs), MEASURED_ROLLOUTS)
    replay = EpisodeReplay(rollouts * cfg.n_envs, *shape)
    timed = TimedEnv(env)
    actor = training_actor(cfg, model, env)
    rng = np.random.default_rng(cfg.seed)
    has_state = model.spec.state_dim > 0

    def play_rollout() -> None:
        replay.add(rollout(timed, actor, cfg.eps_start, rng, has_state))

    def play_update() -> None:
        update(model, target, optim, replay.sample(cfg.batch_episodes, rng), cfg)

    play_rollout()
    timed.seconds = 0.0
    rollout_s, timed_rollouts = _seconds_per_call(play_rollout, rollouts)
    env_step_s = timed.seconds / (timed_rollouts * env.batch * max_steps)
    play_update()
    update_s, timed_updates = _seconds_per_call(play_update, TIMED_UPDATES)
    replay_bytes = sum(a.nbytes for a in replay.data.values()) / replay.capacity
    replay_bytes *= cfg.buffer_episodes
    with tempfile.TemporaryDirectory() as folder:
        started = time.perf_counter()
        replay.save(Path(folder) / "replay.npz", 0)
        torch.save(
            {"weights": model.state_dict(), "optimizer": optim.state_dict()}, Path(folder) / "c.pt"
        )
        saved = sum(f.stat().st_size for f in Path(folder).iterdir())
        save_rate = saved / (time.perf_counter() - started)
    checkpoint_s = replay_bytes / save_rate
    counts = planned_counts(cfg, max_steps)
    seconds = (
        counts["rollouts"] * rollout_s
        + counts["updates"] * update_s
        + counts["checkpoints"] * checkpoint_s
    )
    return {
        "algo": cfg.algo,
        "env": cfg.env,
        "agents": cfg.agents,
        "steps": int(cfg.steps),
        "episode_steps": max_steps,
        "obs_dim": env.spec.size,
        "measured": {"rollouts": timed_rollouts, "updates": timed_updates},
        "seconds_per_env_step": env_step_s,
        "seconds_per_step_acting": rollout_s / (env.batch * max_steps) - env_step_s,
        "seconds_per_rollout": rollout_s,
        "seconds_per_update": update_s,
        "seconds_per_checkpoint": checkpoint_s,
        **counts,
        "replay_gb": replay_bytes / 1e9,
        "cores": cfg.torch_threads,
        "projected_seconds": seconds,
        "projected_core_hours": seconds / 3600 * cfg.torch_threads,
        "load_average": os.getloadavg()[0],
    }


def summary(budget: dict) -> str:
    """The budget in one line."""
    return (
        f"budget: {budget['algo']} on {budget['env']} N {budget['agents']}, "
        f"{budget['steps']:,} steps = {budget['rollouts']:,} rollouts x "
        f"{budget['seconds_per_rollout']:.2f} s + {budget['updates']:,} updates x "
        f"{budget['seconds_per_update']:.2f} s + {budget['checkpoints']} checkpoints x "
        f"{budget['seconds_per_checkpoint']:.1f} s = {budget['projected_core_hours']:.1f} "
        f"core-hours on {budget['cores']} core(s); replay {budget['replay_gb']:.1f} GB; "
        f"measured at load average {budget['load_average']:.1f}"
    )
