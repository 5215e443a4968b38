"""The motor controller mock: drives one move at a time, from where it believes it is to where
the edge wants it, in a simulated world.

``Drive`` is the controller's motion logic. It keeps a belief of its pose (arena metres and
radians: its odometry) and, for each command, plans a straight move from that belief to the
command's target over a trapezoidal speed profile: a cell in ``cell_time_s``, a shorter
correction in less (spec section 8). A command that carries the car's measured pose (the
camera's, with that frame's age) first corrects the belief at the time the frame was taken, so
its move starts from where the car really is and errors do not add up; corrections smaller than
the controller's deadband are not driven (encoder resolution and camera noise), so an exact car
drives exactly the grid moves. A command without a target drives the action's grid move from
the belief (protocol section 3). A stop cancels the move in progress where the car is.

Where a move really ends is the ``World``'s: the default is a car alone on a 9x9 grid that goes
exactly where it is told (a move off the grid is a wait); the HIL world plugs in its own, with
the other cars, the obstacles and a motion model that makes real cars' errors.

``MotorController`` puts a ``Drive`` behind the serial link (COBS + CRC-16 frames, spec section
9), and ``SerialMotors`` is the ESP8266's end of that link. Both ends read their file descriptor
from the asyncio loop, so a pty pair carries real bytes between them.
"""

from __future__ import annotations

import asyncio
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import NamedTuple, Protocol

import serial

from udan.envs.rules import ACTION_DELTAS, WAIT
from udan.firmware_mock import serial_link as sl
from udan.firmware_mock import wire
from udan.firmware_mock.core import Telemetry
from udan.firmware_mock.faults import Faults
from udan.firmware_mock.wire import STOP_ACTION
from udan.profile import move_span, travelled

Cell = tuple[int, int]
BATTERY_FULL_MV = 8200
BATTERY_LOW_MV = 7000
DRAIN_PER_CELL_MV = 2
DEADBAND_M = 0.005
"""Belief corrections and move corrections smaller than this are not driven (metres): the
camera's position noise (2.5 mm at most in the HIL) is not chased."""
DEADBAND_RAD = math.radians(3.0)
"""... nor heading corrections smaller than this (the camera's heading noise: 0.4 degrees
median, 2.8 at the 99th percentile, 3.5 at most on the HIL's 12 cm markers)."""
QUARTER_TURN_CELLS = 1.0
"""A quarter turn takes as long as a cell's move."""


class Pose(NamedTuple):
    """Arena metres (x along the columns, y along the rows) and heading (radians, 0 facing -y,
    clockwise), as the camera and the protocol give them."""

    x: float
    y: float
    heading: float

    def shifted(self, dx: float, dy: float, dh: float) -> Pose:
        return Pose(self.x + dx, self.y + dy, self.heading + dh)


def wrap(angle: float) -> float:
    """An angle in -pi..pi."""
    return math.remainder(angle, math.tau)


@dataclass(frozen=True, slots=True)
class Trajectory:
    """A straight move from ``start`` to ``end`` begun at ``started_ns`` (``time.monotonic_ns``,
    one clock for every process of the machine), lasting ``duration_ns`` on the speed profile
    of ``accel_share``: the controller's plan in its belief, or the world's truth."""

    start: Pose
    end: Pose
    started_ns: int
    duration_ns: int
    accel_share: float = 0.0

    def at(self, now_ns: int) -> Pose:
        """Where the move is at ``now_ns`` (the start before it, the end after it)."""
        f = float(travelled((now_ns - self.started_ns) / self.duration_ns, self.accel_share))
        (x0, y0, h0), (x1, y1, h1) = self.start, self.end
        return Pose(x0 + f * (x1 - x0), y0 + f * (y1 - y0), h0 + f * wrap(h1 - h0))

    def shifted(self, dx: float, dy: float, dh: float) -> Trajectory:
        return replace(self, start=self.start.shifted(dx, dy, dh), end=self.end.shifted(dx, dy, dh))


class World(Protocol):
    """Where the car really is: told when a move starts, when its time is up, and when one is
    cut short."""

    cell_m: float
    """Side of a grid cell (metres): what a grid move drives."""

    def begin(self, car_id: int, plan: Trajectory) -> None:
        """The car started driving ``plan`` (its own belief of the move)."""
        ...

    def abort(self, car_id: int) -> None:
        """The move in progress was cut (stop, watchdog, estop): the car stays where it is."""
        ...

    def end(self, car_id: int) -> bool:
        """The move's time is up: True if it happened, False if the arena's rules refused it
        (the car is back where it started)."""
        ...


@dataclass
class GridWorld:
    """A car alone on a ``height`` x ``width`` grid that goes exactly where it is told; a move
    off the grid does not happen."""

    height: int = 9
    width: int = 9
    cell_m: float = 2.8 / 9
    _ends: dict[int, Pose] = field(default_factory=dict, repr=False)

    def begin(self, car_id: int, plan: Trajectory) -> None:
        """Remember where the move goes."""
        self._ends[car_id] = plan.end

    def abort(self, car_id: int) -> None:
        """Forget the move."""
        self._ends.pop(car_id, None)

    def end(self, car_id: int) -> bool:
        """Whether the move ends on the grid."""
        end = self._ends.pop(car_id)
        row, col = math.floor(end.y / self.cell_m), math.floor(end.x / self.cell_m)
        return 0 <= row < self.height and 0 <= col < self.width


class Motors(Protocol):
    """What the firmware drives: the controller itself, or the serial link to it."""

    def move(self, seq: int, action: int, guidance: wire.Guidance | None = None) -> None:
        """Start (or queue behind the current move) the move of command ``seq``; its target
        and measured pose (the pose's age counted to now) if the command carried them."""
        ...

    def stop(self, reason: int) -> None:
        """Stop at once, dropping any queued move."""
        ...

    def telemetry(self) -> Telemetry:
        """Pose, battery and motion state as last known."""
        ...


@dataclass(slots=True)
class _Order:
    seq: int
    action: int
    target: Pose | None
    delay: float = 0.0  # start this share of a cell time after the order starts


class Drive:
    """Executes moves in a ``World``: one at a time, one queued at most (the newest).

    ``accel_share`` is the speed profile the controller drives (0: constant speed)."""

    def __init__(
        self,
        car_id: int,
        world: World,
        start: Cell,
        cell_time_s: float,
        faults: Faults,
        on_change: Callable[[], None] = lambda: None,
        *,
        accel_share: float = 0.0,
    ) -> None:
        self.car_id = car_id
        self.world = world
        self.cell_m = world.cell_m
        self.belief = Pose((start[1] + 0.5) * self.cell_m, (start[0] + 0.5) * self.cell_m, 0.0)
        """Where the controller believes it is at rest (the start of the move in progress)."""
        self.cell_time_s = cell_time_s
        self.accel_share = accel_share
        self.faults = faults
        self.on_change = on_change
        self.battery_mv = BATTERY_FULL_MV
        self.stalled = False
        self.done_seq = 0
        self.executed = 0
        self.aborted = 0
        self.stalls = 0
        self.corrections = 0
        """Commands whose measured pose moved the belief (past the deadband)."""
        self._current: _Order | None = None
        self._plan: Trajectory | None = None
        self._queued: _Order | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._cut_at: float | None = None
        self._stuck = False  # the move in progress does not happen (a stuck wheel)

    @property
    def pose(self) -> Cell:
        """The cell the controller believes it is in (at the start of a move in progress)."""
        return math.floor(self.belief.y / self.cell_m), math.floor(self.belief.x / self.cell_m)

    def telemetry(self) -> Telemetry:
        """The controller's own view: its believed cell, battery, motion."""
        row, col = self.pose
        return Telemetry(
            row=row,
            col=col,
            battery_mv=self.battery_mv,
            moving=self._current is not None,
            stalled=self.stalled,
            low_battery=self.battery_mv < BATTERY_LOW_MV,
            done_seq=self.done_seq,
        )

    def believed_at(self, t_ns: int) -> Pose:
        """Where the controller believes it was at ``t_ns`` (on the move in progress, or at
        rest before it)."""
        plan = self._plan
        return self.belief if plan is None or t_ns <= plan.started_ns else plan.at(t_ns)

    def move(self, seq: int, action: int, guidance: wire.Guidance | None = None) -> None:
        """Correct the belief with the command's measured pose, then start the move, or queue
        it (replacing an older queued one) while another runs."""
        if action == STOP_ACTION:
            self.stop(sl.STOP_COMMAND)
            self.done_seq = seq
            self.on_change()
            return
        order = _Order(seq, action, None)
        if guidance is not None:
            if guidance.pose is not None:
                now = time.monotonic_ns()
                self._correct(Pose(*guidance.pose), now - guidance.pose_age_us * 1000)
            if guidance.target is not None:
                order.target = Pose(*guidance.target)
            order.delay = guidance.delay
        if self._current is not None:
            self._queued = order
            return
        self._start(order)

    def cut_next_move(self, share: float) -> None:
        """Test hook (the HIL's ``cut`` fault): the next move stops after ``share`` of its time,
        where the car then is, as a wheel blocked for a moment would leave it."""
        self._cut_at = share

    def _correct(self, measured: Pose, taken_ns: int) -> None:
        """Shift the belief by how far the camera saw it off when the frame was taken."""
        then = self.believed_at(taken_ns)
        dx, dy = measured.x - then.x, measured.y - then.y
        dh = wrap(measured.heading - then.heading)
        if math.hypot(dx, dy) <= DEADBAND_M and abs(dh) <= DEADBAND_RAD:
            return
        self.corrections += 1
        self.belief = self.belief.shifted(dx, dy, dh)
        if self._plan is not None:
            self._plan = self._plan.shifted(dx, dy, dh)

    def _plan_for(self, order: _Order, now_ns: int) -> Trajectory | None:
        """The move from the belief to the order's target (or its grid move), starting after
        the order's delay, or None when there is nothing to drive. A target within the deadband
        of the grid move drives the grid move itself, in exactly one cell time."""
        here = self.belief
        now_ns += round(order.delay * self.cell_time_s * 1e9)
        d_row, d_col = (int(v) for v in ACTION_DELTAS[order.action])
        grid = Pose(here.x + d_col * self.cell_m, here.y + d_row * self.cell_m, here.heading)
        end = grid if order.target is None else order.target
        off = math.hypot(end.x - grid.x, end.y - grid.y)
        if off <= DEADBAND_M and abs(wrap(end.heading - grid.heading)) <= DEADBAND_RAD:
            if order.action == WAIT:
                return None
            return Trajectory(here, grid, now_ns, round(self.cell_time_s * 1e9), self.accel_share)
        cells = math.hypot(end.x - here.x, end.y - here.y) / self.cell_m
        turns = abs(wrap(end.heading - here.heading)) / (math.pi / 2) * QUARTER_TURN_CELLS
        span = move_span(cells, turns)
        return Trajectory(here, end, now_ns, round(self.cell_time_s * span * 1e9), self.accel_share)

    def _start(self, order: _Order) -> None:
        self._current = order
        plan = self._plan_for(order, time.monotonic_ns())
        if plan is None:
            self._finish()
            return
        self._plan = plan
        self._stuck = self.faults.stuck_wheel
        if not self._stuck:
            self.world.begin(self.car_id, plan)
        loop = asyncio.get_running_loop()
        share, self._cut_at = self._cut_at, None
        delay_s = order.delay * self.cell_time_s
        if share is None:
            self._timer = loop.call_later(delay_s + plan.duration_ns / 1e9, self._finish)
        else:
            cut_s = delay_s + share * plan.duration_ns / 1e9
            self._timer = loop.call_later(cut_s, self._finish, True)
        self.on_change()

    def _finish(self, cut: bool = False) -> None:
        order, plan = self._current, self._plan
        assert order is not None
        self._current = self._plan = self._timer = None
        self.stalled = plan is not None and (self._stuck or cut)
        if plan is None:
            self.executed += 1
        elif self._stuck:
            self.stalls += 1
        elif cut:
            self.stalls += 1
            self.belief = plan.at(time.monotonic_ns())
            self.world.abort(self.car_id)
        else:
            moved = self.world.end(self.car_id)
            self.belief = plan.end if moved else plan.start
            if moved and order.action != WAIT:
                self.battery_mv = max(0, self.battery_mv - DRAIN_PER_CELL_MV)
            self.executed += 1
        self.done_seq = order.seq
        queued, self._queued = self._queued, None
        self.on_change()
        if queued is not None:
            self._start(queued)

    def stop(self, reason: int) -> None:
        """Cut the motors: the move in progress ends where the car is, the queued one is
        dropped; both count as done (neither will run)."""
        queued, self._queued = self._queued, None
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        order, plan = self._current, self._plan
        if order is None:
            return
        self._current = self._plan = None
        self.done_seq = (queued or order).seq
        if plan is not None:
            self.aborted += 1
            if not self._stuck:
                self.belief = plan.at(time.monotonic_ns())
                self.world.abort(self.car_id)
        self.on_change()


class MotorController:
    """A ``Drive`` listening on its end of the serial line and reporting STATE after each change."""

    def __init__(self, fd: int, drive: Drive) -> None:
        self.fd = fd
        self.drive = drive
        self.deframer = sl.Deframer()
        drive.on_change = self._report
        os.set_blocking(fd, False)
        asyncio.get_running_loop().add_reader(fd, self._readable)

    def _readable(self) -> None:
        try:
            data = os.read(self.fd, 4096)
        except (BlockingIOError, OSError):
            return
        for kind, f in self.deframer.messages(data, (sl.MOVE, sl.STOP)):
            if kind == sl.MOVE:
                self.drive.move(f["seq"], f["action"], wire.guidance(f))
            else:
                self.drive.stop(f["reason"])

    def _report(self) -> None:
        t = self.drive.telemetry()
        flags = (
            (sl.STATE_MOVING if t.moving else 0)
            | (sl.STATE_STALL if t.stalled else 0)
            | (sl.STATE_LOW_BATTERY if t.low_battery else 0)
        )
        body = sl.encode_message(
            sl.STATE,
            row=t.row,
            col=t.col,
            battery_mv=t.battery_mv,
            flags=flags,
            done_seq=t.done_seq,
        )
        os.write(self.fd, sl.frame(body))

    def close(self) -> None:
        """Stop listening and stop the motors."""
        self.drive.stop(sl.STOP_BOOT)
        asyncio.get_running_loop().remove_reader(self.fd)


class SerialMotors:
    """The ESP8266's end of the serial line: MOVE/STOP out, STATE in (pyserial on a tty).

    When the controller's end is gone (its process ended: the pty hangs up), the line is
    quiet from then on, as a UART whose peer lost power: nothing comes in, what goes out is lost.
    """

    def __init__(self, port: serial.Serial, on_change: Callable[[], None] = lambda: None) -> None:
        self.port = port
        self.on_change = on_change
        self.deframer = sl.Deframer()
        self.hung_up = False
        self._telemetry = Telemetry()
        asyncio.get_running_loop().add_reader(port.fileno(), self._readable)

    def move(self, seq: int, action: int, guidance: wire.Guidance | None = None) -> None:
        """MOVE over the line (a STOP command too, so its seq is reported as done), with the
        command's target and measured pose."""
        fields = wire.guide_payload(guidance)
        self._write(sl.frame(sl.encode_message(sl.MOVE, seq=seq, action=action, **fields)))

    def stop(self, reason: int) -> None:
        """STOP over the line."""
        self._write(sl.frame(sl.encode_message(sl.STOP, reason=reason)))

    def _write(self, data: bytes) -> None:
        if self.hung_up:
            return
        try:
            self.port.write(data)
        except (serial.SerialException, OSError):
            self._hang_up()

    def _hang_up(self) -> None:
        self.hung_up = True
        asyncio.get_running_loop().remove_reader(self.port.fileno())

    def telemetry(self) -> Telemetry:
        """The controller's last STATE report."""
        return self._telemetry

    def _readable(self) -> None:
        try:
            data = self.port.read(self.port.in_waiting or 1)
        except (serial.SerialException, OSError):
            self._hang_up()
            return
        for _, f in self.deframer.messages(data, (sl.STATE,)):
            self._telemetry = Telemetry(
                row=f["row"],
                col=f["col"],
                battery_mv=f["battery_mv"],
                moving=bool(f["flags"] & sl.STATE_MOVING),
                stalled=bool(f["flags"] & sl.STATE_STALL),
                low_battery=bool(f["flags"] & sl.STATE_LOW_BATTERY),
                done_seq=f["done_seq"],
            )
            self.on_change()

    def close(self) -> None:
        """Stop listening and close the port."""
        if not self.hung_up:
            asyncio.get_running_loop().remove_reader(self.port.fileno())
        self.port.close()
