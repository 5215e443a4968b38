"""PettingZoo ``ParallelEnv`` view over one arena of the vectorised core.

Agents are named ``agent_<id>`` with ids stable within an episode; an agent that leaves is
terminated, one that joins appears in ``agents`` and in the next observations.
"""

from __future__ import annotations

import functools
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from udan.envs.arena import ArenaBatch, ArenaConfig
from udan.envs.hidden_goal import HiddenGoalBatch, HiddenGoalConfig
from udan.envs.rules import N_ACTIONS, WAIT


class ArenaParallelEnv(ParallelEnv):
    """One arena episode at a time; the numbers come from :class:`ArenaBatch` with B = 1."""

    metadata: ClassVar[dict] = {
        "name": "udan_arena_v1",
        "render_modes": ["ansi"],
        "is_parallelizable": True,
    }

    def __init__(
        self,
        config: ArenaConfig | HiddenGoalConfig,
        seed: int | None = 0,
        render_mode: str | None = None,
    ) -> None:
        self.config = config
        self.render_mode = render_mode
        core = HiddenGoalBatch if isinstance(config, HiddenGoalConfig) else ArenaBatch
        self._core = core(config, batch=1, seed=seed)
        joins = config.max_steps if config.churn > 0 else 0
        self.possible_agents = [f"agent_{i}" for i in range(config.agents[1] + joins)]
        self.agents: list[str] = []
        self._slot_of: dict[str, int] = {}

    @property
    def core(self) -> ArenaBatch:
        """The underlying one-arena batch (positions, layout, target) for planners and renderers."""
        return self._core

    @functools.cache  # noqa: B019 - the API test wants the same object each call
    def observation_space(self, agent: str) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, shape=(self.config.spec.size,), dtype=np.float32)

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Discrete:
        return spaces.Discrete(N_ACTIONS)

    def _names(self) -> list[str]:
        core = self._core
        slots = np.flatnonzero(core.present[0])
        self._slot_of = {f"agent_{core.agent_id[0, s]}": int(s) for s in slots}
        return list(self._slot_of)

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._core.rng = np.random.default_rng(seed)
        obs = self._core.reset()[0]
        self.agents = self._names()
        return ({a: obs[s] for a, s in self._slot_of.items()}, {a: {} for a in self.agents})

    def step(self, actions: dict[str, Any]):
        core = self._core
        if not self.agents:
            raise ValueError("the episode is over: call reset() first")
        missing = [a for a in self.agents if a not in actions]
        unknown = [a for a in actions if a not in self._slot_of]
        if missing or unknown:
            raise ValueError(
                f"step() needs one action for each of {self.agents}"
                + (f"; missing {missing}" if missing else "")
                + (f"; not in the episode: {unknown}" if unknown else "")
            )
        act = np.full((1, core.slots), WAIT, dtype=np.int64)
        for agent, action in actions.items():
            value = np.asarray(action)
            if value.shape != () or value.dtype.kind not in "iu":
                raise ValueError(
                    f"{agent}: an action is an integer 0..{N_ACTIONS - 1}, got {action!r}"
                )
            act[0, self._slot_of[agent]] = value
        before = dict(self._slot_of)
        obs, reward, done = core.step(act)
        self.agents = [] if done[0] else self._names()
        rewards = {a: float(reward[0, s]) for a, s in before.items()}
        terminated = {a: bool(core.left[0, s]) for a, s in before.items()}
        truncated = {a: bool(done[0]) and not terminated[a] for a in before}
        for agent in self.agents:  # joined this step
            if agent not in before:
                rewards[agent] = 0.0
                terminated[agent] = truncated[agent] = False
        observations = {a: obs[0, s] for a, s in {**before, **self._slot_of}.items()}
        infos = {a: {} for a in observations}
        return observations, rewards, terminated, truncated, infos

    def state(self) -> np.ndarray:
        return self._core.global_state()[0]

    def render(self) -> str:
        return self._core.render(0)


def make_arena(
    name: str, seed: int | None = 0, render_mode: str | None = None, **options: Any
) -> ArenaParallelEnv:
    """Registry factory for ``arena/<task>``: options are :class:`ArenaConfig` fields."""
    config = ArenaConfig(task=name.removeprefix("arena/"), **options)
    return ArenaParallelEnv(config, seed=seed, render_mode=render_mode)


def make_hidden_goal(
    name: str, seed: int | None = 0, render_mode: str | None = None, **options: Any
) -> ArenaParallelEnv:
    """Registry factory for ``arena/hidden_goal``: options are :class:`HiddenGoalConfig` fields."""
    return ArenaParallelEnv(HiddenGoalConfig(**options), seed=seed, render_mode=render_mode)
