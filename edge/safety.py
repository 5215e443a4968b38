"""The safety filter between the policy and the cars: the grid rules, applied before dispatch.

The policy's actions go through the very rules training steps the arena with (the conflict
loop of :func:`udan.envs.rules.resolve_moves`, in ``udan._kernels``), so a filtered set of
moves never puts two cars into one cell, never swaps two cars, and never drives into an
obstacle or off the arena: a move the rules turn into a wait is sent as ``wait``. Everything
else the camera sees on the grid that is not a car we drive (an unknown marker, a car that is
not in the fleet, the surround target) blocks its cell.

A car seen where the edge did not send it (pushed, slipped, a stalled wheel) is stopped for the
step: its command becomes ``stop`` and its cell blocks the others, and it moves again next step
from where the camera sees it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from udan import _kernels
from udan.envs.rules import FREE

STOP = 5  # udan.edge.protocol.Action.STOP: halt the motors


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
    does not drive. The cars stand on the arena (the runtime passes only those). One loop in C
    (``udan._kernels.filter_moves``): a fleet of 5 cars costs no more numpy calls than one of
    1,000."""
    pos = np.ascontiguousarray(pos, dtype=np.int64).reshape(-1, 2)
    n = len(pos)
    expected = np.full_like(pos, -1) if expected is None else expected
    others = np.zeros((0, 2), np.int64) if others is None or not len(others) else others
    out = Filtered(np.empty(n, np.int64), np.empty(n, bool), np.empty(n, bool), np.empty_like(pos))
    _kernels.filter_moves(
        np.ascontiguousarray(layout, np.uint8),
        pos,
        np.ascontiguousarray(actions, np.int64).reshape(-1),
        np.ascontiguousarray(expected, np.int64).reshape(-1, 2),
        np.ascontiguousarray(others, np.int64).reshape(-1, 2),
        FREE,
        STOP,
        out.commands,
        out.blocked,
        out.stopped,
        out.dest,
    )
    return out
