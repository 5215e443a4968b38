"""Cars that move like real cars, without sockets: the HIL's motion model against the figures
docs/motion.md gives for each level, the car's controller converging from a displaced pose on
the pose the camera feeds back (and drifting without it), level 0 being the earlier exact grid,
and an e-stop mid-move leaving the car where it stopped."""

from __future__ import annotations

import asyncio
import math
import time

import numpy as np
import pytest

from udan.edge.geometry import ArenaGeometry
from udan.envs.errors import EnvConfigError
from udan.envs.rules import ACTION_DELTAS, DOWN, LEFT, RIGHT, UP, WAIT
from udan.firmware_mock import wire
from udan.firmware_mock.faults import Faults
from udan.firmware_mock.motor import DEADBAND_M, Drive, Pose, Trajectory
from udan.hil.motion import (
    LEVELS,
    CarMotion,
    bodies_touch,
    may_meet,
    may_touch,
    motion_level,
    poses_at,
    reach_box,
)
from udan.hil.world import HilWorld
from udan.profile import travelled

GEOMETRY = ArenaGeometry()
CELL = GEOMETRY.cell_m
MOVES = 4000


def _centre(cell: tuple[int, int]) -> Pose:
    return Pose(*GEOMETRY.cell_centre(*cell), 0.0)


def _errors(level: str, car: int, action: int) -> np.ndarray:
    """``MOVES`` grid moves of one car from (4, 4) -> (along, across, heading) errors, in the
    car's frame of the move (metres, metres, radians)."""
    motion = CarMotion(LEVELS[level], seed=7, car_id=car, cell_m=CELL)
    start = _centre((4, 4))
    d_row, d_col = ACTION_DELTAS[action]
    end = _centre((4 + int(d_row), 4 + int(d_col)))
    plan = Trajectory(start, end, 0, 1)
    ux, uy = (end.x - start.x) / CELL, (end.y - start.y) / CELL
    out = []
    for _ in range(MOVES):
        true = motion.true_end(start, plan)
        dx, dy = true.x - end.x, true.y - end.y
        out.append((dx * ux + dy * uy, -dx * uy + dy * ux, true.heading))
    return np.array(out)


@pytest.mark.parametrize("level", ["low", "lab", "rough"])
def test_the_motion_model_makes_the_errors_its_level_documents(level: str) -> None:
    """Per move, within one car: the spread of the distance driven forwards is the scale error
    (slips aside), sideways it is short by the roller loss, the cross-track and heading drift
    have their spread; slips come as often as documented; across cars the systematic biases
    have theirs."""
    lv = LEVELS[level]
    ahead = _errors(level, 1, UP)
    sideways = _errors(level, 1, RIGHT)
    slipped = (
        ahead[:, 0] < -lv.slip_loss[0] * CELL * 0.9 if lv.slip_probability else ahead[:, 0] < -1
    )
    clean = ahead[~slipped]
    assert np.std(clean[:, 0]) / CELL == pytest.approx(lv.scale_sd, rel=0.1)
    assert np.std(clean[:, 1]) / CELL == pytest.approx(lv.drift_sd, rel=0.1)
    assert np.degrees(np.std(clean[:, 2])) == pytest.approx(lv.heading_sd_deg, rel=0.1)
    rate = slipped.mean()
    sd = math.sqrt(max(lv.slip_probability, 1e-4) * (1 - lv.slip_probability) / MOVES)
    assert abs(rate - lv.slip_probability) < 4 * sd
    if lv.slip_probability:
        losses = -ahead[slipped, 0] / CELL
        assert lv.slip_loss[0] * 0.85 < losses.min() and losses.max() < lv.slip_loss[1] * 1.15
    clean_side = sideways[sideways[:, 0] > -max(lv.slip_loss[0], 1) * CELL * 0.9]
    if lv.slip_probability:
        clean_side = sideways[sideways[:, 0] > -lv.slip_loss[0] * CELL * 0.9]
    shortfall = -np.mean(clean_side[:, 0]) / CELL
    bias = CarMotion(lv, 7, 1, CELL).scale_bias
    assert shortfall == pytest.approx(lv.strafe_loss - bias, abs=0.15 * lv.strafe_loss + 0.002)
    # never longer than the scale error allows: rollers and slips only shorten a move
    assert np.max(ahead[:, 0]) / CELL < bias + 4.5 * lv.scale_sd
    biases = np.array([CarMotion(lv, 7, car, CELL).scale_bias for car in range(1, 801)])
    assert np.std(biases) == pytest.approx(lv.scale_bias, rel=0.1)


def test_level_0_is_the_exact_grid_the_earlier_world_drew() -> None:
    """At level 0 a move ends exactly on its target cell's centre, and while it runs the camera
    draws the car where the earlier world did: start + f (end - start), f the share of the
    cell time gone, heading 0, to the last bit."""
    world = HilWorld(GEOMETRY, {1: 10})
    world.place(np.zeros((9, 9), np.uint8), {1: (2, 3)})
    t0 = time.monotonic_ns()
    plan = Trajectory(_centre((2, 3)), _centre((2, 4))._replace(x=1.4 + 1e-4), t0, 200_000_000)
    world.begin(1, plan)
    for ms in (0, 37, 100, 163, 200, 250):
        now = t0 + ms * 1_000_000
        (_, x, y, heading), *_ = world.snapshot(now)[0]
        f = min(max((now - t0) / 200_000_000, 0.0), 1.0)
        (x0, y0), (x1, y1) = GEOMETRY.cell_centre(2, 3), GEOMETRY.cell_centre(2, 4)
        assert (x, y, heading) == (x0 + f * (x1 - x0), y0 + f * (y1 - y0), 0.0)
    assert world.end(1)
    assert world.pose[1] == (*GEOMETRY.cell_centre(2, 4), 0.0)


def test_an_unknown_motion_level_is_one_line() -> None:
    with pytest.raises(EnvConfigError, match=r"unknown motion level 'bumpy' .*0, low, lab, rough"):
        motion_level("bumpy")


def test_bodies_touch_as_squares_of_the_rendered_size() -> None:
    assert bodies_touch([0, 0, 0], [0.21, 0, 0]) and not bodies_touch([0, 0, 0], [0.23, 0, 0])
    assert bodies_touch([0, 0, 0], [0.23, 0, math.pi / 4])  # a corner turned towards it
    assert not bodies_touch([0, 0, 0], [CELL, CELL, 0.1])  # diagonal neighbours never do


def test_the_speed_profile_accelerates_cruises_and_brakes() -> None:
    share = travelled(np.linspace(0, 1, 9), 0.25)
    assert share[0] == 0 and share[-1] == 1 and np.all(np.diff(share) > 0)
    speeds = np.diff(share)
    assert speeds[0] < speeds[3] == pytest.approx(speeds[4]) and speeds[-1] < speeds[4]


async def _drive(level: str, feedback: bool, moves: int, start: Pose) -> list[float]:
    """One car in a world of ``level``, displaced to ``start``, driven back and forth between
    (4, 4) and (4, 5) with each command's target; with ``feedback`` the command also carries
    the true pose (a perfect camera). The distance from the target after every move."""
    world = HilWorld(GEOMETRY, {1: 10}, LEVELS[level], seed=3)
    world.place(np.zeros((9, 9), np.uint8), {1: (4, 4)})
    world.pose[1] = start
    drive = Drive(1, world, (4, 4), 0.004, Faults(), accel_share=LEVELS[level].accel_share)
    errors = []
    cell = (4, 4)
    for seq in range(1, moves + 1):
        action = RIGHT if cell == (4, 4) else LEFT
        cell = (4, 5) if action == RIGHT else (4, 4)
        target = _centre(cell)
        pose = world.pose[1] if feedback else None
        drive.move(seq, action, wire.Guidance(target, pose, 0))
        while drive.done_seq != seq:
            await asyncio.sleep(0.001)
        true = world.pose[1]
        errors.append(math.hypot(true.x - target.x, true.y - target.y))
    return errors


async def test_the_cars_controller_converges_from_a_displaced_pose_on_the_fed_back_pose() -> None:
    """Put 9 cm and 12 degrees off: with its pose in every command the car is back within the
    settling tolerance after its first move, and each move then ends off by that move's own
    error only (a slip now and then: the edge re-centres those), the same in the last 40 moves
    as in the first 40; without it the car never learns it was displaced, and the errors of
    its moves add up."""
    start = Pose(1.4 + 0.06, 1.4 - 0.07, math.radians(12))
    with_pose = await _drive("lab", True, 120, start)
    assert with_pose[0] < 0.03 and np.percentile(with_pose, 90) < 0.03
    first, last = np.median(with_pose[:40]), np.median(with_pose[-40:])
    assert last < 1.5 * first + 0.002
    blind = await _drive("lab", False, 120, start)
    assert np.median(blind[-40:]) > 2 * np.median(blind[:40])  # its errors add up
    assert np.median(blind[-40:]) > 5 * last


async def test_level_0_with_a_noisy_camera_drives_exactly_the_grid() -> None:
    """The camera's noise (a few millimetres, a degree) is within the controller's deadband:
    an exact car fed noisy poses still drives exactly one cell per move."""
    world = HilWorld(GEOMETRY, {1: 10})
    world.place(np.zeros((9, 9), np.uint8), {1: (4, 4)})
    drive = Drive(1, world, (4, 4), 0.004, Faults())
    rng = np.random.default_rng(0)
    cell = (4, 4)
    for seq, action in enumerate([UP, RIGHT, DOWN, LEFT, WAIT] * 8, start=1):
        d_row, d_col = ACTION_DELTAS[action]
        cell = (cell[0] + int(d_row), cell[1] + int(d_col))
        noise = rng.uniform(-1, 1, 3) * (DEADBAND_M * 0.5, DEADBAND_M * 0.5, 0.01)
        seen = tuple(np.add(world.pose[1], noise))
        drive.move(seq, action, wire.Guidance(_centre(cell), seen, 0))
        while drive.done_seq != seq:
            await asyncio.sleep(0.001)
        assert world.pose[1] == _centre(cell) and drive.corrections == 0


async def test_an_estop_mid_move_leaves_the_car_where_it_stopped_until_it_is_released() -> None:
    """Stopped half-way between (4, 4) and (4, 5), the car stands between the cells; commands
    refused while the stop is latched (the protocol core's part) never reach the motors, so
    nothing moves it; after the release its next command drives it from where it is to its
    target."""
    world = HilWorld(GEOMETRY, {1: 10}, LEVELS["low"], seed=1)
    world.place(np.zeros((9, 9), np.uint8), {1: (4, 4)})
    drive = Drive(1, world, (4, 4), 0.2, Faults(), accel_share=0.25)
    drive.move(1, RIGHT, wire.Guidance(_centre((4, 5)), world.pose[1], 0))
    await asyncio.sleep(0.1)
    drive.stop(2)  # what the firmware does on an ESTOP engage
    stopped = world.pose[1]
    assert drive.done_seq == 1 and world.counts["aborted"] == 1
    assert 0.3 * CELL < stopped.x - _centre((4, 4)).x < 0.7 * CELL  # across the border
    await asyncio.sleep(0.3)
    assert world.pose[1] == stopped and 1 not in world.motion
    drive.move(2, WAIT, wire.Guidance(_centre((4, 5)), stopped, 0))  # after the release
    while drive.done_seq != 2:
        await asyncio.sleep(0.005)
    assert math.dist(world.pose[1][:2], _centre((4, 5))[:2]) < 0.02


def test_two_collisions_in_one_sweep_are_each_counted_once() -> None:
    """Two pairs of cars that touch between the same two events: both contacts are counted
    and recorded with where the bodies were, and touching on is not counted again."""
    world = HilWorld(GEOMETRY, {1: 10, 2: 11, 3: 12, 4: 13})
    world.place(np.zeros((9, 9), np.uint8), {1: (2, 2), 2: (2, 3), 3: (5, 2), 4: (5, 3)})
    t0 = time.monotonic_ns()
    for car, row in ((1, 2), (3, 5)):
        world.begin(car, Trajectory(_centre((row, 2)), _centre((row, 3)), t0, 100_000_000))
    time.sleep(0.15)
    world.abort(1)
    world.abort(3)
    assert world.counts["collisions"] == 2
    assert sorted(c[1:3] for c in world.contacts) == [[1, 2], [3, 4]]
    assert all(len(c) == 9 for c in world.contacts)


def test_pairs_the_sweep_skips_never_come_close_enough_to_touch() -> None:
    """The contact sweep samples only pairs :func:`may_meet` lets through: over 3,000 random
    pairs of moves and rests (neighbouring cells, diagonals, accelerating profiles, windows
    that begin before a move and end after it) none it skips is ever close enough to touch
    (:func:`may_touch`) at a sampled instant, and it skips most pairs of cars a cell or more
    apart."""
    rng = np.random.default_rng(7)
    skipped = 0
    for _ in range(3000):
        t0 = 1_000_000_000
        since = t0 + int(rng.integers(-50, 150)) * 1_000_000
        now = since + int(rng.integers(1, 250)) * 1_000_000
        times = np.append(np.arange(since + 5_000_000, now, 5_000_000), now)
        boxes, paths = [], []
        for _car in range(2):
            start = _centre((int(rng.integers(3, 6)), int(rng.integers(3, 6))))
            start = start._replace(heading=float(rng.uniform(-math.pi, math.pi)))
            if rng.random() < 0.7:
                d_row, d_col = ACTION_DELTAS[int(rng.integers(0, 4))]
                end = Pose(start.x + d_col * CELL, start.y + d_row * CELL, start.heading)
                move = Trajectory(start, end, t0, 200_000_000, float(rng.choice([0.0, 0.25])))
                paths.append(poses_at(move, times))
            else:
                move = None
                paths.append(np.broadcast_to(np.asarray(start), (len(times), 3)))
            boxes.append(reach_box(move, start, since, now))
        if not may_meet(*boxes):
            skipped += 1
            assert not may_touch(paths[0], paths[1]).any()
    assert skipped > 1000
