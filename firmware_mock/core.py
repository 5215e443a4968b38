"""The car's sans-I/O protocol core: what the firmware accepts, what it answers, when it stops.

No sockets and no clock of its own: the driver (UDP ESP8266 mock, CAN motor controller) passes the
car's clock in microseconds since boot to every call, so the same rules run in tests with a fake
clock and in the mock processes with ``time.monotonic_ns``. The checks run in the order given in
docs/protocol.md section 4, and the first failing check is the reason counted.

Sessions are opened by a handshake (section 6): the car's JOIN carries a fresh nonce, the edge's
ACCEPT echoes it with one of its own, and both derive the session's id and key from the pair.
Nonces come from ``secrets`` (the hardware RNG on a real car), never from a seed.
"""

from __future__ import annotations

import secrets
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

from udan.firmware_mock import wire

REJECT_REASONS = (
    "malformed",
    "wrong_version",
    "unknown_car",
    "bad_tag",
    "wrong_session",
    "replay",
    "expired",
    "bad_time",
    "estopped",
    "stale_accept",
)
TIME_WINDOW_US = 60_000_000  # MAVLink 2 signing's one-minute window
MAX_VALIDITY_US = 1_000_000  # a deadline further ahead than this is refused as bad_time
WATCHDOG_US = 300_000
CELL_TIME_US = 200_000  # a start delay is counted in cell times (section 3)
DUPLICATE_CACHE = 16
SEQ_MAX = (1 << 32) - 1
RENEW_AT = SEQ_MAX - (1 << 16)  # from here on the car asks for a new session
RENEW_PERIOD_US = 250_000  # how often it asks again
ANSWER_BURST = 8  # answers to duplicates, replays and HELLOs: a burst of 8, ...
ANSWER_INTERVAL_US = 10_000  # ... then one per 10 ms


@dataclass
class Counters:
    """What a test or the HIL harness reads off a mock car; kept across reboots."""

    received: int = 0
    accepted: int = 0
    duplicates: int = 0
    rejected: Counter[str] = field(default_factory=Counter)
    watchdog_stops: int = 0
    sent: int = 0
    reboots: int = 0
    unanswered: int = 0
    sessions: list[int] = field(default_factory=list)

    def as_dict(self) -> dict[str, object]:
        """Plain JSON-able form, every reject reason present (zero when never seen)."""
        return {
            "received": self.received,
            "accepted": self.accepted,
            "duplicates": self.duplicates,
            "rejected": {r: self.rejected[r] for r in REJECT_REASONS},
            "watchdog_stops": self.watchdog_stops,
            "sent": self.sent,
            "reboots": self.reboots,
            "unanswered": self.unanswered,
            "sessions": list(self.sessions),
        }


@dataclass(frozen=True, slots=True)
class Telemetry:
    """What the motor controller last reported, for status frames."""

    row: int = 0
    col: int = 0
    battery_mv: int = 8200
    moving: bool = False
    stalled: bool = False
    low_battery: bool = False
    done_seq: int = 0


@dataclass(frozen=True, slots=True)
class Outcome:
    """The verdict on one incoming frame, the frames to send back, and the order for the motors.

    ``motor`` is ``(seq, action)`` of an accepted command (``wire.STOP_ACTION`` stops at once),
    ``guidance`` its target and measured pose if it carries them; ``halt`` says an emergency
    stop was engaged: stop the motors now. Verdict ``joined``: a new session is open, and the
    driver confirms it with a STATUS at once (section 6).
    """

    verdict: str
    replies: tuple[bytes, ...] = ()
    motor: tuple[int, int] | None = None
    halt: bool = False
    guidance: wire.Guidance | None = None


class _Session:
    """One session's key and counters, on the car's side."""

    def __init__(self, session_id: int, key: bytes) -> None:
        self.id = session_id
        self.key = key
        self.tx_seq = 0
        self.max_seq = 0
        self.recent: OrderedDict[int, bytes] = OrderedDict()


class _Bucket:
    """Token bucket in car microseconds: a burst, then one token per interval."""

    def __init__(self, burst: int, interval_us: int) -> None:
        self.burst, self.interval_us = burst, interval_us
        self.tokens = burst
        self.since_us = 0

    def take(self, now_us: int) -> bool:
        if self.tokens == self.burst:
            self.since_us = now_us
        earned = (now_us - self.since_us) // self.interval_us
        if earned > 0:
            self.tokens = min(self.burst, self.tokens + earned)
            self.since_us += earned * self.interval_us
        if not self.tokens:
            return False
        self.tokens -= 1
        return True


def _fresh_nonce() -> bytes:
    return secrets.token_bytes(wire.NONCE_LEN)


class CarCore:
    """Sessions, replay windows, deadlines, estop latch and watchdog of one car."""

    def __init__(
        self,
        car_id: int,
        key: bytes,
        marker: int,
        *,
        watchdog_us: int = WATCHDOG_US,
        max_validity_us: int = MAX_VALIDITY_US,
        cell_time_us: int = CELL_TIME_US,
        nonce: Callable[[], bytes] = _fresh_nonce,
    ) -> None:
        if len(key) != wire.KEY_LEN:
            raise ValueError(f"car {car_id}: key must be {wire.KEY_LEN} bytes, got {len(key)}")
        self.car_id = car_id
        self.marker = marker
        self.watchdog_us = watchdog_us
        self.cell_time_us = cell_time_us
        self.max_validity_us = max_validity_us
        self.counters = Counters()
        self._key = key
        self._nonce = nonce
        self._booted = False
        self._reset()

    def _reset(self) -> None:
        self.estopped = False
        self.watchdog_tripped = False
        self._current: _Session | None = None
        self._previous: _Session | None = None  # until the edge's first frame in the current
        self._pending: bytes | None = None  # the nonce of the JOIN awaiting an ACCEPT
        self._cause = wire.JOIN_BOOT
        self._renew_asked_us: int | None = None
        self._moved_in = 0  # the session of the last command handed to the motors
        self._answers = _Bucket(ANSWER_BURST, ANSWER_INTERVAL_US)
        self._fed_at: int | None = None

    @property
    def joined(self) -> bool:
        """A session with an edge is open."""
        return self._current is not None

    @property
    def session(self) -> int:
        """The current session's id (0: none yet)."""
        return 0 if self._current is None else self._current.id

    def boot(self, now_us: int) -> bytes:
        """Power-on or reboot: forget every session and the latch, return the first JOIN."""
        if self._booted:
            self.counters.reboots += 1
        self._booted = True
        self._reset()
        return self.join(now_us)

    def join(self, now_us: int) -> bytes:
        """JOIN asking for a session: the same nonce until an ACCEPT for it arrives."""
        if self._pending is None:
            self._pending = self._nonce()
        self.counters.sent += 1
        return wire.encode(
            wire.JOIN,
            self.car_id,
            0,
            0,
            now_us,
            self._key,
            marker=self.marker,
            cause=self._cause,
            min_version=wire.VERSION,
            max_version=wire.VERSION,
            car_nonce=self._pending,
        )

    def renewal(self, now_us: int) -> bytes | None:
        """A JOIN (cause renew) when the session's counter nears its end, every 250 ms."""
        s = self._current
        if s is None or s.tx_seq < RENEW_AT:
            return None
        if self._renew_asked_us is not None and now_us - self._renew_asked_us < RENEW_PERIOD_US:
            return None
        self._renew_asked_us = now_us
        self._cause = wire.JOIN_RENEW
        return self.join(now_us)

    def _frame(self, s: _Session, kind: int, now_us: int, **fields: int) -> bytes | None:
        """A frame in session ``s``; None once its counter is used up (it never wraps)."""
        if s.tx_seq >= SEQ_MAX:
            if s is self._current:
                self._current, self._cause = None, wire.JOIN_RENEW
            return None
        s.tx_seq += 1
        self.counters.sent += 1
        return wire.encode(kind, self.car_id, s.id, s.tx_seq, now_us, s.key, **fields)

    def leave(self, now_us: int, reason: int = 0) -> bytes | None:
        """LEAVE (0 shutdown, 1 low battery, 2 fault), in the current session."""
        if self._current is None:
            return None
        return self._frame(self._current, wire.LEAVE, now_us, reason=reason)

    def status(self, now_us: int, t: Telemetry) -> bytes | None:
        """STATUS heartbeat: pose estimate, battery, fault flags, last finished command.

        ``done_seq`` is reported only for a command of the current session (0 otherwise), so
        an edge never reads a number from another session's count.
        """
        if self._current is None:
            return None
        faults = (
            (wire.FAULT_WATCHDOG if self.watchdog_tripped else 0)
            | (wire.FAULT_ESTOP if self.estopped else 0)
            | (wire.FAULT_STALL if t.stalled else 0)
            | (wire.FAULT_LOW_BATTERY if t.low_battery else 0)
        )
        return self._frame(
            self._current,
            wire.STATUS,
            now_us,
            row=t.row,
            col=t.col,
            battery_mv=t.battery_mv,
            faults=faults,
            state=int(t.moving),
            done_seq=t.done_seq if self._moved_in == self._current.id else 0,
        )

    def _ack(self, s: _Session, f: wire.Frame, result: str, now_us: int) -> tuple[bytes, ...]:
        action = f.payload["action"] if f.type == wire.COMMAND else wire.NO_ACTION
        frame = self._frame(
            s,
            wire.ACK,
            now_us,
            ref_seq=f.seq,
            result=wire.RESULTS.index(result),
            action=action,
            rx_us=now_us,
        )
        return () if frame is None else (frame,)

    def _limited(self, now_us: int) -> bool:
        """Whether an answer to a replayable frame may go out now (else it is counted)."""
        if self._answers.take(now_us):
            return True
        self.counters.unanswered += 1
        return False

    def _reject(self, reason: str, replies: tuple[bytes, ...] = ()) -> Outcome:
        self.counters.rejected[reason] += 1
        return Outcome(reason, replies)

    def reject(self, reason: str) -> None:
        """Count a frame the transport already refused (e.g. bad CAN padding)."""
        self.counters.received += 1
        self.counters.rejected[reason] += 1

    def handle(self, data: bytes, now_us: int) -> Outcome:
        """Judge one frame from the edge received at car time ``now_us``."""
        self.counters.received += 1
        try:
            f = wire.parse(data)
        except wire.Malformed as err:
            return self._reject(err.reason)
        if f.type & 0x80:
            return self._reject("malformed")
        if f.car_id != self.car_id:
            return self._reject("unknown_car")
        if f.type in wire.HANDSHAKE:
            return self._handshake(f, now_us)
        s = next((x for x in (self._current, self._previous) if x and x.id == f.session), None)
        if s is None:
            return self._reject("wrong_session")
        if not wire.authentic(f, s.key):
            return self._reject("bad_tag")
        if s.recent.get(f.seq) == f.tag:
            self.counters.duplicates += 1
            replies = self._ack(s, f, "duplicate", now_us) if self._limited(now_us) else ()
            return Outcome("duplicate", replies)
        if f.seq <= s.max_seq:
            replies = self._ack(s, f, "replay", now_us) if self._limited(now_us) else ()
            return self._reject("replay", replies)
        s.max_seq = f.seq
        if s is self._current:
            self._previous = None  # the edge has moved to the new session
        if abs(f.timestamp_us - now_us) > TIME_WINDOW_US:
            return self._reject("bad_time", self._ack(s, f, "bad_time", now_us))
        if f.type == wire.TIME_REQ:
            reply = self._frame(
                s, wire.TIME_RESP, now_us, t1_ns=f.payload["t1_ns"], t2_us=now_us, t3_us=now_us
            )
            return self._accept(s, f, now_us, () if reply is None else (reply,))
        deadline = f.payload["deadline_us"]
        stopping = f.type == wire.COMMAND and f.payload["action"] == wire.STOP_ACTION
        engaging = f.type == wire.ESTOP and f.payload["engage"] == 1
        if not engaging:
            if deadline < now_us:
                return self._reject("expired", self._ack(s, f, "expired", now_us))
            if deadline > now_us + self.max_validity_us:
                return self._reject("bad_time", self._ack(s, f, "bad_time", now_us))
        if f.type == wire.ESTOP:
            self.estopped = engaging
            return self._accept(s, f, now_us, halt=engaging)
        if self.estopped and not stopping:
            return self._reject("estopped", self._ack(s, f, "estopped", now_us))
        # the watchdog counts from when the command's move starts (after its start delay)
        self._fed_at = now_us + f.payload["delay_pct"] * self.cell_time_us // 100
        self.watchdog_tripped = False
        self._moved_in = s.id
        motor = (f.seq, f.payload["action"])
        return self._accept(s, f, now_us, motor=motor, guidance=wire.guidance(f.payload))

    def _handshake(self, f: wire.Frame, now_us: int) -> Outcome:
        """HELLO and ACCEPT: signed with the car's own key, fresh only if they echo our nonce."""
        if not wire.authentic(f, self._key):
            return self._reject("bad_tag")
        if f.type == wire.HELLO:  # anyone may replay one: answered, but nothing changes
            if self._pending is None and self._current is not None:
                self._cause = wire.JOIN_HELLO  # else the JOIN under way keeps its cause
            replies = (self.join(now_us),) if self._limited(now_us) else ()
            return Outcome("hello", replies)
        if self._pending is None or f.payload["car_nonce"] != self._pending:
            return self._reject("stale_accept")
        if f.payload["version"] != wire.VERSION:
            return self._reject("wrong_version")
        session_id, session_key = wire.session_for(
            self._key, self._pending, f.payload["edge_nonce"]
        )
        self._previous = self._current
        self._current = _Session(session_id, session_key)
        self._pending = None
        self._renew_asked_us = None
        self.counters.sessions.append(session_id)
        return Outcome("joined")

    def _accept(
        self,
        s: _Session,
        f: wire.Frame,
        now_us: int,
        replies: tuple[bytes, ...] | None = None,
        *,
        motor: tuple[int, int] | None = None,
        halt: bool = False,
        guidance: wire.Guidance | None = None,
    ) -> Outcome:
        self.counters.accepted += 1
        s.recent[f.seq] = f.tag
        if len(s.recent) > DUPLICATE_CACHE:
            s.recent.popitem(last=False)
        if replies is None:
            replies = self._ack(s, f, "accepted", now_us)
        return Outcome("accepted", replies, motor, halt, guidance)

    def next_wakeup_us(self) -> int | None:
        """Car time at which ``poll`` must run next (the watchdog expiry), if any."""
        return None if self._fed_at is None else self._fed_at + self.watchdog_us

    def poll(self, now_us: int) -> bool:
        """True once when the watchdog expires: the driver must stop the motors now."""
        if self._fed_at is None or now_us - self._fed_at < self.watchdog_us:
            return False
        self._fed_at = None
        self.watchdog_tripped = True
        self.counters.watchdog_stops += 1
        return True
