"""The safety filter between the policy and the cars: the grid rules, applied before dispatch.

The policy's actions go through the very rules training steps the arena with
(:func:`udan.envs.rules.resolve_moves`, or for a few cars :func:`udan.envs.rules.resolve_few`),
so a filtered set of moves never puts two cars into one cell, never swaps two cars, and never
drives into an obstacle or off the arena: a move the rules turn into a wait is sent as
``wait``. Everything else the camera sees on the grid that is not a car we drive (an unknown
marker, a car that is not in the fleet, the surround target) blocks its cell.

A car seen where the edge did not send it (pushed, slipped, a stalled wheel) is stopped for the
step: its command becomes ``stop`` and its cell blocks the others, and it moves again next step
from where the camera sees it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from udan.envs.rules import ACTION_DELTAS, FREE, WAIT, in_bounds, resolve_few, resolve_moves

STOP = 5  # udan.edge.protocol.Action.STOP: halt the motors
FEW_CARS = 24
"""Fleets up to this size are filtered in plain Python: cheaper than numpy's per-call cost."""
_DELTAS = [tuple(delta) for delta in ACTION_DELTAS.tolist()]  # (d_row, d_col) per action


@dataclass(frozen=True, slots=True)
class Filtered:
    """Commands after the filter, and why some differ from the policy's actions."""

    commands: np.ndarray  # (N,) 0-4 the grid actions, 5 stop
    blocked: np.ndarray  # (N,) bool: a move the rules turned into a wait
    stopped: np.ndarray  # (N,) bool: a car seen off its expected cell, stopped
    dest: np.ndarray  # (N, 2) the cell each car is in once its command is done


def filter_moves(
    layout: np.ndarray,
    pos: np.ndarray,
    actions: np.ndarray,
    *,
    expected: np.ndarray | None = None,
    others: np.ndarray | Sequence[Sequence[int]] | None = None,
) -> Filtered:
    """Commands for cars at ``pos`` (N, 2) wanting ``actions`` (N,) on ``layout`` (H, W) rules
    cell codes. ``expected`` (N, 2), where each car should be after its last command (rows of
    -1: no expectation); ``others`` (M, 2) or a list of pairs, cells held by things the edge
    does not drive.
    The cars stand on the arena (the runtime passes only those). Up to ``FEW_CARS`` cars in
    plain Python (:func:`udan.envs.rules.resolve_few`), more with the arrays of
    :func:`udan.envs.rules.resolve_moves`: the same commands either way."""
    pos = np.asarray(pos, dtype=np.int64).reshape(-1, 2)
    actions = np.asarray(actions, dtype=np.int64).reshape(-1)
    others = [] if others is None else others
    if expected is None:
        expected = np.full_like(pos, -1)
    filter_cars = _filter_few if len(pos) <= FEW_CARS else _filter_many
    return filter_cars(layout, pos, actions, expected, others)


def _filter_few(
    layout: np.ndarray,
    pos: np.ndarray,
    actions: np.ndarray,
    expected: np.ndarray,
    others: np.ndarray | Sequence[Sequence[int]],
) -> Filtered:
    """:func:`filter_moves` on Python lists: a few cars."""
    cells = pos.tolist()
    stopped = [e[0] >= 0 and e != c for e, c in zip(expected.tolist(), cells, strict=True)]
    cur = list(map(tuple, cells))
    moving = [WAIT if s else a for s, a in zip(stopped, actions.tolist(), strict=True)]
    height, width = layout.shape
    held = set(map(tuple, others.tolist() if isinstance(others, np.ndarray) else others))
    dst = []
    for (row, col), action in zip(cur, moving, strict=True):
        d_row, d_col = _DELTAS[action]
        to = row + d_row, col + d_col
        free = 0 <= to[0] < height and 0 <= to[1] < width and layout.item(to) == FREE
        dst.append(to if free and to not in held else (row, col))
    moved = resolve_few(cur, dst)
    blocked = [a != WAIT and not m for a, m in zip(moving, moved, strict=True)]
    commands = [
        STOP if s else WAIT if b else a for s, b, a in zip(stopped, blocked, moving, strict=True)
    ]
    dest = [d if m else c for d, m, c in zip(dst, moved, cur, strict=True)]
    return Filtered(
        commands=np.array(commands, np.int64),
        blocked=np.array(blocked, bool),
        stopped=np.array(stopped, bool),
        dest=np.array(dest, np.int64).reshape(-1, 2),
    )


def _filter_many(
    layout: np.ndarray,
    pos: np.ndarray,
    actions: np.ndarray,
    expected: np.ndarray,
    others: np.ndarray | Sequence[Sequence[int]],
) -> Filtered:
    """:func:`filter_moves` with array operations: many cars."""
    stopped = (expected != pos).any(axis=1) & (expected[:, 0] >= 0)  # seen off its cell
    moving = np.where(stopped, WAIT, actions)
    wants = moving != WAIT
    if not wants.any():  # nothing moves: nothing can conflict
        return Filtered(np.where(stopped, STOP, moving), wants, stopped, pos.copy())
    passable = layout == FREE
    others = np.asarray(others, np.int64).reshape(-1, 2)
    others = others[in_bounds(others, *layout.shape)]
    passable[others[:, 0], others[:, 1]] = False
    dest = resolve_moves(pos[None], moving[None], passable[None], np.ones((1, len(pos)), bool))[0]
    blocked = wants & np.logical_and.reduce(dest == pos, axis=1)  # a move that did not happen
    commands = np.where(blocked, WAIT, moving)
    commands[stopped] = STOP
    return Filtered(commands=commands, blocked=blocked, stopped=stopped, dest=dest)
