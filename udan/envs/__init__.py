"""Environment registry: ``make(name)`` gives a PettingZoo ParallelEnv, ``make_vec`` B at once.

Backends are imported lazily, so the arena core (numpy only) never needs pettingzoo or magent2
unless those envs are asked for.
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
}

__all__ = [
    "EnvConfigError",
    "UnknownEnvError",
    "env_names",
    "make",
    "make_vec",
    "observation_layout",
]


def observation_layout(obs_spec: dict) -> tuple[int, tuple[str, ...], tuple[str, ...]]:
    """(version, channels, features) this code has for a saved spec's ``name``: each task with
    an observation of its own versions it apart (no name: the find_water/surround spec)."""
    from udan.envs.hidden_goal import SPEC_NAME, HiddenGoalSpec
    from udan.envs.observe import ObsSpec

    spec = HiddenGoalSpec if obs_spec.get("name") == SPEC_NAME else ObsSpec
    return spec.version, spec.channels, spec.features


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
