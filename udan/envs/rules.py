"""What a move does: the grid world rules shared by training, the edge safety filter and HIL.

Every function here is batched over arenas (axis 0) and agents (axis 1), so the vectorised
training core, the edge runtime (one arena) and the HIL world all run the same code; the
conflict rules' fixed point is a loop in C (``udan._kernels``), whatever the number of agents.

Positions are ``(row, col)`` integer pairs; row 0 is the top of the camera image.
"""

from __future__ import annotations

import numpy as np

from udan import _kernels

ACTIONS: tuple[str, ...] = ("up", "down", "left", "right", "wait")
UP, DOWN, LEFT, RIGHT, WAIT = range(len(ACTIONS))
N_ACTIONS = len(ACTIONS)

#: (d_row, d_col) per action, indexed by action id.
ACTION_DELTAS = np.array([[-1, 0], [1, 0], [0, -1], [0, 1], [0, 0]], dtype=np.int64)

# Static cell codes of an arena layout.
FREE, WALL, OBSTACLE, WATER = 0, 1, 2, 3


def checked_actions(actions, batch: int, slots: int, present: np.ndarray) -> np.ndarray:
    """``actions`` as int64 (B, N), or ValueError naming what was expected: integers (a float or
    a string is never rounded or parsed), one per slot, each in 0..4 for present agents (absent
    slots' values are ignored and read as wait)."""
    arr = np.asarray(actions)
    if arr.dtype.kind not in "iu":
        raise ValueError(f"actions must be integers 0..{N_ACTIONS - 1}, got dtype {arr.dtype}")
    if arr.size != batch * slots:
        raise ValueError(f"expected {batch}x{slots} actions (one per slot), got shape {arr.shape}")
    arr = np.where(present, arr.reshape(batch, slots).astype(np.int64), WAIT)
    if arr.min() < 0 or arr.max() >= N_ACTIONS:
        bad = arr[(arr < 0) | (arr >= N_ACTIONS)][0]
        raise ValueError(f"actions must be in 0..{N_ACTIONS - 1} ({', '.join(ACTIONS)}), got {bad}")
    return arr


def in_bounds(pos: np.ndarray, height: int, width: int) -> np.ndarray:
    """True where ``pos[..., :]`` (integer rows and columns) lies inside a ``height`` x
    ``width`` grid. A negative row or column read as unsigned is a huge number, so one
    comparison checks both bounds."""
    unsigned = np.ascontiguousarray(pos, dtype=np.int64).view(np.uint64)
    return (unsigned < np.array([height, width], np.uint64)).all(axis=-1)


def resolve_moves(
    pos: np.ndarray, actions: np.ndarray, passable: np.ndarray, present: np.ndarray
) -> np.ndarray:
    """Simultaneous moves with deterministic conflict rules; returns the new positions.

    - a move off the arena or into an impassable cell is a wait;
    - two or more agents claiming one cell all wait (no priority, so no agent id bias);
    - a move into the cell of an agent that stays is a wait (resolved to a fixed point);
    - two agents swapping cells both wait (cars cannot pass through each other);
    - following (entering a cell its occupant leaves in the same step) is allowed, and so is a
      rotation of three or more agents, since no two cars are ever in one cell.

    ``pos`` (B, N, 2) int64, ``actions`` (B, N), ``passable`` (B, H, W) bool, ``present``
    (B, N). Absent agents (``present`` False) neither move nor block; present ones stand on
    their arena (ValueError otherwise). Each round of the fixed point looks at every move
    before it blocks any, so the outcome does not depend on the agents' order. One loop per
    arena over cells numbered on the arena bordered by one impassable cell, so a move is one
    addition and a move off the arena lands on the border (``udan._kernels.resolve_moves``:
    the edge calls this for 5 cars every step, training for thousands of agents).
    """
    pos = np.ascontiguousarray(pos, np.int64)
    out = np.empty_like(pos)
    _kernels.resolve_moves(
        pos,
        np.ascontiguousarray(actions, np.int64),
        np.ascontiguousarray(passable, bool),
        np.ascontiguousarray(present, bool),
        out,
    )
    return out


def manhattan(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Grid distance between positions, broadcast over leading axes."""
    return np.abs(a[..., 0] - b[..., 0]) + np.abs(a[..., 1] - b[..., 1])
