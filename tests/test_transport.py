"""The edge's transports on their own: serial codec, registry, UDP routing, pty bytes, CAN ids.

The serial codec is checked against docs/protocol_vectors.json and against the mock firmware's
independent codec (``udan.firmware_mock.serial_link``); the end-to-end runs with cars are in
tests/test_link.py.
"""

from __future__ import annotations

import asyncio
import json
import os
import socket
import sys
import tty
import uuid
from pathlib import Path

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from udan.edge import transport as tr
from udan.firmware_mock import serial_link as sl
from udan.fleetfile import CarEntry

VECTORS = json.loads((Path(__file__).parent.parent / "docs/protocol_vectors.json").read_text())
KEY = bytes(range(32))
COMMAND = bytes.fromhex(VECTORS["can"][0]["frame"])  # a real COMMAND frame to car 1


def _cars(*ids: int, **fields: object) -> list[CarEntry]:
    return [CarEntry(c, c, KEY, **fields) for c in ids]  # type: ignore[arg-type]


class Inbox:
    """Collects what a transport delivers and lets a test wait for it."""

    def __init__(self) -> None:
        self.frames: list[bytes] = []
        self._arrived = asyncio.Event()

    def __call__(self, frame: bytes) -> None:
        self.frames.append(frame)
        self._arrived.set()

    async def wait(self, count: int, timeout: float = 2.0) -> list[bytes]:
        async with asyncio.timeout(timeout):
            while len(self.frames) < count:
                self._arrived.clear()
                await self._arrived.wait()
        return self.frames


# --- serial codec ------------------------------------------------------------------------------
def test_codec_matches_the_vectors() -> None:
    check = VECTORS["crc16"]
    assert tr.crc16(check["input_ascii"].encode()) == int(check["check"], 16) == 0x29B1
    for case in VECTORS["cobs"]:
        raw, encoded = bytes.fromhex(case["raw"]), bytes.fromhex(case["encoded"])
        assert tr.cobs_encode(raw) == encoded
        assert tr.cobs_decode(encoded) == raw
    deframer = tr.Deframer()
    for case in VECTORS["serial"]:
        body, line = bytes.fromhex(case["body"]), bytes.fromhex(case["line"])
        assert tr.serial_frame(body) == line, case["name"]
        assert deframer.feed(line) == [body], case["name"]
    assert deframer.bad_frames == 0


@settings(max_examples=300)
@given(st.binary(max_size=tr.MAX_SERIAL_BODY), st.binary(max_size=600))
def test_codec_agrees_with_the_mock_firmware(body: bytes, blob: bytes) -> None:
    assert tr.serial_frame(body) == sl.frame(body)
    assert 0 not in tr.cobs_encode(blob)
    assert tr.cobs_decode(tr.cobs_encode(blob)) == blob == sl.cobs_decode(sl.cobs_encode(blob))


@settings(max_examples=200)
@given(
    st.lists(st.binary(min_size=1, max_size=tr.MAX_SERIAL_BODY), min_size=1, max_size=5),
    st.lists(st.integers(1, 60), max_size=20),
    st.binary(max_size=40),
)
def test_deframer_any_split_and_resync_after_noise(
    bodies: list[bytes], cuts: list[int], noise: bytes
) -> None:
    stream = noise + b"\x00" + b"".join(tr.serial_frame(b) for b in bodies)
    deframer = tr.Deframer()
    got: list[bytes] = []
    pos = 0
    for cut in cuts:
        got += deframer.feed(stream[pos : pos + cut])
        pos += cut
    got += deframer.feed(stream[pos:])
    assert got[-len(bodies) :] == bodies
    assert len(got) - len(bodies) <= 1  # noise passes the CRC with probability 2**-16


def test_corrupt_frames_are_counted_not_delivered() -> None:
    deframer = tr.Deframer()
    line = bytearray(tr.serial_frame(b"\x01\x02\x03"))
    line[2] ^= 0x40  # COBS still decodes, the CRC does not match
    assert deframer.feed(bytes(line) + b"\x05\x00" + bytes(600)) == []
    assert deframer.bad_frames == 2
    assert deframer.feed(bytes(range(1, 255)) * 3) == [] and deframer.bad_frames == 3  # no 0x00
    with pytest.raises(ValueError):
        tr.serial_frame(bytes(tr.MAX_SERIAL_BODY + 1))
    with pytest.raises(ValueError):
        tr.cobs_decode(b"\x05\x01")


# --- registry ----------------------------------------------------------------------------------
def test_unknown_transport_or_option_is_one_line() -> None:
    with pytest.raises(tr.TransportError, match=r"unknown transport 'ipx'; known: can, loop"):
        tr.open_transport("ipx", _cars(1))
    with pytest.raises(tr.TransportError, match=r"'udp' has no option baud; options: listen"):
        tr.open_transport("udp", _cars(1), baud=9600)
    with pytest.raises(tr.TransportError, match="listen address must be HOST:PORT"):
        tr.open_transport("udp", _cars(1), listen="9000")
    with pytest.raises(tr.TransportError, match="car 1 has no serial device"):
        tr.open_transport("serial", _cars(1))
    with pytest.raises(tr.TransportError, match="car id 200 outside 1-127"):
        tr.open_transport("can", _cars(200), interface="virtual")


def test_missing_driver_fails_only_when_chosen(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "serial", None)  # import serial -> ImportError
    monkeypatch.setitem(sys.modules, "can", None)
    assert isinstance(tr.open_transport("udp", _cars(1)), tr.UdpTransport)
    assert isinstance(tr.open_transport("loop", _cars(1)), tr.LoopTransport)
    with pytest.raises(tr.TransportError, match=r"'serial' needs pyserial \(pip install pyserial"):
        tr.open_transport("serial", _cars(1, serial="/dev/null"))
    with pytest.raises(tr.TransportError, match=r"'can' needs python-can"):
        tr.open_transport("can", _cars(1))


# --- UDP ---------------------------------------------------------------------------------------
async def test_udp_routes_to_the_fleet_address_then_to_where_the_car_speaks_from() -> None:
    loop = asyncio.get_running_loop()
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
    fleet_car, roaming_car = socks
    port = fleet_car.getsockname()[1]
    cars = [CarEntry(1, 1, KEY, "127.0.0.1", port), CarEntry(2, 2, KEY)]
    transport = tr.open_transport("udp", cars, listen="127.0.0.1:0")
    inbox = Inbox()
    confirm: dict[bytes, int] = {b"from car 2": 2}

    def on_frame(frame: bytes) -> None:
        inbox(frame)
        if frame in confirm:
            transport.confirm_source(confirm[frame])

    await transport.open(on_frame)
    try:
        assert transport.address is not None and transport.address[1] > 0
        transport.send(1, b"to car 1")
        assert await asyncio.wait_for(loop.sock_recv(fleet_car, 100), 2) == b"to car 1"
        with pytest.raises(tr.TransportError, match="car 2: no address"):
            transport.send(2, b"x")
        roaming_car.sendto(b"unconfirmed", transport.address)
        await inbox.wait(1)
        with pytest.raises(tr.TransportError):
            transport.send(2, b"x")  # a frame that did not pass the checks routes nothing
        roaming_car.sendto(b"from car 2", transport.address)
        assert await inbox.wait(2) == [b"unconfirmed", b"from car 2"]
        transport.send(2, b"to car 2")
        assert await asyncio.wait_for(loop.sock_recv(roaming_car, 100), 2) == b"to car 2"
    finally:
        transport.close()
        for s in socks:
            s.close()
    with pytest.raises(tr.TransportError, match="not open"):
        transport.send(1, b"after close")


# --- serial over a real pty --------------------------------------------------------------------
async def test_serial_frames_cross_a_pty_both_ways() -> None:
    loop = asyncio.get_running_loop()
    master, slave = os.openpty()
    tty.setraw(slave)
    transport = tr.open_transport("serial", _cars(1, serial=os.ttyname(slave)))
    inbox = Inbox()
    await transport.open(inbox)
    os.close(slave)
    car_side = sl.Deframer()
    received: asyncio.Queue[bytes] = asyncio.Queue()

    def readable() -> None:
        for body in car_side.feed(os.read(master, 4096)):
            received.put_nowait(body)

    loop.add_reader(master, readable)
    try:
        transport.send(1, COMMAND)
        assert await asyncio.wait_for(received.get(), 2) == COMMAND
        line = sl.frame(COMMAND[::-1])
        os.write(master, b"\x13\x37\x00" + line[:5])  # noise, then a frame in two pieces
        await asyncio.sleep(0.02)
        os.write(master, line[5:] + b"\x02\x00")  # ... and a frame failing its CRC
        assert await inbox.wait(1) == [COMMAND[::-1]]
        await asyncio.sleep(0.05)
        assert transport.dropped["serial_bad_frames"] == 2
        with pytest.raises(tr.TransportError, match="car 9: serial line not open"):
            transport.send(9, COMMAND)
        loop.remove_reader(master)
        os.close(master)  # the line hangs up: counted once, and the reader stops
        await asyncio.sleep(0.05)
        assert transport.dropped["serial_io_error"] == 1
    finally:
        transport.close()


async def test_serial_open_failure_is_one_line() -> None:
    transport = tr.open_transport("serial", _cars(1, serial="/nonexistent/tty"))
    with pytest.raises(tr.TransportError, match="car 1: cannot open /nonexistent/tty"):
        await transport.open(Inbox())


# --- CAN FD on python-can's virtual bus --------------------------------------------------------
def _fd(can_id: int, data: bytes) -> can.Message:
    return can.Message(
        arbitration_id=can_id, is_fd=True, bitrate_switch=True, is_extended_id=False, data=data
    )


async def test_can_ids_padding_and_filtering() -> None:
    channel = f"udan-{uuid.uuid4().hex}"
    other = can.Bus(interface="virtual", channel=channel, protocol=can.CanProtocol.CAN_FD)
    transport = tr.open_transport("can", _cars(1), interface="virtual", channel=channel)
    inbox = Inbox()
    await transport.open(inbox)
    try:
        transport.send(1, COMMAND)
        msg = await asyncio.to_thread(other.recv, 2.0)
        assert msg is not None and msg.is_fd and msg.bitrate_switch
        vector = VECTORS["can"][0]
        assert (msg.arbitration_id, bytes(msg.data).hex()) == (vector["can_id"], vector["data"])
        ack = VECTORS["can"][2]
        frame, data = bytes.fromhex(ack["frame"]), bytes.fromhex(ack["data"])
        other.send(_fd(0x101, bytes.fromhex(vector["data"])))  # another edge's frame: ignored
        other.send(_fd(ack["can_id"], data[:-1] + b"\x01"))  # bad padding: dropped, counted
        other.send(_fd(ack["can_id"] + 1, data))  # car 1's frame on car 2's id: dropped
        other.send(_fd(ack["can_id"], data))
        assert await inbox.wait(1) == [frame]
        assert transport.dropped["can_malformed"] == 2
    finally:
        transport.close()
        other.shutdown()


# --- loop --------------------------------------------------------------------------------------
async def test_loop_delivers_from_the_event_loop_never_inside_send() -> None:
    transport = tr.open_transport("loop", _cars(1))
    assert isinstance(transport, tr.LoopTransport)
    at_car: list[bytes] = []
    inbox = Inbox()
    await transport.open(inbox)
    transport.attach(1, at_car.append)
    transport.send(1, b"a")
    transport.car_send(b"b")
    assert at_car == [] and inbox.frames == []
    await asyncio.sleep(0)
    assert at_car == [b"a"] and await inbox.wait(1) == [b"b"]
    assert transport.sent == [(1, b"a")]
    with pytest.raises(tr.TransportError, match="car 2: nothing attached"):
        transport.send(2, b"c")
    transport.close()
    transport.car_send(b"after close")
    await asyncio.sleep(0.01)
    assert inbox.frames == [b"b"]
