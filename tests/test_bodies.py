"""Real car bodies on the grid: who starts later so bodies never meet at a corner, and which car
the guard stops when one is about to touch another (edge/bodies.py)."""

from __future__ import annotations

from udan.edge.bodies import CORNER_DELAY, closing_in, corner_delays, crossing
from udan.edge.core import MotionRules
from udan.edge.geometry import ArenaGeometry

CELL = ArenaGeometry().cell_m
REACH = MotionRules().reach


def test_a_straight_train_starts_together() -> None:
    delays, waits = corner_delays({1: ((0, 0), (0, 1)), 2: ((0, 1), (0, 2)), 3: ((0, 2), (0, 3))})
    assert delays == {1: 0.0, 2: 0.0, 3: 0.0} and waits == set()


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
