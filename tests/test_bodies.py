"""Real car bodies on the grid: who starts later so bodies never meet at a corner, and which car
the guard stops when one is about to touch another (edge/bodies.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from udan.edge.bodies import CORNER_DELAY, Plan, closing_in, corner_delays, crossing
from udan.edge.core import MotionRules
from udan.edge.geometry import ArenaGeometry
from udan.edge.protocol import Guidance
from udan.firmware_mock.motor import Pose, Trajectory
from udan.hil.motion import LEVELS, bodies_touch

CELL = ArenaGeometry().cell_m
REACH = MotionRules().reach
MS = 1_000_000
FRAME_MS = 25.0
"""The camera's 40 FPS."""
REACTION_MS = 25.0
"""From a frame's capture to its stop taking effect: its analysis (6-13 ms in the HIL's
telemetry on the loaded machine) and the stop's way to the car, with room."""
ACCEL = LEVELS["lab"].accel_share


def test_a_straight_train_starts_a_follow_gap_apart() -> None:
    train = {1: ((0, 0), (0, 1)), 2: ((0, 1), (0, 2)), 3: ((0, 2), (0, 3))}
    delays, waits = corner_delays(train, straight=0.4)
    assert delays == pytest.approx({1: 0.8, 2: 0.4, 3: 0.0}) and waits == set()
    assert corner_delays(train) == ({1: 0.0, 2: 0.0, 3: 0.0}, set())  # no gap: all together


def test_entering_a_cell_left_sideways_waits_for_the_leaver_per_corner_of_the_chain() -> None:
    moves = {
        1: ((0, 1), (0, 2)),  # leaves right
        2: ((1, 1), (0, 1)),  # enters it from below: a corner
        3: ((2, 1), (1, 1)),  # follows car 2 the same way: starts with it
        4: ((1, 0), (1, 1)),  # enters car 2's cell from the left: a second corner
        5: ((5, 5), (5, 5)),  # stays
    }
    delays, waits = corner_delays(moves)
    assert waits == set()
    assert delays == {1: 0.0, 2: CORNER_DELAY, 3: CORNER_DELAY, 4: 2 * CORNER_DELAY, 5: 0.0}
    # a third corner would make the start delay longer than a command can carry: it waits
    delays, waits = corner_delays({**moves, 6: ((1, 2), (1, 1)), 7: ((2, 2), (1, 2))})
    assert 6 in delays and waits == {7}


def test_a_ring_cannot_be_driven_and_whoever_enters_a_ring_cell_waits_too() -> None:
    ring = {1: ((0, 0), (0, 1)), 2: ((0, 1), (1, 1)), 3: ((1, 1), (1, 0)), 4: ((1, 0), (0, 0))}
    delays, waits = corner_delays({**ring, 5: ((2, 1), (1, 1)), 6: ((7, 7), (7, 8))})
    assert waits == {1, 2, 3, 4} | {5} and delays == {6: 0.0}


def test_the_guard_stops_the_car_closing_in_never_the_one_standing() -> None:
    # car 2 stands 12 cm short of its target (6, 0), across (7, 0), where car 1 is going from
    # (8, 0) at 2 m/s
    x = 0.5 * CELL
    now = {1: (x, 7.9 * CELL), 2: (x, 7.5 * CELL - 0.12)}
    before = {1: (x, 7.9 * CELL + 0.05, 0.025)}
    targets = {1: (x, 7.5 * CELL), 2: (x, 6.5 * CELL)}
    assert closing_in(now, before, targets, 0.08, REACH) == {1}
    # the same speed towards a car standing on the next cell's centre: it stops at its target
    now[2] = (x, 6.5 * CELL)
    assert closing_in(now, before, targets, 0.08, REACH) == set()


def test_the_guard_leaves_a_straight_train_and_parallel_lanes_alone_and_stops_a_head_on() -> None:
    x = 0.5 * CELL
    train_now = {1: (x, 7.3 * CELL), 2: (x, 6.3 * CELL)}
    train_before = {c: (px, py + 0.05, 0.025) for c, (px, py) in train_now.items()}
    targets = {1: (x, 6.5 * CELL), 2: (x, 5.5 * CELL)}
    assert closing_in(train_now, train_before, targets, 0.08, REACH) == set()
    lanes_now = {1: (x, 7.3 * CELL), 2: (x + CELL, 7.3 * CELL)}
    lanes_before = {c: (px, py + 0.05, 0.025) for c, (px, py) in lanes_now.items()}
    lanes_targets = {1: (x, 6.5 * CELL), 2: (x + CELL, 6.5 * CELL)}
    assert closing_in(lanes_now, lanes_before, lanes_targets, 0.08, REACH) == set()
    # a bug upstream sends two cars at one cell: both are stopped
    head_on = {1: (x, 7.2 * CELL), 2: (x, 5.8 * CELL)}
    before = {1: (x, 7.2 * CELL + 0.05, 0.025), 2: (x, 5.8 * CELL - 0.05, 0.025)}
    both = {1: (x, 6.5 * CELL), 2: (x, 6.5 * CELL)}
    assert closing_in(head_on, before, both, 0.08, REACH) == {1, 2}


def test_recentring_paths_that_would_sweep_through_each_other_go_one_at_a_time() -> None:
    x = 0.5 * CELL
    # car 3 slipped and stands 13 cm short of (5, 0)'s centre, car 1 stopped behind it: car 3
    # completes its move first (away from car 1); car 1 would drive into it, and waits
    paths = {
        1: ((x, 6.5 * CELL + 0.1), (x, 6.5 * CELL)),
        3: ((x, 5.5 * CELL + 0.13), (x, 5.5 * CELL)),
    }
    assert crossing(paths, {}, REACH) == {1}
    # diagonal neighbours, both 6 cm off towards each other: each moves away from the other
    a, b = (1.5 * CELL + 0.06, 2.5 * CELL + 0.06), (2.5 * CELL - 0.06, 3.5 * CELL - 0.06)
    diagonal = {4: (a, (1.5 * CELL, 2.5 * CELL)), 2: (b, (2.5 * CELL, 3.5 * CELL))}
    assert crossing(diagonal, {}, REACH) == set()
    # side by side in their own lanes: both go; towards a car that stands: it waits
    lanes = {
        1: ((x, 4.4 * CELL), (x, 4.5 * CELL)),
        2: ((x + CELL, 4.6 * CELL), (x + CELL, 4.5 * CELL)),
    }
    assert crossing(lanes, {}, REACH) == set()
    assert crossing({1: ((x, 4.6 * CELL), (x, 4.5 * CELL))}, {7: (x, 3.75 * CELL)}, REACH) == {1}


def _centre(row: int, col: int) -> Pose:
    return Pose((col + 0.5) * CELL, (row + 0.5) * CELL, 0.0)


def _leader_and_follower(
    way: str, cell_ms: float, slip: float, phase_ms: float, motion: MotionRules | None
) -> tuple[bool, bool]:
    """A leader leaving (4, 4) (up, or right: ``way``) and a follower entering it from below,
    on the HIL's speed profile; the leader slips and ends ``slip`` of its move short. The camera
    takes a frame every 25 ms from ``phase_ms``; on each the guard runs as the core runs it
    (the cars still in their moves, their last two sightings, their targets; with ``motion``,
    the moves' plans and its follow gap, else the earlier guard and no gap), and a stop takes
    effect ``REACTION_MS`` later. Whether the bodies touched, and
    whether the follower was stopped."""
    cell_ns = cell_ms * MS
    leader_target = _centre(3, 4) if way == "up" else _centre(4, 5)
    start, follower_start = _centre(4, 4), _centre(5, 4)
    short = Pose(*(start[i] + (1 - slip) * (leader_target[i] - start[i]) for i in range(3)))
    leader = Trajectory(start, short, 0, round(cell_ns), ACCEL)
    moves = {1: ((4, 4), (3, 4) if way == "up" else (4, 5)), 2: ((5, 4), (4, 4))}
    delays, _ = corner_delays(moves, straight=0.0 if motion is None else motion.follow_delay)
    ack_ns = 2 * MS  # the follower's command leaves after the leader's ACK
    begins = ack_ns + round(delays[2] * cell_ns)
    follower = Trajectory(follower_start, start, begins, round(cell_ns), ACCEL)
    plans = {}
    if motion is not None:
        for car, (pose, target, taken, delay) in {
            1: (start, leader_target, 0, delays[1]),
            2: (follower_start, start, ack_ns, delays[2]),
        }.items():
            plans[car] = motion.plan(Guidance(tuple(target), tuple(pose), 0, delay), taken)
    targets = {1: leader_target[:2], 2: start[:2]}
    stopped_at, before = None, {}
    t = (phase_ms - FRAME_MS) * MS  # a frame of both standing first
    end = begins + cell_ns + 50 * MS
    while t < end and stopped_at is None:
        now = {1: leader.at(int(t))[:2], 2: follower.at(int(t))[:2]}
        moving = [c for c, move in ((1, leader), (2, follower)) if t < move.started_ns + cell_ns]
        seen = {c: (*before[c], FRAME_MS / 1000) for c in moving if c in before}
        horizon = (motion or MotionRules()).guard_horizon_s
        live = {c: targets[c] for c in moving}
        if 2 in closing_in(now, seen, live, horizon, REACH, plans, int(t)):
            stopped_at = int(t + REACTION_MS * MS)
        before, t = now, t + FRAME_MS * MS
    times = np.arange(0, end, MS // 2)
    a = np.array([leader.at(int(x)) for x in times])
    b = np.array([follower.at(int(min(x, stopped_at or x))) for x in times])
    return bool(bodies_touch(a, b).any()), stopped_at is not None


PHASES_MS = np.arange(0.0, FRAME_MS, 2.5)


@pytest.mark.parametrize("way", ["right", "up"])
@pytest.mark.parametrize("cell_ms", [60, 100, 200])
def test_a_follower_of_a_leader_that_slipped_short_is_stopped_before_they_touch(
    way: str, cell_ms: int
) -> None:
    """The slow lab test's contacts at cells of 100 ms: a car entering the cell another leaves
    sideways starts a cell time later, the leaver slipped and stands short, the follower comes
    on, and the guard, going by the speeds two frames show, saw it only after the contact.
    With the moves' plans at the pace each car kept (a car in its start delay is about to
    move; a slipping leader stays slow and stops where it will) and straight followers
    starting the follow gap later, no slip of the `rough` level (30-80 % of the move, `lab`'s
    are 20-50 %) at any phase of the camera makes a contact; with the earlier guard and no
    gap, the corners at 100 ms touch."""
    motion = MotionRules(cell_time_s=cell_ms / 1000)
    slips = np.linspace(LEVELS["lab"].slip_loss[0], LEVELS["rough"].slip_loss[1], 7)
    runs = [(s, p) for s in slips for p in PHASES_MS]
    touched = [(s, p) for s, p in runs if _leader_and_follower(way, cell_ms, s, p, motion)[0]]
    assert touched == []
    if way == "right" and cell_ms == 100:
        earlier = [(s, p) for s, p in runs if _leader_and_follower(way, cell_ms, s, p, None)[0]]
        assert len(earlier) > len(runs) // 4


@pytest.mark.parametrize("way", ["right", "up"])
def test_the_guard_leaves_followers_of_leaders_that_did_not_slip_alone(way: str) -> None:
    motion = MotionRules(cell_time_s=0.1)
    for phase in PHASES_MS:
        assert _leader_and_follower(way, 100, 0.0, phase, motion) == (False, False)


def test_a_commanded_move_is_planned_as_the_cars_controller_drives_it() -> None:
    """A cell in a cell time, from when the car took the command plus its start delay; a
    shorter correction in less. A straight follower's start delay is the follow gap."""
    motion = MotionRules(cell_time_s=0.1)
    assert motion.follow_delay == pytest.approx(0.4)
    assert MotionRules(cell_time_s=0.2).follow_delay == pytest.approx(0.2)
    here, there = _centre(5, 4), _centre(4, 4)
    plan = motion.plan(Guidance(tuple(there), tuple(here), 0, 1.5), 7 * MS)
    assert isinstance(plan, Plan) and math.isclose(plan.length_m, CELL)
    assert (plan.begins_ns, plan.duration_ns) == (157 * MS, 100 * MS)
    assert plan.covered(np.array([0, 157 * MS, 207 * MS, 400 * MS])) == pytest.approx(
        [0.0, 0.0, CELL / 2, CELL]
    )
    nudge = Pose(here.x + CELL / 4, here.y, 0.0)
    assert motion.plan(Guidance(tuple(here), tuple(nudge), 0), 0).duration_ns == 50 * MS
    assert motion.plan(Guidance(tuple(here)), 0) is None  # no pose seen: no plan
