"""The WiFi car: an ESP8266 mock on a UDP socket, wired by a real pty to a motor controller mock.

Datagram in -> ``CarFirmware`` (tag, session, sequence, deadline) -> MOVE over the serial line
(COBS + CRC-16 through an ``os.openpty()`` pair, the ESP8266 end opened with pyserial) -> the
motor controller executes it in its ``World`` and reports STATE back over the line.
"""

from __future__ import annotations

import asyncio
import os
from typing import Any

import serial

from udan.firmware_mock.faults import Faults
from udan.firmware_mock.firmware import DEFAULT_TIMING, CarFirmware, CarTiming
from udan.firmware_mock.fleet import CarSpec
from udan.firmware_mock.motor import Drive, GridWorld, MotorController, SerialMotors, World

BAUD = 921_600


class MockCar(asyncio.DatagramProtocol):
    """One WiFi car. ``start`` binds the socket; ``counters``/``state`` are the test hooks."""

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
        self._transport: asyncio.DatagramTransport | None = None

    async def start(self) -> tuple[str, int]:
        """Open the serial pair and the socket, boot the firmware; returns the bound address.

        ``OSError`` if the socket cannot be bound (port in use); the serial pair is closed again.
        """
        loop = asyncio.get_running_loop()
        master, slave = os.openpty()
        port = serial.Serial(os.ttyname(slave), baudrate=BAUD, timeout=0)
        os.close(slave)
        drive = Drive(
            self.spec.car_id,
            self.world,
            self.spec.start,
            self.timing.cell_time_s,
            self.faults,
            accel_share=self.timing.accel_share,
        )
        self.controller = MotorController(master, drive)
        self.esp_serial = SerialMotors(port)
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
            self._close_serial()
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
        self._close_serial()
        if self._transport is not None:
            self._transport.close()

    def _close_serial(self) -> None:
        self.esp_serial.close()
        self.controller.close()
        os.close(self.controller.fd)

    def counters(self) -> dict[str, Any]:
        """Everything counted on this car: protocol, motors, serial line, link faults."""
        out = self.firmware.counters()
        drive = self.controller.drive
        out.update(executed=drive.executed, aborted=drive.aborted, stalls=drive.stalls)
        ends = (self.controller.deframer, self.esp_serial.deframer)
        out["serial_bad_frames"] = sum(d.bad_frames for d in ends)
        out["serial_bad_messages"] = sum(d.bad_messages for d in ends)
        return out

    def state(self) -> dict[str, Any]:
        """The car as the simulation sees it (true pose) and as its firmware does."""
        core = self.firmware.core
        drive = self.controller.drive
        return {
            "car_id": self.spec.car_id,
            "marker": self.spec.marker,
            "address": list(self.address or ()),
            "session": core.session,
            "joined": core.joined,
            "estopped": core.estopped,
            "watchdog_tripped": core.watchdog_tripped,
            "pose": list(drive.pose),
            "battery_mv": drive.battery_mv,
            "dead": self.firmware.dead(),
            "faults": vars(self.faults).copy(),
        }
