"""The safety filter between the policy and the cars: the grid rules, applied before dispatch.

The policy's actions go through :func:`udan.envs.rules.resolve_moves`, the very rules training
steps the arena with, so a filtered set of moves never puts two cars into one cell, never swaps
two cars, and never drives into an obstacle or off the arena: a move the rules turn into a wait
is sent as ``wait``. Everything else the camera sees on the grid that is not a car we drive (an
unknown marker, a car that is not in the fleet, the surround target) blocks its cell.

A car seen where the edge did not send it (pushed, slipped, a stalled wheel) is stopped for the
step: its command becomes ``stop`` and its cell blocks the others, and it moves again next step
from where the camera sees it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from udan.envs.rules import FREE, WAIT, in_bounds, resolve_moves

STOP = 5  # edge.protocol.Action.STOP: halt the motors


@dataclass(frozen=True, slots=True)
class Filtered:
    """Commands after the filter, and why some differ from the policy's actions."""

    commands: np.ndarray  # (N,) 0-4 the grid actions, 5 stop
    blocked: np.ndarray  # (N,) bool: a move the rules turned into a wait
    stopped: np.ndarray  # (N,) bool: a car seen off its expected cell, stopped


def filter_moves(
    layout: np.ndarray,
    pos: np.ndarray,
    actions: np.ndarray,
    *,
    expected: np.ndarray | None = None,
    others: np.ndarray | None = None,
) -> Filtered:
    """Commands for cars at ``pos`` (N, 2) wanting ``actions`` (N,) on ``layout`` (H, W) rules
    cell codes. ``expected`` (N, 2), where each car should be after its last command (rows of
    -1: no expectation); ``others`` (M, 2), cells held by things the edge does not drive."""
    pos = np.asarray(pos, dtype=np.int64).reshape(-1, 2)
    actions = np.asarray(actions, dtype=np.int64).reshape(-1)
    if expected is None:
        stopped = np.zeros(len(pos), dtype=bool)
    else:  # a known expectation (row not -1) that differs from where the car is
        stopped = (expected != pos).any(axis=1) & (expected[:, 0] >= 0)
    moving = np.where(stopped, WAIT, actions)
    wants = moving != WAIT
    if not wants.any():  # nothing moves: nothing can conflict
        return Filtered(np.where(stopped, STOP, moving), wants, stopped)
    passable = layout == FREE
    if others is not None and len(others):
        others = others[in_bounds(others, *layout.shape)]
        passable[others[:, 0], others[:, 1]] = False
    dest = resolve_moves(pos[None], moving[None], passable[None], np.ones((1, len(pos)), bool))[0]
    blocked = wants & np.logical_and.reduce(dest == pos, axis=1)  # a move that did not happen
    commands = np.where(blocked, WAIT, moving)
    commands[stopped] = STOP
    return Filtered(commands=commands, blocked=blocked, stopped=stopped)
