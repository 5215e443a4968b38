"""The car's sans-I/O protocol core: what the firmware accepts, what it answers, when it stops.

No sockets and no clock of its own: the driver (UDP ESP8266 mock, CAN motor controller) passes the
car's clock in microseconds since boot to every call, so the same rules run in tests with a fake
clock and in the mock processes with ``time.monotonic_ns``. The checks run in the order given in
docs/protocol.md section 4, and the first failing check is the reason counted.
"""

from __future__ import annotations

from collections import Counter, OrderedDict
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
)
TIME_WINDOW_US = 60_000_000  # MAVLink 2 signing's one-minute window
MAX_VALIDITY_US = 1_000_000  # a deadline further ahead than this is refused as bad_time
WATCHDOG_US = 300_000
DUPLICATE_CACHE = 16


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

    ``motor`` is ``(seq, action)`` of an accepted command (``wire.STOP_ACTION`` stops at once);
    ``halt`` says an emergency stop was engaged: stop the motors now.
    """

    verdict: str
    replies: tuple[bytes, ...] = ()
    motor: tuple[int, int] | None = None
    halt: bool = False


class CarCore:
    """Session, replay window, deadlines, estop latch and watchdog of one car."""

    def __init__(
        self,
        car_id: int,
        key: bytes,
        marker: int,
        *,
        watchdog_us: int = WATCHDOG_US,
        max_validity_us: int = MAX_VALIDITY_US,
    ) -> None:
        if len(key) != wire.KEY_LEN:
            raise ValueError(f"car {car_id}: key must be {wire.KEY_LEN} bytes, got {len(key)}")
        self.car_id = car_id
        self.marker = marker
        self.watchdog_us = watchdog_us
        self.max_validity_us = max_validity_us
        self.counters = Counters()
        self._key = key
        self.session = 0
        self._reset()

    def _reset(self) -> None:
        self.joined = False
        self.estopped = False
        self.watchdog_tripped = False
        self._tx_seq = 0
        self._max_seq = 0
        self._recent: OrderedDict[int, bytes] = OrderedDict()
        self._fed_at: int | None = None

    def boot(self, session: int, now_us: int) -> bytes:
        """Start a new session (power-on or reboot): forget all state, return the JOIN."""
        if not 0 < session < 1 << 32:
            raise ValueError("session must be a nonzero 32-bit value")
        if self.session:
            self.counters.reboots += 1
        self.session = session
        self._reset()
        return self.join(now_us)

    def _frame(self, kind: int, now_us: int, **fields: int) -> bytes:
        self._tx_seq += 1
        self.counters.sent += 1
        return wire.encode(
            kind, self.car_id, self.session, self._tx_seq, now_us, self._key, **fields
        )

    def join(self, now_us: int, cause: int = wire.JOIN_BOOT) -> bytes:
        """JOIN announcing this car's marker and current session."""
        return self._frame(wire.JOIN, now_us, marker=self.marker, cause=cause)

    def leave(self, now_us: int, reason: int = 0) -> bytes:
        """LEAVE (0 shutdown, 1 low battery, 2 fault)."""
        return self._frame(wire.LEAVE, now_us, reason=reason)

    def status(self, now_us: int, t: Telemetry) -> bytes:
        """STATUS heartbeat: pose estimate, battery, fault flags, last finished command."""
        faults = (
            (wire.FAULT_WATCHDOG if self.watchdog_tripped else 0)
            | (wire.FAULT_ESTOP if self.estopped else 0)
            | (wire.FAULT_STALL if t.stalled else 0)
            | (wire.FAULT_LOW_BATTERY if t.low_battery else 0)
        )
        return self._frame(
            wire.STATUS,
            now_us,
            row=t.row,
            col=t.col,
            battery_mv=t.battery_mv,
            faults=faults,
            state=int(t.moving),
            done_seq=t.done_seq,
        )

    def _ack(self, f: wire.Frame, result: str, now_us: int) -> bytes:
        action = f.payload["action"] if f.type == wire.COMMAND else wire.NO_ACTION
        return self._frame(
            wire.ACK,
            now_us,
            ref_seq=f.seq,
            result=wire.RESULTS.index(result),
            action=action,
            rx_us=now_us,
        )

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
        if not wire.authentic(f, self._key):
            return self._reject("bad_tag")
        if f.session != self.session:
            return self._reject("wrong_session", (self.join(now_us, wire.JOIN_WRONG_SESSION),))
        if self._recent.get(f.seq) == f.tag:
            self.counters.duplicates += 1
            return Outcome("duplicate", (self._ack(f, "duplicate", now_us),))
        if f.seq <= self._max_seq:
            return self._reject("replay", (self._ack(f, "replay", now_us),))
        self._max_seq = f.seq
        self.joined = True
        if abs(f.timestamp_us - now_us) > TIME_WINDOW_US:
            return self._reject("bad_time", (self._ack(f, "bad_time", now_us),))
        if f.type == wire.TIME_REQ:
            return self._accept(f, now_us, reply=self._time_response(f, now_us))
        deadline = f.payload["deadline_us"]
        stopping = f.type == wire.COMMAND and f.payload["action"] == wire.STOP_ACTION
        engaging = f.type == wire.ESTOP and f.payload["engage"] == 1
        if not engaging:
            if deadline < now_us:
                return self._reject("expired", (self._ack(f, "expired", now_us),))
            if deadline > now_us + self.max_validity_us:
                return self._reject("bad_time", (self._ack(f, "bad_time", now_us),))
        if f.type == wire.ESTOP:
            self.estopped = engaging
            return self._accept(f, now_us, halt=engaging)
        if self.estopped and not stopping:
            return self._reject("estopped", (self._ack(f, "estopped", now_us),))
        self._fed_at = now_us
        self.watchdog_tripped = False
        return self._accept(f, now_us, motor=(f.seq, f.payload["action"]))

    def _time_response(self, f: wire.Frame, now_us: int) -> bytes:
        return self._frame(
            wire.TIME_RESP, now_us, t1_ns=f.payload["t1_ns"], t2_us=now_us, t3_us=now_us
        )

    def _accept(
        self,
        f: wire.Frame,
        now_us: int,
        *,
        reply: bytes | None = None,
        motor: tuple[int, int] | None = None,
        halt: bool = False,
    ) -> Outcome:
        self.counters.accepted += 1
        self._recent[f.seq] = f.tag
        if len(self._recent) > DUPLICATE_CACHE:
            self._recent.popitem(last=False)
        return Outcome("accepted", (reply or self._ack(f, "accepted", now_us),), motor, halt)

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
