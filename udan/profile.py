"""The speed profile a car's controller drives a move on (protocol section 8): shared by the
mock controller, which drives it, and the edge's guard, which predicts where a commanded car
will be (:func:`udan.edge.bodies.closing_in`)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike


def travelled(tau: ArrayLike, accel_share: float) -> np.ndarray:
    """Share of a move covered after share ``tau`` of its time (a number or an array), for a
    trapezoidal speed profile: constant acceleration for ``accel_share`` of the time, constant
    speed, as long braking. ``accel_share`` 0 is constant speed (the exact level's cars)."""
    tau = np.clip(tau, 0.0, 1.0)
    a = accel_share
    if a <= 0:
        return tau
    peak = 1 / (1 - a)
    speeding = peak * tau * tau / (2 * a)
    braking = 1 - peak * (1 - tau) ** 2 / (2 * a)
    return np.where(tau < a, speeding, np.where(tau > 1 - a, braking, peak * (tau - a / 2)))


def move_span(cells: float, quarter_turns: float) -> float:
    """How many cell times a move of ``cells`` cell sides and ``quarter_turns`` quarter turns
    takes: a cell or a quarter turn one; a shorter move is limited by the acceleration (the
    time grows as the square root of the distance), a longer one by the top speed."""
    return max(cells, math.sqrt(cells), quarter_turns, math.sqrt(quarter_turns))
