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
    "magent/pursuit": "udan.envs.magent:make",
    "magent/tiger": "udan.envs.magent:make",
    "magent/queue": "udan.envs.magent:make",
}
_VECTOR: dict[str, str] = {
    "arena/surround": "udan.envs.arena:make_batch",
    "arena/find_water": "udan.envs.arena:make_batch",
}

__all__ = ["EnvConfigError", "UnknownEnvError", "env_names", "make", "make_vec"]


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
