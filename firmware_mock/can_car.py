"""The wired car on CAN FD: a motor controller that is its own protocol endpoint (spec section 10).

The edge and the cars share one bus; every protocol frame travels whole in one CAN FD frame
(11-bit id, bit-rate switch, zero padding up to the next FD length). Ids: 0x080 + car for
ESTOP (lowest ids win arbitration), 0x100 + car for the edge's other frames, 0x180 + car for
everything a car sends. In one process the bus is python-can's ``virtual`` interface; across
processes on a real machine it is ``socketcan`` (``vcan0`` or a real controller).
"""

from __future__ import annotations

import asyncio
from typing import Any

import can

from udan.firmware_mock import wire
from udan.firmware_mock.faults import Faults
from udan.firmware_mock.firmware import DEFAULT_TIMING, CarFirmware, CarTiming
from udan.firmware_mock.fleet import CarSpec
from udan.firmware_mock.motor import Drive, GridWorld, World

ESTOP_BASE, EDGE_BASE, CAR_BASE = 0x080, 0x100, 0x180
MAX_CAR_ID = 0x7F
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
_BUS = "can-bus"  # the firmware's "edge address": on CAN there is only the bus


def message_for(frame: bytes, car_id: int) -> can.Message:
    """A car's frame as a CAN FD message on 0x180 + car, padded with zeros."""
    size = next(n for n in FD_LENGTHS if n >= len(frame))
    return can.Message(
        arbitration_id=CAR_BASE + car_id,
        is_extended_id=False,
        is_fd=True,
        bitrate_switch=True,
        data=frame + bytes(size - len(frame)),
    )


def frame_from(msg: can.Message, car_id: int) -> bytes:
    """The protocol frame in an edge message for ``car_id``; ``wire.Malformed`` if it is not one.

    The frame's own length (header byte 2) says where the padding starts; padding must be zero
    and the id must match the frame's type (ESTOP on 0x080 + car, others on 0x100 + car).
    """
    data = bytes(msg.data)
    if msg.is_extended_id or not msg.is_fd or len(data) < wire.HEADER_LEN:
        raise wire.Malformed("malformed", "not a CAN FD frame of this protocol")
    end = wire.HEADER_LEN + data[2] + wire.TRAILER_LEN
    if end > len(data) or any(data[end:]):
        raise wire.Malformed("malformed", "bad CAN padding")
    base = ESTOP_BASE if data[1] == wire.ESTOP else EDGE_BASE
    if msg.arbitration_id != base + car_id:
        raise wire.Malformed("malformed", "frame type does not match the CAN id")
    return data[:end]


class CanCar:
    """One car on a CAN FD bus: ``CarFirmware`` driving a ``Drive`` directly (no serial hop)."""

    def __init__(
        self,
        spec: CarSpec,
        bus: can.BusABC,
        *,
        world: World | None = None,
        timing: CarTiming = DEFAULT_TIMING,
        seed: int | None = None,
    ) -> None:
        if not 0 < spec.car_id <= MAX_CAR_ID:
            raise ValueError(f"car id {spec.car_id} does not fit the CAN mapping (1-{MAX_CAR_ID})")
        self.spec = spec
        self.bus = bus
        self.faults = Faults.from_mapping(spec.faults)
        self.drive = Drive(
            spec.car_id,
            world or GridWorld(),
            spec.start,
            timing.cell_time_s,
            self.faults,
            accel_share=timing.accel_share,
        )
        self.firmware = CarFirmware.for_car(
            spec,
            self.drive,
            self._transmit,
            faults=self.faults,
            edge=_BUS,
            timing=timing,
            seed=seed,
        )
        self.drive.on_change = self.firmware.send_status
        self._notifier: can.Notifier | None = None

    async def start(self) -> None:
        """Listen on the bus and boot (announces JOIN on 0x180 + car)."""
        self._notifier = can.Notifier(
            self.bus, [self._on_message], timeout=0.05, loop=asyncio.get_running_loop()
        )
        self.firmware.start()

    def _on_message(self, msg: can.Message) -> None:
        if msg.arbitration_id not in (ESTOP_BASE + self.spec.car_id, EDGE_BASE + self.spec.car_id):
            return  # another node's frame: a CAN controller's acceptance filter drops it
        try:
            frame = frame_from(msg, self.spec.car_id)
        except wire.Malformed as err:
            self.firmware.core.reject(err.reason)
            return
        self.firmware.receive(frame, _BUS)

    def _transmit(self, frame: bytes, _addr: Any) -> None:
        self.bus.send(message_for(frame, self.spec.car_id))

    def close(self) -> None:
        """LEAVE, stop the motors, stop listening (the bus belongs to the caller)."""
        self.firmware.close()
        if self._notifier is not None:
            self._notifier.stop()

    def counters(self) -> dict[str, Any]:
        """Protocol, motor and link-fault counters."""
        out = self.firmware.counters()
        out.update(
            executed=self.drive.executed, aborted=self.drive.aborted, stalls=self.drive.stalls
        )
        return out
