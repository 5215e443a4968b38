"""Where real car bodies would touch, though the grid rules let the moves through.

The arena's rules (:mod:`udan.envs.rules`) let a car enter a cell its occupant leaves in the
same step. Real cars have bodies (22 cm on 31 cm cells in the HIL): a car entering a cell that
another leaves *sideways* cuts the corner of the leaver's path and hits it, and a car following
one that slips and stops short runs into it. Three answers, none of which changes a decision
(so the full loop still plays the simulation's moves, unless a command is missed):

- :func:`corner_delays`: a car that enters a cell its occupant leaves in another direction starts
  later, by ``CORNER_DELAY`` of a cell time per such link of a chain (carried in its command,
  protocol section 3); a car that follows its leader the same way starts a little later too
  (``MotionRules.follow_gap_s``). A ring of cars each entering the next one's cell cannot be
  driven by bodies at all: its cars wait (the grid rules allow it, but it needs four cars in a
  2x2 block turning together, which the policies have not been seen to do), and so does a
  chain that would need more than ``MAX_DELAY``. Re-centring moves are checked by
  :func:`crossing`: of two whose paths would sweep through each other, one waits a round.
- a car entering a cell its occupant leaves is sent its command only once the occupant accepted
  its own (the link's dispatch, ``after``): a car that missed its command stays, and nobody is
  driven into it.
- :func:`closing_in`: between steps, from the camera's frames, a car whose body would touch
  another's within the horizon, each predicted along its move's plan at the pace it kept
  (:class:`Plan`) and never past the target it drives to, is stopped (the guard). It is then
  re-centred like any car stopped mid-move.

Bodies are taken as squares turned by at most the settling tolerance (a few degrees): two cars
touch when their centres are closer than ``reach`` along both axes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from udan.profile import travelled

Cell = tuple[int, int]
CORNER_DELAY = 1.0
"""Start delay of a car entering a cell its occupant leaves sideways, in cell times: a whole
move, so the leaver has arrived before the entrant starts. Nominal timing would allow less (at
constant speed the leaver must be 0.81 of the way out, its body clear of the corner with 3 cm
to spare, before the entrant is 0.19 of the way in: 0.62; with the HIL's trapezoid 0.46), but
a leaver's move starts late when its car is slow to hand the command to its motors, and a
slipping leaver is slow all the way (both seen on a loaded machine)."""
MAX_DELAY = 2.0
"""The longest start delay a command carries (protocol section 3): a chain needing more waits."""
PACE_FROM_M = 0.03
"""The guard measures a car's pace against its plan over a frame's time once the plan drives
this far in it (the camera's position noise, up to 2.5 mm, is then under a tenth of it)."""
MAX_PACE = 2.0
"""... and takes a car as at most this much ahead of its plan (a car whose move began later
than the edge reckons is behind it, then catches up)."""


def corner_delays(
    moves: Mapping[int, tuple[Cell, Cell]], corner: float = CORNER_DELAY, straight: float = 0.0
) -> tuple[dict[int, float], set[int]]:
    """Start delays (cell times) of cars moving ``from -> to``, ``corner`` per corner of a
    chain and ``straight`` per link that follows its leader the same way, and the cars that
    must wait instead (a ring, and every car entering a cell whose leaver waits)."""
    leaver = {start: car for car, (start, end) in moves.items() if start != end}
    delays: dict[int, float] = {}
    waits: set[int] = set()

    def delay(car: int, chain: tuple[int, ...]) -> float | None:
        if car in delays:
            return delays[car]
        if car in chain or car in waits:
            return None
        start, end = moves[car]
        ahead = leaver.get(end)
        if start == end or ahead is None:
            delays[car] = 0.0
            return 0.0
        after = delay(ahead, (*chain, car))
        if after is None:
            waits.add(car)
            return None
        ahead_start, ahead_end = moves[ahead]
        way = (end[0] - start[0], end[1] - start[1])
        same_way = way == (ahead_end[0] - ahead_start[0], ahead_end[1] - ahead_start[1])
        wait = after + (straight if same_way else corner)
        if wait > MAX_DELAY:
            waits.add(car)
            return None
        delays[car] = wait
        return wait

    for car in moves:
        delay(car, ())
    return {c: d for c, d in delays.items() if c not in waits}, waits


def crossing(
    paths: Mapping[int, tuple[tuple[float, float], tuple[float, float]]],
    standing: Mapping[int, tuple[float, float]],
    reach: float,
) -> set[int]:
    """Of cars driving straight ``from -> to`` (metres) at once, those that must wait a round.

    Re-centring moves are not grid moves: a car sent to complete a move it was cut short in
    may drive towards a car that is still where it stopped, and two cars off towards each
    other can sweep their corners through each other. In id order, a car moves only if its
    path keeps clear of every car that does not move this round (``standing``, and the cars of
    ``paths`` not let go yet, where they are) and of every point of the paths let go before it
    (their timing is not known well enough to count on it): never closer than ``reach`` along
    both axes, unless already that close at the start and getting no closer."""
    share = np.linspace(0.0, 1.0, 9)[:, None]
    points = {c: np.add(a, share * np.subtract(b, a)) for c, (a, b) in paths.items()}

    def clear(mine: np.ndarray, theirs: np.ndarray) -> bool:
        apart = np.abs(mine[:, None, :] - theirs[None, :, :]).max(axis=2)
        return bool(apart.min() >= min(reach, float(apart[0, 0])))

    going: list[int] = []
    for car in sorted(paths):
        still = [np.array([xy]) for c, xy in standing.items() if c != car]
        still += [points[c][:1] for c in paths if c != car and c not in going]
        if all(clear(points[car], other) for other in still) and all(
            clear(points[car], points[c]) for c in going
        ):
            going.append(car)
    return set(paths) - set(going)


@dataclass(frozen=True)
class Plan:
    """A commanded move as the car's controller drives it (protocol section 8): ``length_m``
    from where the car was when commanded to its target, beginning at ``begins_ns`` (edge
    clock: when the car took the command, plus its start delay) and lasting ``duration_ns`` on
    the speed profile of ``accel_share``."""

    length_m: float
    begins_ns: int
    duration_ns: int
    accel_share: float

    def covered(self, t_ns: np.ndarray) -> np.ndarray:
        """Metres of the move covered at the times ``t_ns``."""
        tau = (np.asarray(t_ns, np.float64) - self.begins_ns) / max(self.duration_ns, 1)
        return self.length_m * travelled(tau, self.accel_share)


def closing_in(
    now: Mapping[int, tuple[float, float]],
    before: Mapping[int, tuple[float, float, float]],
    targets: Mapping[int, tuple[float, float]],
    horizon_s: float,
    reach: float,
    plans: Mapping[int, Plan] | None = None,
    t_ns: int = 0,
) -> set[int]:
    """Cars to stop: those whose body would come within ``reach`` of another's (along both
    axes) in the next ``horizon_s`` after ``t_ns``, each moving towards its target and never
    past it; of two such cars, the one closing in (both when both are).

    A car with a plan (``plans``, its move as its controller drives it) is predicted along the
    rest of it from where it is, at the pace it kept between ``before`` (x, y, seconds earlier)
    and ``now`` (x, y) against the plan over that time (a car that slipped keeps its slower
    pace; a pace the plan has not yet made measurable, one pace): so a car in its start delay
    is about to move, a braking one stops where it will, a slow leader stays slow. A car
    without one goes on at the speed it showed."""
    cars = sorted(now)
    if len(cars) < 2:
        return set()
    plans = plans or {}
    steps = np.linspace(0.0, horizon_s, 5)
    paths = {}
    for car in cars:
        x, y = now[car]
        shown = 0.0  # metres between the last two sightings, and their time apart
        dt = 0.0
        if car in before and car in targets:
            bx, by, dt = before[car]
            shown = math.hypot(x - bx, y - by)
        plan = plans.get(car) if car in targets else None
        if plan is None:
            advance = steps * (shown / dt if dt > 0 else 0.0)
        else:
            then, *covered = plan.covered(t_ns + np.append(-dt, steps) * 1e9)
            planned = covered[0] - then
            pace = min(shown / planned, MAX_PACE) if planned >= PACE_FROM_M else 1.0
            advance = pace * (np.asarray(covered) - covered[0])
        tx, ty = targets.get(car, (x, y))
        left = math.hypot(tx - x, ty - y)
        travel = np.minimum(advance, left)
        share = travel / left if left > 0 else np.zeros_like(steps)
        paths[car] = np.stack([x + share * (tx - x), y + share * (ty - y)], 1)
    stop = set()
    for i, a in enumerate(cars):
        for b in cars[i + 1 :]:
            if not (np.abs(paths[a] - paths[b]) < reach).all(axis=1).any():
                continue
            for car, other in ((a, b), (b, a)):
                here, there = paths[car], paths[other][0]
                if math.dist(here[-1], there) < math.dist(here[0], there):
                    stop.add(car)
    return stop
