"""The WiFi car: an ESP8266 mock on a UDP socket, wired by a real pty to a motor controller mock.

Datagram in -> ``CarFirmware`` (tag, session, sequence, deadline) -> MOVE over the serial line
(COBS + CRC-16 through an ``os.openpty()`` pair, the ESP8266 end opened by name with pyserial)
-> the motor controller executes it in its ``World`` and reports STATE back over the line.

The two halves are classes of their own, ``EspCar`` and ``MotorEnd``, because on a real car
they are two chips: the HIL rig runs every car's ESP8266 in one process and the motor
controllers beside the world in another (``udan.hil.esp``), so a car's radio never waits for
another car's motors. ``MockCar`` is both halves in one process.
"""

from __future__ import annotations

import asyncio
import os
import tty
from typing import Any

import serial

from udan.firmware_mock.faults import Faults
from udan.firmware_mock.firmware import DEFAULT_TIMING, CarFirmware, CarTiming
from udan.firmware_mock.fleet import CarSpec
from udan.firmware_mock.motor import Drive, GridWorld, MotorController, SerialMotors, World

BAUD = 921_600
SERIAL_COUNTERS = ("serial_bad_frames", "serial_bad_messages")
"""Counted at both ends of a car's serial line; a car's count is their sum."""


class MotorEnd:
    """The motor controller half of one car: its ``Drive`` in ``world`` on the master end of a
    pty whose other end, the ESP8266's, is opened by its name ``tty_path`` (in this process or
    another). Needs a running loop."""

    def __init__(self, spec: CarSpec, world: World, timing: CarTiming, faults: Faults) -> None:
        master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo of STATE back to the controller before the ESP opens it
        self.tty_path = os.ttyname(self._slave)
        self.faults = faults
        drive = Drive(
            spec.car_id, world, spec.start, timing.cell_time_s, faults,
            accel_share=timing.accel_share,
        )  # fmt: skip
        self.controller = MotorController(master, drive)

    def counters(self) -> dict[str, int]:
        """Moves executed, cut short and stalled; bad frames at this end of the line."""
        drive, deframer = self.controller.drive, self.controller.deframer
        return {
            "executed": drive.executed,
            "aborted": drive.aborted,
            "stalls": drive.stalls,
            "serial_bad_frames": deframer.bad_frames,
            "serial_bad_messages": deframer.bad_messages,
        }

    def state(self) -> dict[str, Any]:
        """Where the car truly is and its battery."""
        drive = self.controller.drive
        return {"pose": list(drive.pose), "battery_mv": drive.battery_mv}

    def close(self) -> None:
        """Stop the motors, close both ends of the line."""
        self.controller.close()
        os.close(self.controller.fd)
        os.close(self._slave)


class EspCar(asyncio.DatagramProtocol):
    """The ESP8266 half of one WiFi car: its UDP socket and firmware, the serial line to its
    motor controller opened by name. ``start`` binds the socket."""

    def __init__(
        self,
        spec: CarSpec,
        tty_path: str,
        faults: Faults,
        *,
        edge: tuple[str, int] | None = None,
        timing: CarTiming = DEFAULT_TIMING,
        seed: int | None = None,
    ) -> None:
        self.spec = spec
        self.tty_path = tty_path
        self.faults = faults
        self.edge = edge
        self.timing = timing
        self.seed = seed
        self.address: tuple[str, int] | None = None
        self._transport: asyncio.DatagramTransport | None = None

    async def start(self) -> tuple[str, int]:
        """Open the serial line and the socket, boot the firmware; returns the bound address.

        ``OSError`` if the socket cannot be bound (port in use); the serial line is closed again.
        """
        loop = asyncio.get_running_loop()
        self.esp_serial = SerialMotors(serial.Serial(self.tty_path, baudrate=BAUD, timeout=0))
        self.firmware = CarFirmware.for_car(
            self.spec,
            self.esp_serial,
            self._transmit,
            faults=self.faults,
            edge=self.edge,
            timing=self.timing,
            seed=self.seed,
        )
        self.esp_serial.on_change = self.firmware.send_status
        try:
            self._transport, _ = await loop.create_datagram_endpoint(
                lambda: self, local_addr=(self.spec.host, self.spec.port)
            )
        except (OSError, OverflowError):
            self.esp_serial.close()
            raise
        self.address = self._transport.get_extra_info("sockname")[:2]
        self.firmware.start()
        return self.address

    def datagram_received(self, data: bytes, addr: Any) -> None:
        """Every datagram goes to the firmware (through the injected link faults)."""
        self.firmware.receive(data, addr)

    def _transmit(self, data: bytes, addr: Any) -> None:
        if self._transport is not None and not self._transport.is_closing():
            self._transport.sendto(data, addr)

    def close(self) -> None:
        """LEAVE, stop the motors, close socket and serial line."""
        self.firmware.close()
        self.esp_serial.close()
        if self._transport is not None:
            self._transport.close()

    def counters(self) -> dict[str, Any]:
        """The protocol's and the link faults' counts, bad frames at this end of the line."""
        out = self.firmware.counters()
        out["serial_bad_frames"] = self.esp_serial.deframer.bad_frames
        out["serial_bad_messages"] = self.esp_serial.deframer.bad_messages
        return out

    def state(self) -> dict[str, Any]:
        """The car as its firmware sees it."""
        core = self.firmware.core
        return {
            "car_id": self.spec.car_id,
            "marker": self.spec.marker,
            "address": list(self.address or ()),
            "session": core.session,
            "joined": core.joined,
            "estopped": core.estopped,
            "watchdog_tripped": core.watchdog_tripped,
            "dead": self.firmware.dead(),
            "faults": vars(self.faults).copy(),
        }


def car_counters(esp: dict[str, Any], motor: dict[str, int]) -> dict[str, Any]:
    """One car's counters from its two halves' (``EspCar.counters``, ``MotorEnd.counters``)."""
    return {**esp, **motor, **{name: esp[name] + motor[name] for name in SERIAL_COUNTERS}}


class MockCar:
    """One WiFi car, both halves in this process (sharing one ``Faults``). ``start`` binds the
    socket; ``counters``/``state`` are the test hooks."""

    def __init__(
        self,
        spec: CarSpec,
        *,
        edge: tuple[str, int] | None = None,
        world: World | None = None,
        timing: CarTiming = DEFAULT_TIMING,
        seed: int | None = None,
    ) -> None:
        self.spec = spec
        self.edge = edge
        self.world = world or GridWorld()
        self.timing = timing
        self.seed = seed
        self.faults = Faults.from_mapping(spec.faults)
        self.address: tuple[str, int] | None = None

    async def start(self) -> tuple[str, int]:
        """Wire both halves and boot the firmware; returns the bound address.

        ``OSError`` if the socket cannot be bound (port in use); the serial pair is closed again.
        """
        self.motor = MotorEnd(self.spec, self.world, self.timing, self.faults)
        self.esp = EspCar(
            self.spec, self.motor.tty_path, self.faults, edge=self.edge, timing=self.timing,
            seed=self.seed,
        )  # fmt: skip
        try:
            self.address = await self.esp.start()
        except (OSError, OverflowError):
            self.motor.close()
            raise
        return self.address

    @property
    def firmware(self) -> CarFirmware:
        """The ESP8266's firmware (after ``start``)."""
        return self.esp.firmware

    @property
    def controller(self) -> MotorController:
        """The motor controller (after ``start``)."""
        return self.motor.controller

    def close(self) -> None:
        """LEAVE, stop the motors, close socket and serial line."""
        self.esp.close()
        self.motor.close()

    def counters(self) -> dict[str, Any]:
        """Everything counted on this car: protocol, motors, serial line, link faults."""
        return car_counters(self.esp.counters(), self.motor.counters())

    def state(self) -> dict[str, Any]:
        """The car as the simulation sees it (true pose) and as its firmware does."""
        return {**self.esp.state(), **self.motor.state()}
