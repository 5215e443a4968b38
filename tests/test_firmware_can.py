"""Cars on CAN FD (python-can's virtual bus, in one process) driven by the edge's core."""

from __future__ import annotations

import asyncio
import uuid
from collections.abc import AsyncIterator
from typing import Any

import can
import pytest

from udan.edge import protocol as ep
from udan.firmware_mock.can_car import CanCar
from udan.firmware_mock.firmware import CarTiming
from udan.firmware_mock.fleet import CarSpec

KEYS = {3: bytes(range(9, 41)), 4: bytes(range(60, 92))}


def _fd(can_id: int, data: bytes) -> can.Message:
    return can.Message(
        arbitration_id=can_id, is_extended_id=False, is_fd=True, bitrate_switch=True, data=data
    )


class CanEdge:
    """The edge's end of the bus: the core plus an async reader."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, protocol=can.CanProtocol.CAN_FD)
        self.reader = can.AsyncBufferedReader()
        self.notifier = can.Notifier(
            self.bus, [self.reader], timeout=0.05, loop=asyncio.get_running_loop()
        )
        self.proto = ep.EdgeProtocol(KEYS)

    def send(self, frame: bytes) -> None:
        self.bus.send(_fd(*ep.can_pack(frame)))

    async def expect(self, kind: type, where=lambda e: True, timeout: float = 2.0) -> Any:
        async with asyncio.timeout(timeout):
            while True:
                msg = await self.reader.get_message()
                if not 0x180 < msg.arbitration_id <= 0x1FF:
                    continue  # the edge's own frames are not for it
                event = self.proto.receive(ep.can_unpack(msg.arbitration_id, bytes(msg.data)))
                for _car, frame in self.proto.datagrams_to_send():
                    self.send(frame)
                if isinstance(event, kind) and where(event):
                    return event

    async def join(self, car_id: int) -> None:
        await self.expect(ep.Joined, lambda e: e.car_id == car_id)
        self.send(self.proto.encode_time_request(car_id))
        await self.expect(ep.TimeSynced, lambda e: e.car_id == car_id)

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


@pytest.fixture
async def bus_pair() -> AsyncIterator[tuple[CanEdge, list[CanCar]]]:
    channel = f"udan-{uuid.uuid4().hex}"
    edge = CanEdge(channel)
    car_buses = []
    cars = []
    for car_id, key in KEYS.items():
        bus = can.Bus(interface="virtual", channel=channel, protocol=can.CanProtocol.CAN_FD)
        car_buses.append(bus)
        timing = CarTiming(cell_time_s=0.02)
        car = CanCar(CarSpec(car_id, car_id, key), bus, timing=timing, seed=car_id)
        await car.start()
        cars.append(car)
    yield edge, cars
    for car in cars:
        car.close()
    for bus in car_buses:
        bus.shutdown()
    edge.close()


async def test_command_over_can_fd_is_executed_and_acked(bus_pair) -> None:
    edge, (car3, car4) = bus_pair
    await edge.join(3)
    frame = edge.proto.encode_command(3, ep.Action.UP, validity_ns=500_000_000)
    edge.send(frame)
    ack = await edge.expect(ep.Acked, lambda e: e.ref_seq == ep.decode(frame).seq)
    assert ack.car_id == 3 and ack.result is ep.AckResult.ACCEPTED
    await edge.expect(ep.StatusReport, lambda s: s.car_id == 3 and s.done_seq == ack.ref_seq)
    assert car3.drive.pose == (3, 4) and car4.drive.pose == (4, 4)
    assert car3.counters()["executed"] == 1 and car4.counters()["accepted"] == 0


async def test_forged_and_badly_padded_can_frames_are_rejected(bus_pair) -> None:
    edge, (car3, _) = bus_pair
    await edge.join(3)
    frame = bytearray(edge.proto.encode_command(3, ep.Action.DOWN))
    frame[-1] ^= 1
    edge.send(bytes(frame))
    can_id, data = ep.can_pack(edge.proto.encode_command(3, ep.Action.DOWN))
    edge.bus.send(_fd(can_id, data[:-1] + b"\x07"))  # junk in the padding
    edge.bus.send(_fd(0x083, data))  # a command on the estop id
    estop = edge.proto.encode_estop(3)
    edge.send(estop)
    await edge.expect(ep.Acked, lambda e: e.ref_seq == ep.decode(estop).seq)
    counters = car3.counters()
    assert counters["rejected"]["bad_tag"] == 1 and counters["rejected"]["malformed"] == 2
    assert counters["executed"] == 0 and car3.firmware.core.estopped


async def test_reboot_on_can_is_detected(bus_pair) -> None:
    edge, (car3, _) = bus_pair
    await edge.join(3)
    car3.firmware.reboot()
    event = await edge.expect(ep.Joined, lambda e: e.car_id == 3)
    assert event.reboot and not edge.proto.synced(3)


def test_car_ids_beyond_the_can_range_are_refused() -> None:
    bus = can.Bus(interface="virtual", channel=f"udan-{uuid.uuid4().hex}")
    try:
        with pytest.raises(ValueError, match="CAN mapping"):
            CanCar(CarSpec(200, 1, bytes(32)), bus)
    finally:
        bus.shutdown()
