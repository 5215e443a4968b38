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

# COMMAND guide flags (section 3): which of the target and the measured pose are given.
GUIDE_TARGET, GUIDE_POSE = 1, 2
HEADING_LIMIT_MRAD = 3142  # pi, rounded to the milliradian
POSE_AGE_LIMIT_US = 1_000_000
DELAY_LIMIT_PCT = 200  # two cell times
GUIDE_FIELDS = (
    "guide", "target_x_mm", "target_y_mm", "target_heading_mrad",
    "pose_x_mm", "pose_y_mm", "pose_heading_mrad", "pose_age_us", "delay_pct",
)  # fmt: skip

# Payload layout per type: a struct and the names of its fields, in order.
_PAYLOADS: dict[int, tuple[struct.Struct, tuple[str, ...]]] = {
    COMMAND: (
        struct.Struct(">BQBhhhhhhIB"),
        ("action", "deadline_us", *GUIDE_FIELDS),
    ),
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


@dataclass(frozen=True, slots=True)
class Guidance:
    """A command's target and measured pose in arena metres and radians (section 3), and how
    old the pose was when the edge sent the frame (None: not given)."""

    target: tuple[float, float, float] | None
    pose: tuple[float, float, float] | None
    pose_age_us: int
    delay: float = 0.0
    """Start the move this share of a cell time after accepting it."""


def guidance(payload: dict[str, Any]) -> Guidance | None:
    """The target, pose and start delay of a checked COMMAND payload; None when it carries
    none of them."""
    guide = payload["guide"]
    if not guide and not payload["delay_pct"]:
        return None

    def pose_of(prefix: str) -> tuple[float, float, float]:
        return (
            payload[f"{prefix}_x_mm"] / 1000,
            payload[f"{prefix}_y_mm"] / 1000,
            payload[f"{prefix}_heading_mrad"] / 1000,
        )

    return Guidance(
        target=pose_of("target") if guide & GUIDE_TARGET else None,
        pose=pose_of("pose") if guide & GUIDE_POSE else None,
        pose_age_us=payload["pose_age_us"],
        delay=payload["delay_pct"] / 100,
    )


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


def guide_payload(g: Guidance | None) -> dict[str, int]:
    """The COMMAND fields of ``g`` (all zero for None): the inverse of :func:`guidance`."""
    out = dict.fromkeys(GUIDE_FIELDS, 0)
    if g is None:
        return out
    for prefix, flag, pose in (("target", GUIDE_TARGET, g.target), ("pose", GUIDE_POSE, g.pose)):
        if pose is not None:
            out["guide"] |= flag
            out[f"{prefix}_x_mm"] = round(pose[0] * 1000)
            out[f"{prefix}_y_mm"] = round(pose[1] * 1000)
            out[f"{prefix}_heading_mrad"] = round(pose[2] * 1000)
    if g.pose is not None:
        out["pose_age_us"] = g.pose_age_us
    out["delay_pct"] = round(g.delay * 100)
    return out


def _check_guide(p: dict[str, Any]) -> None:
    """Target, pose and delay fields: flags known, parts not given all zero, headings within
    pi, a pose at most a second old, a start delay of at most two cell times."""
    guide = p["guide"]
    if guide & ~(GUIDE_TARGET | GUIDE_POSE):
        raise Malformed("malformed", f"unknown guide flags 0x{guide:02x}")
    parts = {
        GUIDE_TARGET: ("target_x_mm", "target_y_mm", "target_heading_mrad"),
        GUIDE_POSE: ("pose_x_mm", "pose_y_mm", "pose_heading_mrad", "pose_age_us"),
    }
    for flag, names in parts.items():
        if not guide & flag and any(p[n] for n in names):
            raise Malformed("malformed", "a target or pose field set without its flag")
    if max(abs(p["target_heading_mrad"]), abs(p["pose_heading_mrad"])) > HEADING_LIMIT_MRAD:
        raise Malformed("malformed", "heading beyond pi")
    if p["pose_age_us"] > POSE_AGE_LIMIT_US:
        raise Malformed("malformed", f"pose {p['pose_age_us']} us old")
    if p["delay_pct"] > DELAY_LIMIT_PCT:
        raise Malformed("malformed", f"start delay {p['delay_pct']} % of a cell time")


def _check_fields(kind: int, p: dict[str, Any]) -> None:
    if kind == COMMAND and p["action"] > STOP_ACTION:
        raise Malformed("malformed", f"unknown action {p['action']}")
    if kind == COMMAND:
        _check_guide(p)
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
    A COMMAND's target and pose fields default to zero (not given).
    """
    fmt, names = _PAYLOADS[kind]
    if kind == COMMAND:  # no target and no pose unless given
        fields = {**dict.fromkeys(GUIDE_FIELDS, 0), **fields}
    body = _HEADER.pack(VERSION, kind, fmt.size, 0, car_id, session, seq)
    body += fmt.pack(*(fields[name] for name in names))
    link = LINK_CAR_TO_EDGE if kind & 0x80 else LINK_EDGE_TO_CAR
    body += bytes([link]) + min(max(timestamp_us, 0), _MAX_U48).to_bytes(6, "big")
    return body + tag_for(key, body)
