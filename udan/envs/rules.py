"""What a move does: the grid world rules shared by training, the edge safety filter and HIL.

Every function here is batched over arenas (axis 0) and agents (axis 1), numpy only, so the
vectorised training core, the edge runtime (one arena) and the HIL world all run the same code;
:func:`resolve_few` is the conflict rules once more in plain Python, for the edge's few cars
(tests hold it to :func:`resolve_moves`' answers).

Positions are ``(row, col)`` integer pairs; row 0 is the top of the camera image.
"""

from __future__ import annotations

import functools

import numpy as np

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
    (B, N). Absent agents (``present`` False) neither move nor block. Cells are numbered flat
    on the arenas bordered by one impassable cell, side by side, so a move is one addition, a
    move off the arena lands on the border, and every test below is one array operation (the
    edge calls this for 5 cars every step, training for thousands of agents).
    """
    n_batch, height, width = passable.shape
    bordered = np.zeros((n_batch, height + 2, width + 2), dtype=bool)
    bordered[:, 1:-1, 1:-1] = passable
    strides, steps, base = _numbering(n_batch, height, width)
    cur = pos @ strides + base
    dst = cur + steps[actions]
    dst = np.where(bordered.ravel().take(dst, mode="clip") & present, dst, cur)
    cur, dst = cur[present], dst[present]
    if cur.size == 0:
        return pos.copy()
    occupant = np.full(bordered.size, -1, dtype=np.int64)
    occupant[cur] = np.arange(cur.size)
    moving = dst != cur
    while moving.any():
        claims = np.bincount(dst, minlength=bordered.size)
        other = occupant[dst]
        # a claimed cell held by several, or a swap with the cell's occupant
        blocked = moving & ((claims[dst] > 1) | ((other >= 0) & (dst[other] == cur)))
        if not blocked.any():
            break
        dst = np.where(blocked, cur, dst)
        moving &= ~blocked
    done = np.full(present.shape, WAIT)
    done[present] = np.where(dst != cur, actions[present], WAIT)
    return pos + ACTION_DELTAS[done]


def resolve_few(cur: list[tuple[int, int]], dst: list[tuple[int, int]]) -> list[bool]:
    """Which of a few agents on the cells ``cur`` get to the cells ``dst`` they head for (a
    passable cell next to theirs, or their own: a wait): :func:`resolve_moves`' conflict rules
    and fixed point for one arena, in plain Python. The edge filters ~5 cars a step, where
    resolve_moves' ~40 array operations cost ~40 µs and this a few."""
    moved = [d != c for c, d in zip(cur, dst, strict=True)]
    if True not in moved:
        return moved
    dst = list(dst)
    occupant = {cell: i for i, cell in enumerate(cur)}
    while True:
        shared = len(set(dst)) < len(dst)  # some cell is claimed twice (rare: count then)
        # blocked: a claimed cell held by several, or a swap with the cell's occupant (an agent
        # is its own occupant when its cell is empty: never a swap, as it moves)
        blocked = [
            i
            for i, d in enumerate(dst)
            if moved[i] and ((shared and dst.count(d) > 1) or dst[occupant.get(d, i)] == cur[i])
        ]
        if not blocked:
            return moved
        for i in blocked:
            dst[i], moved[i] = cur[i], False


@functools.lru_cache(maxsize=64)
def _numbering(n_batch: int, height: int, width: int) -> tuple[np.ndarray, ...]:
    """For :func:`resolve_moves`: the (row, col) strides of the bordered cell numbers, each
    action's step in them, and each arena's offset plus the border (B, 1)."""
    strides = np.array([width + 2, 1])
    cells = (height + 2) * (width + 2)
    base = np.arange(0, n_batch * cells, cells)[:, None] + width + 3
    numbering = strides, ACTION_DELTAS @ strides, base
    for array in numbering:
        array.flags.writeable = False
    return numbering


def manhattan(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Grid distance between positions, broadcast over leading axes."""
    return np.abs(a[..., 0] - b[..., 0]) + np.abs(a[..., 1] - b[..., 1])
