"""Car-side codec for the edge <-> car frames, written from docs/protocol.md (section 2-3).

It is deliberately not shared with ``edge/``: the mock firmware is a second, independent reading
of the spec, so the two sides only agree if the spec (and docs/protocol_vectors.json) is followed.
Parsing is strict: anything that is not exactly a frame of this version is ``Malformed``.
"""

from __future__ import annotations

import hashlib
import hmac
import struct
from dataclasses import dataclass
from typing import Any

VERSION = 2
KEY_LEN = 32
NONCE_LEN = 16
TAG_LEN = 6

_HEADER = struct.Struct(">BBBBHII")  # version, type, payload length, flags, car, session, seq
HEADER_LEN = _HEADER.size  # 14
TRAILER_LEN = 1 + 6 + TAG_LEN  # link id, 48-bit timestamp, tag

LINK_EDGE_TO_CAR = 0
LINK_CAR_TO_EDGE = 1

# Message types; the high bit says the direction (set: car -> edge).
COMMAND, ESTOP, TIME_REQ, HELLO, ACCEPT = 0x01, 0x02, 0x03, 0x04, 0x05
ACK, STATUS, JOIN, LEAVE, TIME_RESP = 0x81, 0x82, 0x83, 0x84, 0x85

TYPE_NAMES = {
    COMMAND: "command",
    ESTOP: "estop",
    TIME_REQ: "time_request",
    HELLO: "hello",
    ACCEPT: "accept",
    ACK: "ack",
    STATUS: "status",
    JOIN: "join",
    LEAVE: "leave",
    TIME_RESP: "time_response",
}

# Payload layout per type: a struct and the names of its fields, in order.
_PAYLOADS: dict[int, tuple[struct.Struct, tuple[str, ...]]] = {
    COMMAND: (struct.Struct(">BQ"), ("action", "deadline_us")),
    ESTOP: (struct.Struct(">BQ"), ("engage", "deadline_us")),
    TIME_REQ: (struct.Struct(">Q"), ("t1_ns",)),
    HELLO: (struct.Struct(">B"), ("reason",)),
    ACCEPT: (struct.Struct(">16s16sB"), ("car_nonce", "edge_nonce", "version")),
    ACK: (struct.Struct(">IBBQ"), ("ref_seq", "result", "action", "rx_us")),
    STATUS: (struct.Struct(">hhHHBI"), ("row", "col", "battery_mv", "faults", "state", "done_seq")),
    JOIN: (
        struct.Struct(">HBBB16s"),
        ("marker", "cause", "min_version", "max_version", "car_nonce"),
    ),
    LEAVE: (struct.Struct(">B"), ("reason",)),
    TIME_RESP: (struct.Struct(">QQQ"), ("t1_ns", "t2_us", "t3_us")),
}

# Command actions 0-4 are udan.envs.rules.ACTIONS; 5 stops the motors at once.
STOP_ACTION = 5
NO_ACTION = 0xFF  # ack of a frame that is not a command
# Ack results.
RESULTS = ("accepted", "duplicate", "replay", "expired", "bad_time", "estopped")
# Status fault flags.
FAULT_WATCHDOG, FAULT_ESTOP, FAULT_STALL, FAULT_LOW_BATTERY = 1, 2, 4, 8
# Session-less frames (session 0, seq 0, tagged with the car's own key).
HANDSHAKE = (HELLO, ACCEPT, JOIN)
# Join causes, hello reasons and leave reasons.
JOIN_BOOT, JOIN_HELLO, JOIN_RENEW = 0, 1, 2
HELLO_UNKNOWN_SESSION, HELLO_RENEW = 0, 1
LEAVE_REASONS = ("shutdown", "low_battery", "fault")

_MAX_U48 = (1 << 48) - 1


class Malformed(ValueError):
    """A frame that does not follow the spec; ``reason`` is ``malformed`` or ``wrong_version``."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


@dataclass(frozen=True, slots=True)
class Frame:
    """One parsed (not yet authenticated) frame."""

    type: int
    car_id: int
    session: int
    seq: int
    link_id: int
    timestamp_us: int
    tag: bytes
    payload: dict[str, Any]
    signed: bytes  # every byte the tag covers

    def describe(self) -> dict[str, Any]:
        """The frame as the ``decoded`` objects of docs/protocol_vectors.json."""
        return {
            "type": TYPE_NAMES[self.type],
            "car_id": self.car_id,
            "session": self.session,
            "seq": self.seq,
            "link_id": self.link_id,
            "timestamp_us": self.timestamp_us,
            "tag": self.tag.hex(),
            "payload": {k: v.hex() if isinstance(v, bytes) else v for k, v in self.payload.items()},
        }


def _check_fields(kind: int, p: dict[str, Any]) -> None:
    if kind == COMMAND and p["action"] > STOP_ACTION:
        raise Malformed("malformed", f"unknown action {p['action']}")
    if kind == ESTOP and p["engage"] > 1:
        raise Malformed("malformed", f"estop engage must be 0 or 1, got {p['engage']}")
    if kind == ACK and (
        p["result"] >= len(RESULTS) or (p["action"] > STOP_ACTION and p["action"] != NO_ACTION)
    ):
        raise Malformed("malformed", "ack result or action out of range")
    if kind == STATUS and (p["state"] > 1 or p["faults"] >= 16):
        raise Malformed("malformed", "status state or fault flags out of range")
    if kind == JOIN and (p["cause"] > JOIN_RENEW or p["min_version"] > p["max_version"]):
        raise Malformed("malformed", "join cause or version range out of range")
    if kind == HELLO and p["reason"] > HELLO_RENEW:
        raise Malformed("malformed", f"unknown hello reason {p['reason']}")
    if kind == LEAVE and p["reason"] >= len(LEAVE_REASONS):
        raise Malformed("malformed", f"unknown leave reason {p['reason']}")


def parse(data: bytes) -> Frame:
    """Check the structure of ``data`` (section 2 of the spec) and split it into fields."""
    if not data:
        raise Malformed("malformed", "empty frame")
    if data[0] != VERSION:
        raise Malformed("wrong_version", f"protocol v{data[0]}, this firmware speaks v{VERSION}")
    if len(data) < HEADER_LEN + TRAILER_LEN:
        raise Malformed("malformed", f"truncated: {len(data)} bytes")
    _, kind, plen, flags, car_id, session, seq = _HEADER.unpack_from(data)
    layout = _PAYLOADS.get(kind)
    if layout is None:
        raise Malformed("malformed", f"unknown type 0x{kind:02x}")
    fmt, names = layout
    if plen != fmt.size or len(data) != HEADER_LEN + plen + TRAILER_LEN:
        raise Malformed("malformed", "length does not match the type")
    if flags != 0 or car_id in (0, 0xFFFF):
        raise Malformed("malformed", "reserved value in the header")
    if kind in HANDSHAKE:
        if session != 0 or seq != 0:
            raise Malformed("malformed", "a handshake frame carries session 0 and seq 0")
    elif session == 0 or seq == 0:
        raise Malformed("malformed", "session and seq must be nonzero")
    end = HEADER_LEN + plen
    link_id = data[end]
    if link_id != (LINK_CAR_TO_EDGE if kind & 0x80 else LINK_EDGE_TO_CAR):
        raise Malformed("malformed", f"link id {link_id} does not match the direction")
    payload = dict(zip(names, fmt.unpack_from(data, HEADER_LEN), strict=True))
    _check_fields(kind, payload)
    return Frame(
        type=kind,
        car_id=car_id,
        session=session,
        seq=seq,
        link_id=link_id,
        timestamp_us=int.from_bytes(data[end + 1 : end + 7], "big"),
        tag=bytes(data[-TAG_LEN:]),
        payload=payload,
        signed=bytes(data[:-TAG_LEN]),
    )


def tag_for(key: bytes, signed: bytes) -> bytes:
    """First 48 bits of HMAC-SHA256 over every byte before the tag."""
    return hmac.digest(key, signed, hashlib.sha256)[:TAG_LEN]


def authentic(frame: Frame, key: bytes) -> bool:
    """Constant-time check of the frame's tag under ``key``."""
    return hmac.compare_digest(tag_for(key, frame.signed), frame.tag)


def session_for(key: bytes, car_nonce: bytes, edge_nonce: bytes) -> tuple[int, bytes]:
    """The session two nonces open: its id (nonzero) and the key its frames are tagged with."""
    session_key = hmac.digest(key, b"udan/2 session" + car_nonce + edge_nonce, hashlib.sha256)
    session_id = int.from_bytes(hmac.digest(session_key, b"udan/2 id", hashlib.sha256)[:4], "big")
    return session_id if session_id else 1, session_key


def encode(
    kind: int, car_id: int, session: int, seq: int, timestamp_us: int, key: bytes, **fields: Any
) -> bytes:
    """Build and sign one frame; ``fields`` are the payload fields of ``kind`` by name.

    Handshake frames are signed with the car's key, every other frame with its session's key.
    """
    fmt, names = _PAYLOADS[kind]
    body = _HEADER.pack(VERSION, kind, fmt.size, 0, car_id, session, seq)
    body += fmt.pack(*(fields[name] for name in names))
    link = LINK_CAR_TO_EDGE if kind & 0x80 else LINK_EDGE_TO_CAR
    body += bytes([link]) + min(max(timestamp_us, 0), _MAX_U48).to_bytes(6, "big")
    return body + tag_for(key, body)
