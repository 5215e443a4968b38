"""The motor controller mock: executes one grid move at a time in a simulated world.

``Drive`` is the controller's motion logic (a move takes ``cell_time_s``; the pose is updated when
the move ends; a stop cancels the move in progress, so the car stays on its cell). Where a move
ends is decided by a ``World``: the default is a car alone on a 9x9 grid under the shared rules
(``udan.envs.rules``); the HIL world plugs in its own to add other cars and obstacles.

``MotorController`` puts a ``Drive`` behind the serial link (COBS + CRC-16 frames, spec section
9), and ``SerialMotors`` is the ESP8266's end of that link. Both ends read their file descriptor
from the asyncio loop, so a pty pair carries real bytes between them.
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import serial

from udan.envs.rules import ACTION_DELTAS, WAIT, in_bounds
from udan.firmware_mock import serial_link as sl
from udan.firmware_mock.core import Telemetry
from udan.firmware_mock.faults import Faults
from udan.firmware_mock.wire import STOP_ACTION

Pose = tuple[int, int]
BATTERY_FULL_MV = 8200
BATTERY_LOW_MV = 7000
DRAIN_PER_CELL_MV = 2


class World(Protocol):
    """Decides where a move ends; told when a move starts and when one is cut short."""

    def begin(self, car_id: int, pose: Pose, action: int) -> None:
        """A move of ``car_id`` from ``pose`` started (it ends after the cell time)."""
        ...

    def abort(self, car_id: int) -> None:
        """The move in progress was cut (stop, watchdog, estop): the car stays where it was."""
        ...

    def move(self, car_id: int, pose: Pose, action: int) -> Pose:
        """The cell ``car_id`` ends on after ``action`` from ``pose``; called when the move's
        time is up."""
        ...


@dataclass
class GridWorld:
    """A car alone on a ``height`` x ``width`` grid: moves off the edge are waits."""

    height: int = 9
    width: int = 9

    def begin(self, car_id: int, pose: Pose, action: int) -> None:
        """Alone on the grid, nothing to reserve."""

    def abort(self, car_id: int) -> None:
        """Alone on the grid, nothing to release."""

    def move(self, car_id: int, pose: Pose, action: int) -> Pose:
        """The rules' delta for ``action``, unless it leaves the grid."""
        dest = np.asarray(pose, dtype=np.int64) + ACTION_DELTAS[action]
        return (int(dest[0]), int(dest[1])) if in_bounds(dest, self.height, self.width) else pose


class Motors(Protocol):
    """What the firmware drives: the controller itself, or the serial link to it."""

    def move(self, seq: int, action: int) -> None:
        """Start (or queue behind the current move) the move of command ``seq``."""
        ...

    def stop(self, reason: int) -> None:
        """Stop at once, dropping any queued move."""
        ...

    def telemetry(self) -> Telemetry:
        """Pose, battery and motion state as last known."""
        ...


class Drive:
    """Executes moves in a ``World`` with a time per cell; one queued move at most (the newest)."""

    def __init__(
        self,
        car_id: int,
        world: World,
        pose: Pose,
        cell_time_s: float,
        faults: Faults,
        on_change: Callable[[], None] = lambda: None,
    ) -> None:
        self.car_id = car_id
        self.world = world
        self.pose = pose
        self.cell_time_s = cell_time_s
        self.faults = faults
        self.on_change = on_change
        self.battery_mv = BATTERY_FULL_MV
        self.stalled = False
        self.done_seq = 0
        self.executed = 0
        self.aborted = 0
        self.stalls = 0
        self._current: tuple[int, int] | None = None
        self._queued: tuple[int, int] | None = None
        self._timer: asyncio.TimerHandle | None = None

    def telemetry(self) -> Telemetry:
        """The controller's own view (its pose is its odometry, which is exact in the mock)."""
        return Telemetry(
            row=self.pose[0],
            col=self.pose[1],
            battery_mv=self.battery_mv,
            moving=self._current is not None,
            stalled=self.stalled,
            low_battery=self.battery_mv < BATTERY_LOW_MV,
            done_seq=self.done_seq,
        )

    def move(self, seq: int, action: int) -> None:
        """Start the move, or queue it (replacing an older queued one) while another runs."""
        if action == STOP_ACTION:
            self.stop(sl.STOP_COMMAND)
            self.done_seq = seq
            self.on_change()
            return
        if self._current is not None:
            self._queued = (seq, action)
            return
        self._start(seq, action)

    def _start(self, seq: int, action: int) -> None:
        self._current = (seq, action)
        if action == WAIT:
            self._finish()
            return
        self.world.begin(self.car_id, self.pose, action)
        self._timer = asyncio.get_running_loop().call_later(self.cell_time_s, self._finish)
        self.on_change()

    def _finish(self) -> None:
        assert self._current is not None
        seq, action = self._current
        self._current = self._timer = None
        self.stalled = self.faults.stuck_wheel and action != WAIT
        if self.stalled:
            self.stalls += 1
            self.world.abort(self.car_id)
        else:
            if action != WAIT:
                self.pose = self.world.move(self.car_id, self.pose, action)
                self.battery_mv = max(0, self.battery_mv - DRAIN_PER_CELL_MV)
            self.executed += 1
        self.done_seq = seq
        queued, self._queued = self._queued, None
        self.on_change()
        if queued is not None:
            self._start(*queued)

    def stop(self, reason: int) -> None:
        """Cut the motors: the move in progress is abandoned where it started."""
        self._queued = None
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._current is not None:
            self._current = None
            self.aborted += 1
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
                self.drive.move(f["seq"], f["action"])
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
    """The ESP8266's end of the serial line: MOVE/STOP out, STATE in (pyserial on a tty)."""

    def __init__(self, port: serial.Serial, on_change: Callable[[], None] = lambda: None) -> None:
        self.port = port
        self.on_change = on_change
        self.deframer = sl.Deframer()
        self._telemetry = Telemetry()
        asyncio.get_running_loop().add_reader(port.fileno(), self._readable)

    def move(self, seq: int, action: int) -> None:
        """MOVE over the line (a STOP command too, so its seq is reported as done)."""
        self.port.write(sl.frame(sl.encode_message(sl.MOVE, seq=seq, action=action)))

    def stop(self, reason: int) -> None:
        """STOP over the line."""
        self.port.write(sl.frame(sl.encode_message(sl.STOP, reason=reason)))

    def telemetry(self) -> Telemetry:
        """The controller's last STATE report."""
        return self._telemetry

    def _readable(self) -> None:
        data = self.port.read(self.port.in_waiting or 1)
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
        asyncio.get_running_loop().remove_reader(self.port.fileno())
        self.port.close()
