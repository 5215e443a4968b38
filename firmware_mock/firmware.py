"""The car firmware's main loop around ``CarCore``, independent of the transport.

It owns what the sans-I/O core cannot: the car clock (microseconds since boot), the timers
(join announcements until the edge answers, status heartbeats, the watchdog), the motors, the
injected faults, and reboots. The UDP ESP8266 mock and the CAN motor controller both run it; the
transport hands it datagrams with ``receive`` and gives it a ``transmit`` to send with.

``seed`` drives the injected link faults only; session nonces come from ``secrets`` in the core,
so two runs with one seed never share a session.
"""

from __future__ import annotations

import asyncio
import logging
import random
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from udan.firmware_mock import serial_link as sl
from udan.firmware_mock import wire
from udan.firmware_mock.core import WATCHDOG_US, CarCore
from udan.firmware_mock.faults import Faults, LossyLink
from udan.firmware_mock.fleet import CarSpec
from udan.firmware_mock.motor import Motors


@dataclass(frozen=True, slots=True)
class CarTiming:
    """A mock car's time constants (spec sections 6 and 8), the same for every transport.

    Defaults are the spec's: a cell in 200 ms, under the 300 ms watchdog so a kept-alive car is
    never cut mid-move; STATUS every 100 ms; JOIN every 250 ms until the edge answers; constant
    speed over a move (``accel_share`` 0; real cars accelerate and brake, see the HIL's motion
    levels).
    """

    cell_time_s: float = 0.2
    watchdog_s: float = WATCHDOG_US / 1e6
    status_period_s: float = 0.1
    join_period_s: float = 0.25
    accel_share: float = 0.0


DEFAULT_TIMING = CarTiming()
log = logging.getLogger(__name__)


class CarFirmware:
    """One car's firmware: protocol core + timers + faults, talking through ``transmit``."""

    def __init__(
        self,
        core: CarCore,
        motors: Motors,
        transmit: Callable[[bytes, Any], None],
        *,
        faults: Faults,
        edge: Any = None,
        timing: CarTiming = DEFAULT_TIMING,
        seed: int | None = None,
    ) -> None:
        self.core = core
        self.motors = motors
        self.faults = faults
        self.configured_edge = edge
        self.edge = edge
        self.status_period_s = timing.status_period_s
        self.join_period_s = timing.join_period_s
        self.dead_dropped = 0
        self.closed = False
        self._rng = random.Random(seed)
        self.inbound = LossyLink(faults, self._on_frame, random.Random(self._rng.getrandbits(64)))
        self.outbound = LossyLink(faults, transmit, random.Random(self._rng.getrandbits(64)))
        self._boot_ns = time.monotonic_ns()
        self._dead_at_ns: int | None = None
        self._timers: dict[str, asyncio.TimerHandle] = {}
        self._versions_logged: set[int] = set()

    @classmethod
    def for_car(
        cls,
        spec: CarSpec,
        motors: Motors,
        transmit: Callable[[bytes, Any], None],
        *,
        faults: Faults,
        edge: Any,
        timing: CarTiming,
        seed: int | None,
    ) -> CarFirmware:
        """The firmware of one fleet car: its core keyed and numbered from ``spec``."""
        core = CarCore(
            spec.car_id,
            spec.key,
            spec.marker,
            watchdog_us=round(timing.watchdog_s * 1e6),
            cell_time_us=round(timing.cell_time_s * 1e6),
        )
        return cls(core, motors, transmit, faults=faults, edge=edge, timing=timing, seed=seed)

    # --- clock and timers ---
    def now_us(self) -> int:
        """The car clock: microseconds since the last boot."""
        return (time.monotonic_ns() - self._boot_ns) // 1000

    def _schedule(self, name: str, delay_s: float, callback: Callable[[], None]) -> None:
        self._cancel(name)
        self._timers[name] = asyncio.get_running_loop().call_later(max(delay_s, 0.0), callback)

    def _cancel(self, name: str) -> None:
        handle = self._timers.pop(name, None)
        if handle is not None:
            handle.cancel()

    def start(self) -> None:
        """Power on: boot, start the heartbeat, arm the configured faults (needs a running loop)."""
        self.apply_faults(
            {"reboot_at_s": self.faults.reboot_at_s, "dead_at_s": self.faults.dead_at_s}
        )
        self._boot()
        self._heartbeat()

    def _boot(self) -> None:
        self._boot_ns = time.monotonic_ns()
        self._cancel("watchdog")
        self.edge = self.configured_edge
        self.motors.stop(sl.STOP_BOOT)
        self._send(self.core.boot(self.now_us()))
        self._schedule("join", self.join_period_s, self._announce)

    def reboot(self) -> None:
        """Power-cycle the car: new session, new clock; the edge has to join it again."""
        self._boot()

    def dead(self) -> bool:
        """The dead-car fault is active: the car neither hears nor answers."""
        return self._dead_at_ns is not None and time.monotonic_ns() >= self._dead_at_ns

    def apply_faults(self, values: Mapping[str, Any]) -> None:
        """Change fault settings at run time; reboot/dead times count from now."""
        self.faults.update(values)
        if "reboot_at_s" in values:
            self._cancel("reboot")
            if self.faults.reboot_at_s is not None:
                self._schedule("reboot", self.faults.reboot_at_s, self.reboot)
        if "dead_at_s" in values:
            at = self.faults.dead_at_s
            self._dead_at_ns = None if at is None else time.monotonic_ns() + int(at * 1e9)

    def _send(self, frame: bytes | None) -> None:
        if frame is not None and self.edge is not None and not self.dead():
            self.outbound.send(frame, self.edge)

    def _announce(self) -> None:
        """JOIN every ``join_period_s`` while the car has no session."""
        if self.core.joined:
            self._timers.pop("join", None)
            return
        self._send(self.core.join(self.now_us()))
        self._schedule("join", self.join_period_s, self._announce)

    def _heartbeat(self) -> None:
        self.send_status()
        self._send(self.core.renewal(self.now_us()))
        if not self.core.joined and "join" not in self._timers:  # its counter ran out
            self._announce()
        self._schedule("status", self.status_period_s, self._heartbeat)

    def send_status(self) -> None:
        """A STATUS frame now, if an edge has joined this car."""
        if self.core.joined:
            self._send(self.core.status(self.now_us(), self.motors.telemetry()))

    def _watchdog(self) -> None:
        wake = self.core.next_wakeup_us()
        if self.core.poll(self.now_us()):
            self.motors.stop(sl.STOP_WATCHDOG)
            self.send_status()
        elif wake is not None:
            self._schedule("watchdog", (wake - self.now_us()) / 1e6, self._watchdog)

    # --- frames in ---
    def receive(self, data: bytes, addr: Any) -> None:
        """A datagram from the transport (goes through the link faults first)."""
        self.inbound.send(data, addr)

    def _on_frame(self, data: bytes, addr: Any) -> None:
        if self.closed:  # a datagram the link held back (delay fault) arriving after power-off
            return
        if self.dead():
            self.dead_dropped += 1
            return
        out = self.core.handle(data, self.now_us())
        if out.verdict in ("accepted", "joined"):
            self.edge = addr
        elif out.verdict == "wrong_version" and data[0] not in self._versions_logged:
            self._versions_logged.add(data[0])
            log.warning(
                "car %d: a protocol v%d frame refused, this firmware speaks v%d",
                self.core.car_id,
                data[0],
                wire.VERSION,
            )
        for reply in out.replies:  # before the motors report, so frames leave in seq order
            self.outbound.send(reply, addr)
        if out.verdict == "joined":
            self.send_status()  # the first frame of the new session confirms it to the edge
        if out.halt:
            self.motors.stop(sl.STOP_ESTOP)
        if out.motor is not None:
            self.motors.move(*out.motor, out.guidance)
            wake = self.core.next_wakeup_us()
            if wake is not None:
                self._schedule("watchdog", (wake - self.now_us()) / 1e6, self._watchdog)

    def close(self) -> None:
        """Shut down: say LEAVE to the edge (if joined and alive), stop the motors and timers."""
        leave = self.core.leave(self.now_us(), 0)
        if leave is not None and self.edge is not None and not self.dead():
            self.outbound.deliver(leave, self.edge)
        self.motors.stop(sl.STOP_BOOT)
        self.closed = True
        for name in list(self._timers):
            self._cancel(name)

    def counters(self) -> dict[str, Any]:
        """Core counters plus what the link faults did."""
        out = self.core.counters.as_dict()
        out["dead_dropped"] = self.dead_dropped
        out["link_in"] = vars(self.inbound.stats).copy()
        out["link_out"] = vars(self.outbound.stats).copy()
        return out
