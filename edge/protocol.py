"""Edge side of the car protocol (docs/protocol.md): frames out, events in, per-car sessions.

Sans-I/O: no sockets, no asyncio, and the clock is injected (``clock()`` returns nanoseconds,
``time.monotonic_ns`` by default), so the transports (UDP, serial, CAN) and the tests drive the
same rules. ``EdgeProtocol.receive`` never raises on bad input: every frame becomes an event, and a
frame that fails a check becomes ``Rejected`` with the reason. Frames the protocol sends of its
own accord (ACCEPT answering a JOIN, HELLO asking an unknown car to join, a renewal before the
counters run out) wait in ``datagrams_to_send``.

A session is keyed by two fresh nonces, the car's (in its JOIN) and the edge's (in its ACCEPT),
so no frame of any earlier session, either side's, authenticates in a new one, and a new edge
process needs nothing of the old one. Per car it keeps the current session (sequence numbers,
replay window), the one it replaced (for a short overlap), the sessions offered but not yet
confirmed by the car, and the car clock offset from time sync, used to write each command's
validity deadline in the car's clock.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import secrets
import struct
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag

PROTOCOL_VERSION = 2
KEY_BYTES = 32
NONCE_BYTES = 16
TAG_BYTES = 6
TIME_WINDOW_US = 60_000_000
DEFAULT_VALIDITY_NS = 10_000_000  # the dispatch deadline of the design: 10 ms
DRIFT_PPM = 50  # bound on crystal drift between edge and car, widens the deadline margin
REPLAY_WINDOW = 64  # car frames may arrive this far out of order and still be taken
SEQ_MAX = (1 << 32) - 1
RENEW_AT = SEQ_MAX - (1 << 16)  # a side asks for a new session when its counter gets here
PENDING_OFFERS = 4  # sessions offered (ACCEPT sent) and not yet confirmed, kept per car
PREVIOUS_GRACE_NS = 1_000_000_000  # a replaced session's frames are still taken this long
LIVE_NS = 500_000_000  # a session heard from within this long is live
HELLO_INTERVAL_NS = 100_000_000  # at most one HELLO per car this often
ANSWER_BURST = 8  # answers to frames anyone could have recorded: burst, then ...
ANSWER_INTERVAL_NS = 10_000_000  # ... one per 10 ms on average
_WINDOW_MASK = (1 << REPLAY_WINDOW) - 1


class MsgType(IntEnum):
    """Message type byte; the high bit marks car -> edge."""

    COMMAND = 0x01
    ESTOP = 0x02
    TIME_REQUEST = 0x03
    HELLO = 0x04
    ACCEPT = 0x05
    ACK = 0x81
    STATUS = 0x82
    JOIN = 0x83
    LEAVE = 0x84
    TIME_RESPONSE = 0x85


HANDSHAKE = frozenset({MsgType.HELLO, MsgType.ACCEPT, MsgType.JOIN})


class Action(IntEnum):
    """Command actions: 0-4 are ``udan.envs.rules.ACTIONS`` in order, STOP halts the motors."""

    UP = 0
    DOWN = 1
    LEFT = 2
    RIGHT = 3
    WAIT = 4
    STOP = 5


class AckResult(IntEnum):
    """What the car did with a frame it authenticated."""

    ACCEPTED = 0
    DUPLICATE = 1
    REPLAY = 2
    EXPIRED = 3
    BAD_TIME = 4
    ESTOPPED = 5


class JoinCause(IntEnum):
    """Why a car sent JOIN: it booted, a HELLO asked, or its counter nears the end."""

    BOOT = 0
    HELLO = 1
    RENEW = 2


class HelloReason(IntEnum):
    """Why the edge sent HELLO: it holds no session the car uses, or its counter nears the end."""

    UNKNOWN_SESSION = 0
    RENEW = 1


class Fault(IntFlag):
    """Status fault flags."""

    NONE = 0
    WATCHDOG = 1
    ESTOP = 2
    STALL = 4
    LOW_BATTERY = 8


_HEAD = struct.Struct(">BBBBHII")
_HEAD_LEN = _HEAD.size
_TAIL_LEN = 1 + 6 + TAG_BYTES
_NO_ACTION = 0xFF
GUIDE_TARGET = 1  # COMMAND ``guide`` flag: the target fields are given
GUIDE_POSE = 2  # ... the measured pose fields are given
MAX_HEADING_MRAD = 3142  # round(1000 pi): headings are in -pi..pi
MAX_POSE_AGE_US = 1_000_000  # a pose older than a car may hold a command is useless
MAX_DELAY_PCT = 200  # a start delay of at most two cell times
_TARGET_FIELDS = ("target_x_mm", "target_y_mm", "target_heading_mrad")
_POSE_FIELDS = ("pose_x_mm", "pose_y_mm", "pose_heading_mrad", "pose_age_us")
_I16 = 32767
_LAYOUT: dict[MsgType, tuple[struct.Struct, tuple[str, ...]]] = {
    MsgType.COMMAND: (
        struct.Struct(">BQBhhhhhhIB"),
        ("action", "deadline_us", "guide", *_TARGET_FIELDS, *_POSE_FIELDS, "delay_pct"),
    ),
    MsgType.ESTOP: (struct.Struct(">BQ"), ("engage", "deadline_us")),
    MsgType.TIME_REQUEST: (struct.Struct(">Q"), ("t1_ns",)),
    MsgType.HELLO: (struct.Struct(">B"), ("reason",)),
    MsgType.ACCEPT: (struct.Struct(">16s16sB"), ("car_nonce", "edge_nonce", "version")),
    MsgType.ACK: (struct.Struct(">IBBQ"), ("ref_seq", "result", "action", "rx_us")),
    MsgType.STATUS: (
        struct.Struct(">hhHHBI"),
        ("row", "col", "battery_mv", "faults", "state", "done_seq"),
    ),
    MsgType.JOIN: (
        struct.Struct(">HBBB16s"),
        ("marker", "cause", "min_version", "max_version", "car_nonce"),
    ),
    MsgType.LEAVE: (struct.Struct(">B"), ("reason",)),
    MsgType.TIME_RESPONSE: (struct.Struct(">QQQ"), ("t1_ns", "t2_us", "t3_us")),
}
LEAVE_REASONS = ("shutdown", "low_battery", "fault")

Fields = dict[str, int | bytes]


class FrameError(ValueError):
    """A frame that breaks the spec's structure; ``reason`` is malformed or wrong_version."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


class NotReady(RuntimeError):
    """A frame was asked for a car that has not joined (or whose clock is not synchronised)."""


Pose = tuple[float, float, float]
"""Arena metres x (along the columns), y (along the rows), heading in radians (0 = -y, growing
clockwise), as the vision measures them (spec section 3)."""


@dataclass(frozen=True, slots=True)
class Guidance:
    """What a COMMAND tells a car besides its action: where its move must end (``target``) and,
    when the camera saw it, where it was (``pose``, in a frame captured at ``captured_ns`` in the
    edge clock), so its controller drives from where it is to where it should be and errors do
    not add up (spec section 8)."""

    target: Pose
    pose: Pose | None = None
    captured_ns: int = 0
    delay: float = 0.0
    """Start the move this share of a cell time after accepting it (a car that enters a cell
    another car leaves sideways waits for that car's body to clear its path; one following
    another straight starts a little after it)."""


def _mrad(heading: float) -> int:
    """A heading in milliradians, wrapped into -pi..pi first."""
    return round(1000 * math.remainder(heading, math.tau))


def _mm(metres: float) -> int:
    return round(1000 * metres)


def guide_fields(guidance: Guidance | None, now_ns: int) -> dict[str, int]:
    """The COMMAND fields of ``guidance`` at edge time ``now_ns``. A pose that cannot be sent
    (captured more than 1 s ago, or outside the 16-bit millimetre range) is left out; a target
    outside that range, or a start delay beyond two cell times, is a ``ValueError`` (a bug,
    not a measurement)."""
    fields = dict.fromkeys(("guide", *_TARGET_FIELDS, *_POSE_FIELDS, "delay_pct"), 0)
    if guidance is None:
        return fields
    delay = round(100 * guidance.delay)
    if not 0 <= delay <= MAX_DELAY_PCT:
        raise ValueError(f"start delay {guidance.delay} cell times outside 0-2")
    fields["delay_pct"] = delay
    target = (_mm(guidance.target[0]), _mm(guidance.target[1]))
    if max(map(abs, target)) > _I16:
        raise ValueError(f"target {guidance.target[:2]} m outside the 16-bit millimetre range")
    fields.update(
        guide=GUIDE_TARGET,
        target_x_mm=target[0],
        target_y_mm=target[1],
        target_heading_mrad=_mrad(guidance.target[2]),
    )
    age_us = (now_ns - guidance.captured_ns) // 1000
    if guidance.pose is not None and 0 <= age_us <= MAX_POSE_AGE_US:
        pose = (_mm(guidance.pose[0]), _mm(guidance.pose[1]))
        if max(map(abs, pose)) <= _I16:
            fields.update(
                guide=GUIDE_TARGET | GUIDE_POSE,
                pose_x_mm=pose[0],
                pose_y_mm=pose[1],
                pose_heading_mrad=_mrad(guidance.pose[2]),
                pose_age_us=age_us,
            )
    return fields


@dataclass(frozen=True, slots=True)
class Decoded:
    """A structurally valid frame; its tag is not checked yet."""

    type: MsgType
    car_id: int
    session: int
    seq: int
    link_id: int
    timestamp_us: int
    tag: bytes
    fields: Fields
    signed: bytes

    def as_vector(self) -> dict[str, object]:
        """Same shape as the ``decoded`` objects in docs/protocol_vectors.json."""
        return {
            "type": self.type.name.lower(),
            "car_id": self.car_id,
            "session": self.session,
            "seq": self.seq,
            "link_id": self.link_id,
            "timestamp_us": self.timestamp_us,
            "tag": self.tag.hex(),
            "payload": {k: v.hex() if isinstance(v, bytes) else v for k, v in self.fields.items()},
        }


def _guide_ok(f: Fields) -> bool:
    """A COMMAND's target, pose and delay fields (spec section 3): known flags, headings within
    ±pi, a pose at most 1 s old, the fields of an absent part all zero, a start delay of at
    most two cell times."""
    guide = f["guide"]
    if guide & ~(GUIDE_TARGET | GUIDE_POSE):
        return False
    for flag, fields in ((GUIDE_TARGET, _TARGET_FIELDS), (GUIDE_POSE, _POSE_FIELDS)):
        if not guide & flag and any(f[name] for name in fields):
            return False
    headings = (f["target_heading_mrad"], f["pose_heading_mrad"])
    return (
        all(abs(h) <= MAX_HEADING_MRAD for h in headings)
        and f["pose_age_us"] <= MAX_POSE_AGE_US
        and f["delay_pct"] <= MAX_DELAY_PCT
    )


def _field_error(kind: MsgType, f: Fields) -> str | None:
    if kind == MsgType.COMMAND and not _guide_ok(f):
        return "COMMAND target or pose field out of range"
    checks = {
        MsgType.COMMAND: f.get("action", 0) <= Action.STOP,
        MsgType.ESTOP: f.get("engage", 0) in (0, 1),
        MsgType.HELLO: f.get("reason", 0) <= HelloReason.RENEW,
        MsgType.ACK: f.get("result", 0) <= AckResult.ESTOPPED
        and (f.get("action", 0) <= Action.STOP or f.get("action") == _NO_ACTION),
        MsgType.STATUS: f.get("state", 0) in (0, 1) and f.get("faults", 0) < 16,
        MsgType.JOIN: f.get("cause", 0) <= JoinCause.RENEW
        and f.get("min_version", 0) <= f.get("max_version", 0),
        MsgType.LEAVE: f.get("reason", 0) < len(LEAVE_REASONS),
    }
    return None if checks.get(kind, True) else f"{kind.name} field out of range"


def decode(data: bytes) -> Decoded:
    """Parse one frame (any direction) or raise ``FrameError``."""
    if len(data) == 0:
        raise FrameError("malformed", "empty")
    if data[0] != PROTOCOL_VERSION:
        raise FrameError(
            "wrong_version", f"protocol v{data[0]} frame, this edge speaks v{PROTOCOL_VERSION}"
        )
    if len(data) < _HEAD_LEN + _TAIL_LEN:
        raise FrameError("malformed", "truncated")
    _, raw_type, plen, flags, car_id, session, seq = _HEAD.unpack_from(data)
    try:
        kind = MsgType(raw_type)
    except ValueError:
        raise FrameError("malformed", f"type 0x{raw_type:02x}") from None
    fmt, names = _LAYOUT[kind]
    if plen != fmt.size or len(data) != _HEAD_LEN + fmt.size + _TAIL_LEN:
        raise FrameError("malformed", "bad length")
    if flags or car_id == 0 or car_id == 0xFFFF:
        raise FrameError("malformed", "reserved header value")
    handshake = kind in HANDSHAKE
    if (session != 0 or seq != 0) if handshake else (session == 0 or seq == 0):
        raise FrameError("malformed", "session and seq are 0 on handshake frames only")
    link_id = data[_HEAD_LEN + plen]
    if link_id != (1 if raw_type & 0x80 else 0):
        raise FrameError("malformed", "link id does not match direction")
    fields: Fields = dict(zip(names, fmt.unpack_from(data, _HEAD_LEN), strict=True))
    if (problem := _field_error(kind, fields)) is not None:
        raise FrameError("malformed", problem)
    ts_at = _HEAD_LEN + plen + 1
    return Decoded(
        type=kind,
        car_id=car_id,
        session=session,
        seq=seq,
        link_id=link_id,
        timestamp_us=int.from_bytes(data[ts_at : ts_at + 6], "big"),
        tag=bytes(data[len(data) - TAG_BYTES :]),
        fields=fields,
        signed=bytes(data[: len(data) - TAG_BYTES]),
    )


def fresh_nonce() -> bytes:
    """A session nonce from the operating system's CSPRNG (never from a seed)."""
    return secrets.token_bytes(NONCE_BYTES)


def compute_tag(key: bytes, signed: bytes) -> bytes:
    """HMAC-SHA256 truncated to 48 bits, as MAVLink 2 signing truncates its SHA-256."""
    return hmac.digest(key, signed, hashlib.sha256)[:TAG_BYTES]


def derive_session(key: bytes, car_nonce: bytes, edge_nonce: bytes) -> tuple[int, bytes]:
    """``(session id, session key)`` of the session the two nonces open (spec section 6)."""
    session_key = hmac.digest(key, b"udan/2 session" + car_nonce + edge_nonce, hashlib.sha256)
    label = hmac.digest(session_key, b"udan/2 id", hashlib.sha256)[:4]
    return int.from_bytes(label, "big") or 1, session_key


def encode(
    kind: MsgType,
    car_id: int,
    session: int,
    seq: int,
    timestamp_us: int,
    key: bytes,
    fields: Mapping[str, int | bytes],
) -> bytes:
    """Serialise and sign a frame of any type (the edge sends 0x01-0x05; tests build the rest).

    ``key`` is the car's key for handshake frames (session and seq 0), else the session key.
    A COMMAND's target and pose fields default to zero (not given).
    """
    fmt, names = _LAYOUT[kind]
    if kind == MsgType.COMMAND:
        fields = {**guide_fields(None, 0), **fields}
    out = bytearray(_HEAD.pack(PROTOCOL_VERSION, kind, fmt.size, 0, car_id, session, seq))
    out += fmt.pack(*[fields[n] for n in names])
    out.append(1 if kind & 0x80 else 0)
    out += max(0, min(timestamp_us, (1 << 48) - 1)).to_bytes(6, "big")
    return bytes(out + compute_tag(key, bytes(out)))


# --- CAN FD mapping (spec section 10) --------------------------------------------------------
CAN_ESTOP_BASE = 0x080
CAN_EDGE_BASE = 0x100
CAN_CAR_BASE = 0x180
CAN_MAX_CAR = 0x7F
_FD_SIZES = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)


def can_pack(frame: bytes) -> tuple[int, bytes]:
    """``(11-bit id, CAN FD data)`` for one frame: id by direction and car, data zero-padded."""
    kind, car_id = frame[1], int.from_bytes(frame[4:6], "big")
    if not 0 < car_id <= CAN_MAX_CAR:
        raise ValueError(f"car id {car_id} does not fit the CAN mapping (1-{CAN_MAX_CAR})")
    if kind & 0x80:
        base = CAN_CAR_BASE
    else:
        base = CAN_ESTOP_BASE if kind == MsgType.ESTOP else CAN_EDGE_BASE
    size = next(s for s in _FD_SIZES if s >= len(frame))
    return base + car_id, frame + bytes(size - len(frame))


def can_unpack(can_id: int, data: bytes) -> bytes:
    """The frame inside a CAN FD payload; ``FrameError`` if the padding or the id disagree."""
    if len(data) < 3:
        raise FrameError("malformed", "CAN payload too short")
    length = _HEAD_LEN + data[2] + _TAIL_LEN
    frame, padding = bytes(data[:length]), data[length:]
    if len(frame) != length or any(padding):
        raise FrameError("malformed", "CAN padding")
    try:
        expected = can_pack(frame)[0]
    except ValueError:
        raise FrameError("malformed", "car id outside the CAN range") from None
    if expected != can_id:
        raise FrameError("malformed", f"frame does not belong on CAN id 0x{can_id:03x}")
    return frame


# --- events ------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Joining:
    """A car asked for a session (JOIN); the edge answered with an offer (ACCEPT).

    Nothing changes until the car confirms the offer with its first frame in the new session:
    a JOIN replayed from an earlier session gets an offer its car never takes.
    """

    car_id: int
    marker: int
    cause: JoinCause


@dataclass(frozen=True, slots=True)
class Acked:
    """The car's answer to one edge frame."""

    car_id: int
    session: int  # the session of the ACK, and so of the frame it answers
    ref_seq: int
    result: AckResult
    action: int | None
    car_rx_us: int
    received_at_ns: int  # car receive time in the edge clock (estimate)
    round_trip_ns: int | None  # send -> ack, when ``ref_seq`` is a frame this core encoded


@dataclass(frozen=True, slots=True)
class StatusReport:
    """A car's heartbeat; ``done_seq`` counts in ``session``."""

    car_id: int
    session: int
    row: int
    col: int
    battery_mv: int
    faults: Fault
    moving: bool
    done_seq: int
    car_time_us: int


@dataclass(frozen=True, slots=True)
class Joined:
    """A new session is confirmed. ``reboot``: the car restarted, its clock must be synced again.

    ``previous_session`` is the session it replaces at this edge (None for a car new to it);
    ``status`` is the frame that confirmed it, when that was a STATUS (as a car sends first).
    """

    car_id: int
    marker: int
    session: int
    previous_session: int | None
    reboot: bool
    status: StatusReport | None = None


@dataclass(frozen=True, slots=True)
class Left:
    """A car said goodbye; it must JOIN again to be driven."""

    car_id: int
    reason: str


@dataclass(frozen=True, slots=True)
class TimeSynced:
    """A time-sync round trip finished; ``offset_ns`` = car clock - edge clock (best sample)."""

    car_id: int
    offset_ns: int
    rtt_ns: int


@dataclass(frozen=True, slots=True)
class Rejected:
    """An incoming frame that was dropped, and why (``detail``: the one line to log, if any)."""

    reason: str
    car_id: int | None = None
    detail: str = field(default="", compare=False)


Event = Joining | Joined | Acked | StatusReport | Left | TimeSynced | Rejected


@dataclass(frozen=True, slots=True)
class _Sample:
    offset_ns: int
    rtt_ns: int
    at_ns: int


@dataclass
class _Session:
    """One session's key and counters, on the edge's side."""

    id: int
    key: bytes
    tx_seq: int = 0
    rx_seq: int = 0
    seen: int = 0  # bit i: rx_seq - i was received
    sent_at: OrderedDict[int, int] = field(default_factory=OrderedDict)

    def fresh(self, seq: int) -> bool:
        """Anti-replay window (RFC 4303 style): a new seq, or an unseen one of the last 64."""
        if seq > self.rx_seq:
            jump = seq - self.rx_seq  # bounded: a shift by billions of bits takes seconds
            self.seen = ((self.seen << jump) | 1) & _WINDOW_MASK if jump < REPLAY_WINDOW else 1
            self.rx_seq = seq
            return True
        back = self.rx_seq - seq
        if back >= REPLAY_WINDOW or self.seen >> back & 1:
            return False
        self.seen |= 1 << back
        return True


@dataclass
class _Offer:
    """A session offered to a car (ACCEPT sent), waiting for the car's first frame in it."""

    session: _Session
    accept: bytes
    marker: int
    cause: JoinCause
    offset_ns: int  # provisional car clock offset, from the JOIN's timestamp


class _Answers:
    """Token bucket: answers to frames anyone could have recorded stay few (no amplifier)."""

    def __init__(self, burst: int, interval: int) -> None:
        self.burst, self.interval = burst, interval
        self.tokens = burst
        self.at: int | None = None

    def take(self, now: int) -> bool:
        """Spend one answer if the bucket holds one (it refills one per ``interval``)."""
        if self.at is None or self.tokens == self.burst:
            self.at = now  # a full bucket banks no time
        gained = (now - self.at) // self.interval
        if gained > 0:
            self.tokens = min(self.burst, self.tokens + gained)
            self.at += gained * self.interval
        if self.tokens == 0:
            return False
        self.tokens -= 1
        return True


@dataclass
class _Peer:
    key: bytes
    answers: _Answers
    marker: int = 0
    current: _Session | None = None
    previous: _Session | None = None
    previous_until_ns: int = 0
    offers: OrderedDict[bytes, _Offer] = field(default_factory=OrderedDict)
    heard_ns: int | None = None  # last authenticated frame of the current session
    hello_ns: int | None = None  # last HELLO sent
    provisional_offset_ns: int = 0
    samples: deque[_Sample] = field(default_factory=lambda: deque(maxlen=8))
    pending_sync: OrderedDict[int, int] = field(default_factory=OrderedDict)

    def session_of(self, session_id: int, now: int) -> tuple[_Session, _Offer | None] | None:
        """The session a car frame claims, with its offer if it is not confirmed yet."""
        if self.current is not None and session_id == self.current.id:
            return self.current, None
        if (
            self.previous is not None
            and session_id == self.previous.id
            and now < self.previous_until_ns
        ):
            return self.previous, None
        for offer in self.offers.values():
            if offer.session.id == session_id:
                return offer.session, offer
        return None

    def live(self, now: int) -> bool:
        """The car has been heard in its current session lately."""
        return self.heard_ns is not None and now - self.heard_ns <= LIVE_NS

    def best(self) -> _Sample | None:
        return min(self.samples, key=lambda s: s.rtt_ns, default=None)

    def offset_ns(self) -> int:
        best = self.best()
        return self.provisional_offset_ns if best is None else best.offset_ns


def _status_report(d: Decoded) -> StatusReport:
    f = d.fields
    return StatusReport(
        car_id=d.car_id,
        session=d.session,
        row=f["row"],
        col=f["col"],
        battery_mv=f["battery_mv"],
        faults=Fault(f["faults"]),
        moving=bool(f["state"]),
        done_seq=f["done_seq"],
        car_time_us=d.timestamp_us,
    )


def _remember(table: OrderedDict, k: object, v: object, limit: int) -> None:
    table[k] = v
    while len(table) > limit:
        table.popitem(last=False)


class EdgeProtocol:
    """Protocol state for every car the edge holds a key for."""

    def __init__(
        self,
        keys: Mapping[int, bytes],
        clock: Callable[[], int] = time.monotonic_ns,
        *,
        drift_ppm: int = DRIFT_PPM,
        nonce: Callable[[], bytes] = fresh_nonce,
    ) -> None:
        self._clock = clock
        self._drift_ppm = drift_ppm
        self._nonce = nonce
        self._peers: dict[int, _Peer] = {}
        self._outbox: list[tuple[int, bytes]] = []
        for car_id, key in keys.items():
            self.add_car(car_id, key)

    def add_car(self, car_id: int, key: bytes) -> None:
        """Provision a car's key; the car can then JOIN at any time."""
        if not 0 < car_id < 0xFFFF:
            raise ValueError(f"car id {car_id} outside 1-65534")
        if len(key) != KEY_BYTES:
            raise ValueError(f"car {car_id}: key must be {KEY_BYTES} bytes, got {len(key)}")
        self._peers[car_id] = _Peer(bytes(key), _Answers(ANSWER_BURST, ANSWER_INTERVAL_NS))

    # --- queries ---
    def joined(self, car_id: int) -> bool:
        """The car confirmed a session with this edge (and has not left)."""
        peer = self._peers.get(car_id)
        return peer is not None and peer.current is not None

    def synced(self, car_id: int) -> bool:
        """A time-sync round trip completed since the car's last boot."""
        peer = self._peers.get(car_id)
        return peer is not None and peer.current is not None and bool(peer.samples)

    def joined_cars(self) -> list[int]:
        """Ids of the cars currently joined."""
        return sorted(c for c, p in self._peers.items() if p.current is not None)

    def session(self, car_id: int) -> int:
        """The car's current session id (0 if it has not joined)."""
        current = self._peers[car_id].current
        return 0 if current is None else current.id

    def sync_age_ns(self, car_id: int) -> int | None:
        """Time since the best time-sync sample, to decide when to sync again."""
        best = self._peers[car_id].best()
        return None if best is None else self._clock() - best.at_ns

    def car_time_us(self, car_id: int, edge_ns: int | None = None) -> int:
        """The car's clock at edge time ``edge_ns`` (default now), in microseconds."""
        peer = self._peers[car_id]
        now = self._clock() if edge_ns is None else edge_ns
        return (now + peer.offset_ns()) // 1000

    def datagrams_to_send(self) -> list[tuple[int, bytes]]:
        """``(car id, frame)`` sent of the protocol's own accord (ACCEPT, HELLO), oldest first."""
        out, self._outbox = self._outbox, []
        return out

    # --- frames out ---
    def _peer_for_send(self, car_id: int, need_sync: bool) -> tuple[_Peer, _Session]:
        peer = self._peers.get(car_id)
        if peer is None or peer.current is None:
            raise NotReady(f"car {car_id} has not joined")
        if need_sync and not peer.samples:
            raise NotReady(f"car {car_id}: clock not synchronised yet")
        if peer.current.tx_seq >= SEQ_MAX:
            raise NotReady(f"car {car_id}: sequence numbers used up, session being renewed")
        return peer, peer.current

    def _hello(self, car_id: int, peer: _Peer, now: int, reason: HelloReason) -> None:
        if peer.hello_ns is not None and now - peer.hello_ns < HELLO_INTERVAL_NS:
            return
        peer.hello_ns = now
        frame = encode(MsgType.HELLO, car_id, 0, 0, 0, peer.key, {"reason": reason})
        self._outbox.append((car_id, frame))

    def _frame(self, car_id: int, kind: MsgType, now: int, **fields: int) -> bytes:
        peer, session = self._peers[car_id], self._peers[car_id].current
        assert session is not None
        session.tx_seq += 1
        if session.tx_seq >= RENEW_AT:
            self._hello(car_id, peer, now, HelloReason.RENEW)
        _remember(session.sent_at, session.tx_seq, now, 64)
        ts = (now + peer.offset_ns()) // 1000
        return encode(kind, car_id, session.id, session.tx_seq, ts, session.key, fields)

    def _deadline_us(self, peer: _Peer, now: int, validity_ns: int) -> int:
        """Edge deadline in the car clock, pulled in by the sync uncertainty (rtt/2 + drift).

        Spec section 7: integer nanoseconds throughout, rtt/2 rounded down, the drift term
        rounded up, and the result floored to microseconds, so rounding only moves it earlier.
        """
        best = peer.best()
        if best is None:
            return max(0, now + validity_ns + peer.provisional_offset_ns) // 1000
        drift = -(-(now - best.at_ns) * self._drift_ppm // 1_000_000)
        margin = best.rtt_ns // 2 + drift
        return max(0, now + validity_ns + best.offset_ns - margin) // 1000

    def encode_command(
        self,
        car_id: int,
        action: int,
        validity_ns: int = DEFAULT_VALIDITY_NS,
        guidance: Guidance | None = None,
    ) -> bytes:
        """A signed COMMAND valid for ``validity_ns`` from now (needs a synchronised clock),
        with its target and measured pose when ``guidance`` is given (the pose's age counted
        to now)."""
        act = Action(action)
        peer, _ = self._peer_for_send(car_id, need_sync=True)
        now = self._clock()
        guide = guide_fields(guidance, now)
        deadline = self._deadline_us(peer, now, validity_ns)
        return self._frame(car_id, MsgType.COMMAND, now, action=act, deadline_us=deadline, **guide)

    def encode_estop(
        self, car_id: int, engage: bool = True, validity_ns: int = DEFAULT_VALIDITY_NS
    ) -> bytes:
        """ESTOP engage (the car ignores its deadline) or release (needs a synchronised clock)."""
        peer, _ = self._peer_for_send(car_id, need_sync=not engage)
        now = self._clock()
        deadline = self._deadline_us(peer, now, validity_ns)
        return self._frame(car_id, MsgType.ESTOP, now, engage=int(engage), deadline_us=deadline)

    def encode_estop_all(self, engage: bool = True) -> dict[int, bytes]:
        """One ESTOP per joined car (keys are per car, so there is no broadcast frame)."""
        return {c: self.encode_estop(c, engage) for c in self.joined_cars()}

    def encode_time_request(self, car_id: int) -> bytes:
        """TIME_REQUEST carrying the edge send time; the response gives offset and round trip."""
        peer, session = self._peer_for_send(car_id, need_sync=False)
        now = self._clock()
        frame = self._frame(car_id, MsgType.TIME_REQUEST, now, t1_ns=now)
        _remember(peer.pending_sync, now, session.tx_seq, 8)
        return frame

    # --- frames in ---
    def receive(self, data: bytes) -> Event:
        """Judge one frame from a car; never raises."""
        now = self._clock()
        try:
            d = decode(data)
        except FrameError as err:
            if err.reason != "wrong_version":
                return Rejected(err.reason)
            claimed = int.from_bytes(data[4:6], "big") if len(data) >= 6 else None
            car_id = claimed if claimed in self._peers else None
            who = "a sender without a key" if car_id is None else f"car {car_id}"
            return Rejected(err.reason, car_id, f"{who} sent a {err.detail}: refused")
        if not d.type & 0x80:
            return Rejected("malformed", d.car_id)
        peer = self._peers.get(d.car_id)
        if peer is None:
            return Rejected("unknown_car", d.car_id)
        if d.type == MsgType.JOIN:
            return self._on_join(d, peer, now)
        found = peer.session_of(d.session, now)
        if found is None:
            if peer.current is None or not peer.live(now):
                self._hello(d.car_id, peer, now, HelloReason.UNKNOWN_SESSION)
            return Rejected("not_joined" if peer.current is None else "wrong_session", d.car_id)
        session, offer = found
        if not hmac.compare_digest(compute_tag(session.key, d.signed), d.tag):
            return Rejected("bad_tag", d.car_id)
        if not session.fresh(d.seq):
            return Rejected("replay", d.car_id)
        if offer is not None:
            status = _status_report(d) if d.type == MsgType.STATUS else None
            return self._confirm(d.car_id, peer, offer, now, status)
        if session is peer.current:
            peer.heard_ns = now
        if abs(d.timestamp_us - (now + peer.offset_ns()) // 1000) > TIME_WINDOW_US:
            return Rejected("bad_time", d.car_id)
        f = d.fields
        if d.type == MsgType.ACK:
            sent = session.sent_at.get(f["ref_seq"])
            return Acked(
                car_id=d.car_id,
                session=d.session,
                ref_seq=f["ref_seq"],
                result=AckResult(f["result"]),
                action=None if f["action"] == _NO_ACTION else f["action"],
                car_rx_us=f["rx_us"],
                received_at_ns=f["rx_us"] * 1000 - peer.offset_ns(),
                round_trip_ns=None if sent is None else now - sent,
            )
        if d.type == MsgType.STATUS:
            return _status_report(d)
        if d.type == MsgType.LEAVE:
            peer.current = peer.previous = None
            peer.heard_ns = None
            return Left(d.car_id, LEAVE_REASONS[f["reason"]])
        return self._on_time_response(d, peer, now)

    def _on_join(self, d: Decoded, peer: _Peer, now: int) -> Event:
        if not hmac.compare_digest(compute_tag(peer.key, d.signed), d.tag):
            return Rejected("bad_tag", d.car_id)
        f = d.fields
        if not f["min_version"] <= PROTOCOL_VERSION <= f["max_version"]:
            detail = (
                f"car {d.car_id} speaks protocol v{f['min_version']}-v{f['max_version']}, "
                f"this edge v{PROTOCOL_VERSION}: refused"
            )
            return Rejected("wrong_version", d.car_id, detail)
        cause = JoinCause(f["cause"])
        asked = peer.hello_ns is not None and now - peer.hello_ns <= LIVE_NS
        if cause == JoinCause.HELLO and peer.live(now) and not asked:
            return Rejected("unsolicited", d.car_id)  # a replayed HELLO made the car ask
        car_nonce = bytes(f["car_nonce"])
        offer = peer.offers.get(car_nonce)
        if not peer.answers.take(now):
            return Rejected("rate_limited", d.car_id)
        if offer is None:
            edge_nonce = self._nonce()
            session_id, session_key = derive_session(peer.key, car_nonce, edge_nonce)
            ts = d.timestamp_us
            fields = {"car_nonce": car_nonce, "edge_nonce": edge_nonce, "version": 2}
            accept = encode(MsgType.ACCEPT, d.car_id, 0, 0, ts, peer.key, fields)
            offer = _Offer(
                _Session(session_id, session_key), accept, f["marker"], cause, ts * 1000 - now
            )
            _remember(peer.offers, car_nonce, offer, PENDING_OFFERS)
        self._outbox.append((d.car_id, offer.accept))
        return Joining(d.car_id, f["marker"], cause)

    def _confirm(
        self, car_id: int, peer: _Peer, offer: _Offer, now: int, status: StatusReport | None
    ) -> Joined:
        """The car's first frame in an offered session: it becomes the current one."""
        previous = peer.current
        reboot = offer.cause == JoinCause.BOOT
        peer.previous = None if reboot else previous
        peer.previous_until_ns = now + PREVIOUS_GRACE_NS
        peer.current = offer.session
        peer.offers.clear()
        peer.heard_ns = now
        peer.marker = offer.marker
        if reboot or previous is None:
            peer.provisional_offset_ns = offer.offset_ns
        if reboot:
            peer.samples.clear()
            peer.pending_sync.clear()
        return Joined(
            car_id,
            offer.marker,
            offer.session.id,
            None if previous is None else previous.id,
            reboot=reboot and previous is not None,
            status=status,
        )

    def _on_time_response(self, d: Decoded, peer: _Peer, now: int) -> Event:
        t1 = d.fields["t1_ns"]
        if t1 not in peer.pending_sync:
            return Rejected("unsolicited", d.car_id)
        del peer.pending_sync[t1]
        t2, t3 = d.fields["t2_us"] * 1000, d.fields["t3_us"] * 1000
        rtt = (now - t1) - (t3 - t2)
        if rtt < 0 or t3 < t2:
            return Rejected("bad_time", d.car_id)
        offset = ((t2 - t1) + (t3 - now)) // 2
        peer.samples.append(_Sample(offset, rtt, now))
        best = min(peer.samples, key=lambda s: s.rtt_ns)
        return TimeSynced(d.car_id, best.offset_ns, best.rtt_ns)
