"""Environment registry: ``make(name)`` gives a PettingZoo ParallelEnv, ``make_vec`` B at once.

Backends are imported lazily, so the arena core (numpy and ``udan._kernels``) never needs
pettingzoo or magent2 unless those envs are asked for.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

from udan.envs.errors import EnvConfigError, UnknownEnvError

# name -> "module:factory" for the ParallelEnv, and for the vectorised form where one exists.
_PARALLEL: dict[str, str] = {
    "arena/surround": "udan.envs.pz:make_arena",
    "arena/find_water": "udan.envs.pz:make_arena",
    "arena/hidden_goal": "udan.envs.pz:make_hidden_goal",
    "magent/pursuit": "udan.envs.magent:make",
    "magent/tiger": "udan.envs.magent:make",
    "magent/queue": "udan.envs.magent:make",
}
_VECTOR: dict[str, str] = {
    "arena/surround": "udan.envs.arena:make_batch",
    "arena/find_water": "udan.envs.arena:make_batch",
    "arena/hidden_goal": "udan.envs.hidden_goal:make_batch",
    "magent/pursuit": "udan.envs.magent:make_batch",
    "magent/tiger": "udan.envs.magent:make_batch",
    "magent/queue": "udan.envs.magent:make_batch",
}

__all__ = [
    "EnvConfigError",
    "UnknownEnvError",
    "code_spec",
    "env_names",
    "make",
    "make_vec",
]


def code_spec(obs_spec: dict):
    """This code's :class:`~udan.envs.observe.ObsSpec` for a saved spec (a checkpoint's or a
    policy's): its version, channels, features and actions are what the saved ones must be. Each
    task with an observation of its own is told apart by ``name`` (none: find_water/surround)."""
    from udan.envs.hidden_goal import SPEC_NAME as HIDDEN_GOAL
    from udan.envs.hidden_goal import HiddenGoalSpec
    from udan.envs.magent_spec import SPEC_NAME as MAGENT
    from udan.envs.magent_spec import MagentSpec
    from udan.envs.observe import ObsSpec

    size = (obs_spec["height"], obs_spec["width"], obs_spec["view"])
    if obs_spec.get("name") == HIDDEN_GOAL:
        return HiddenGoalSpec(*size)
    if obs_spec.get("name") == MAGENT:
        scenario = ("scenario", "opponents", "n_moves", "n_attacks")
        return MagentSpec(*size, **{key: obs_spec[key] for key in scenario})
    return ObsSpec(*size)


def env_names() -> list[str]:
    """Every registered environment name."""
    return sorted(_PARALLEL)


def _load(table: dict[str, str], name: str, what: str) -> Callable[..., Any]:
    if name not in _PARALLEL:
        raise UnknownEnvError(f"unknown env {name!r}; known: {', '.join(env_names())}")
    if name not in table:
        raise UnknownEnvError(f"env {name!r} has no {what} form")
    module, attr = table[name].split(":")
    return getattr(importlib.import_module(module), attr)


def make(name: str, **kwargs: Any):
    """A PettingZoo ``ParallelEnv`` for ``name``; kwargs: agents, obstacles, seed, task options."""
    return _load(_PARALLEL, name, "parallel")(name, **kwargs)


def make_vec(name: str, batch: int, **kwargs: Any):
    """The vectorised core stepping ``batch`` independent episodes of ``name`` at once."""
    return _load(_VECTOR, name, "vectorised")(name, batch=batch, **kwargs)
