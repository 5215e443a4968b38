"""The ESP8266 <-> motor controller line: COBS + CRC-16 framing, over a real pty pair."""

from __future__ import annotations

import asyncio
import os

import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from udan.envs.rules import DOWN, LEFT, RIGHT, UP, WAIT
from udan.firmware_mock import serial_link as sl
from udan.firmware_mock.faults import Faults
from udan.firmware_mock.motor import Drive, GridWorld, MotorController, SerialMotors


@given(st.binary(max_size=600))
def test_cobs_round_trip_has_no_zero(data: bytes) -> None:
    encoded = sl.cobs_encode(data)
    assert 0 not in encoded
    assert sl.cobs_decode(encoded) == data


@settings(max_examples=200)
@given(
    st.lists(st.binary(min_size=1, max_size=sl.MAX_BODY), min_size=1, max_size=5),
    st.lists(st.integers(1, 50), max_size=20),
    st.binary(max_size=40),
)
def test_deframer_any_split_and_resync_after_noise(
    bodies: list[bytes], cuts: list[int], noise: bytes
) -> None:
    stream = noise + b"\x00" + b"".join(sl.frame(b) for b in bodies)
    deframer = sl.Deframer()
    got: list[bytes] = []
    pos = 0
    for cut in cuts:
        got += deframer.feed(stream[pos : pos + cut])
        pos += cut
    got += deframer.feed(stream[pos:])
    # every body survives; the noise before the first delimiter is at most one chunk, which
    # passes the CRC with probability 2**-16
    assert got[-len(bodies) :] == bodies
    assert len(got) - len(bodies) <= 1


def test_corrupted_frame_is_dropped_by_the_crc() -> None:
    line = bytearray(sl.frame(sl.encode_message(sl.MOVE, seq=7, action=UP)))
    line[1] ^= 0x01  # the message id byte: COBS still decodes, the CRC does not match
    deframer = sl.Deframer()
    assert deframer.feed(bytes(line)) == [] and deframer.bad_frames == 1
    with pytest.raises(ValueError):
        sl.decode_message(b"\x10\x00")
    with pytest.raises(ValueError):
        sl.frame(bytes(sl.MAX_BODY + 1))


async def test_moves_cross_a_real_pty_and_state_comes_back() -> None:
    master, slave = os.openpty()
    port = serial.Serial(os.ttyname(slave), baudrate=921_600, timeout=0)
    os.close(slave)
    changed = asyncio.Event()
    faults = Faults()
    drive = Drive(1, GridWorld(), (0, 0), 0.01, faults)
    controller = MotorController(master, drive)
    esp = SerialMotors(port, on_change=changed.set)
    try:

        async def until(check) -> None:
            while not check(esp.telemetry()):
                changed.clear()
                await asyncio.wait_for(changed.wait(), 2)

        esp.move(1, DOWN)
        await until(lambda t: t.done_seq == 1)
        assert (esp.telemetry().row, esp.telemetry().col) == (1, 0)
        esp.move(2, UP)
        esp.move(3, RIGHT)  # queued behind move 2
        await until(lambda t: t.done_seq == 3)
        assert (esp.telemetry().row, esp.telemetry().col) == (0, 1)
        esp.move(4, LEFT)
        esp.move(5, LEFT)  # off the grid: the world makes it a wait
        await until(lambda t: t.done_seq == 5)
        assert drive.pose == (0, 0)
        faults.stuck_wheel = True
        esp.move(6, DOWN)
        await until(lambda t: t.done_seq == 6)
        assert esp.telemetry().stalled and drive.pose == (0, 0) and drive.stalls == 1
        faults.stuck_wheel = False
        drive.cell_time_s = 5.0
        esp.move(7, DOWN)
        await until(lambda t: t.moving)
        esp.stop(sl.STOP_COMMAND)
        await until(lambda t: not t.moving)
        assert drive.pose == (0, 0) and drive.aborted == 1
        esp.move(8, WAIT)
        await until(lambda t: t.done_seq == 8)
        os.write(master, b"\x05garbage\x00")  # line noise from the controller side
        esp.move(9, DOWN)
        drive.cell_time_s = 0.01
        await until(lambda t: t.done_seq == 9)
        assert esp.deframer.bad_frames == 1 and controller.deframer.bad_messages == 0
    finally:
        esp.close()
        controller.close()
        os.close(master)
