"""The wire between ESP8266 and motor controller: COBS frames with a CRC-16 (spec section 9).

A frame on the line is ``COBS(body || CRC-16/CCITT-FALSE(body), big-endian) || 0x00``. COBS keeps
0x00 out of the frame, so a receiver that joins mid-stream or loses bytes resynchronises at the
next 0x00; the CRC drops frames corrupted by line noise. The bodies are the car-internal
messages below (the ESP8266 has already authenticated the edge's frame; the UART is inside the
car). The same framing carries whole protocol frames on a wired serial link to an edge.
"""

from __future__ import annotations

import struct
from collections.abc import Collection

from udan.firmware_mock.wire import GUIDE_FIELDS, GUIDE_POSE, GUIDE_TARGET, STOP_ACTION

MAX_BODY = 253  # one COBS block, so a frame is never longer than 256 bytes on the line


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor ("123456789" ->
    0x29B1)."""
    crc = 0xFFFF
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ _CRC_TABLE[(crc >> 8) ^ byte]
    return crc


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing (canonical form): the result has no 0x00 byte."""
    out = bytearray()
    block = bytearray()
    for i, byte in enumerate(data):
        if byte == 0:
            out.append(len(block) + 1)
            out += block
            block.clear()
            continue
        block.append(byte)
        if len(block) == 254:
            out.append(255)
            out += block
            block.clear()
            if i == len(data) - 1:
                return bytes(out)
    out.append(len(block) + 1)
    out += block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of ``cobs_encode``; ``ValueError`` on a zero byte or a code running past the end."""
    out = bytearray()
    i = 0
    while i < len(data):
        code = data[i]
        if code == 0 or i + code > len(data):
            raise ValueError("bad COBS block")
        block = data[i + 1 : i + code]
        if 0 in block:
            raise ValueError("zero byte inside a COBS frame")
        out += block
        i += code
        if code < 255 and i < len(data):
            out.append(0)
    return bytes(out)


def frame(body: bytes) -> bytes:
    """One body as it goes on the line, delimiter included."""
    if len(body) > MAX_BODY:
        raise ValueError(f"serial body of {len(body)} bytes exceeds {MAX_BODY}")
    return cobs_encode(body + crc16(body).to_bytes(2, "big")) + b"\x00"


class Deframer:
    """Splits a byte stream at 0x00 and returns the bodies whose COBS and CRC check out."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.bad_frames = 0
        self.bad_messages = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Bytes as they arrive (any split) -> complete, checked bodies."""
        bodies = []
        self._buf += data
        while (end := self._buf.find(0)) >= 0:
            chunk = bytes(self._buf[:end])
            del self._buf[: end + 1]
            if not chunk:
                continue
            try:
                raw = cobs_decode(chunk)
            except ValueError:
                self.bad_frames += 1
                continue
            if len(raw) < 3 or crc16(raw[:-2]) != int.from_bytes(raw[-2:], "big"):
                self.bad_frames += 1
                continue
            bodies.append(raw[:-2])
        if len(self._buf) > 2 * (MAX_BODY + 4):  # no delimiter for too long: line noise
            self.bad_frames += 1
            self._buf.clear()
        return bodies

    def messages(self, data: bytes, kinds: Collection[int]) -> list[tuple[int, dict[str, int]]]:
        """Bytes as they arrive -> the car-internal messages of ``kinds`` they complete.

        Each end of the line expects only its peer's messages (the controller MOVE and STOP, the
        ESP8266 STATE); a frame that passes the CRC but is not one of those is counted in
        ``bad_messages`` rather than acted on.
        """
        out = []
        for body in self.feed(data):
            try:
                kind, fields = decode_message(body)
            except ValueError:
                kind, fields = -1, {}
            if kind in kinds:
                out.append((kind, fields))
            else:
                self.bad_messages += 1
        return out


# Car-internal messages (the body's first byte is the message id).
MOVE, STOP, STATE = 0x10, 0x11, 0x90
STOP_COMMAND, STOP_WATCHDOG, STOP_ESTOP, STOP_BOOT = range(4)
STATE_MOVING, STATE_STALL, STATE_LOW_BATTERY = 1, 2, 4
_MESSAGES: dict[int, tuple[struct.Struct, tuple[str, ...]]] = {
    MOVE: (struct.Struct(">IBBhhhhhhIB"), ("seq", "action", *GUIDE_FIELDS)),
    STOP: (struct.Struct(">B"), ("reason",)),
    STATE: (struct.Struct(">hhHBI"), ("row", "col", "battery_mv", "flags", "done_seq")),
}


def encode_message(kind: int, **fields: int) -> bytes:
    """A car-internal message body; a MOVE's target and pose fields default to none given."""
    fmt, names = _MESSAGES[kind]
    if kind == MOVE:
        fields = {**dict.fromkeys(GUIDE_FIELDS, 0), **fields}
    return bytes([kind]) + fmt.pack(*(fields[n] for n in names))


def decode_message(body: bytes) -> tuple[int, dict[str, int]]:
    """``(kind, fields)``; ``ValueError`` for an unknown id, a wrong length, a MOVE action > 5
    or unknown MOVE guide flags."""
    if not body or body[0] not in _MESSAGES:
        raise ValueError("unknown serial message")
    fmt, names = _MESSAGES[body[0]]
    if len(body) != 1 + fmt.size:
        raise ValueError("serial message length does not match its id")
    fields = dict(zip(names, fmt.unpack_from(body, 1), strict=True))
    if body[0] == MOVE and fields["action"] > STOP_ACTION:
        raise ValueError(f"MOVE action {fields['action']} out of range")
    if body[0] == MOVE and fields["guide"] & ~(GUIDE_TARGET | GUIDE_POSE):
        raise ValueError(f"MOVE guide flags 0x{fields['guide']:02x} unknown")
    return body[0], fields
