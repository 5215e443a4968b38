"""The edge's link to its cars: joins, clock sync, heartbeats and the 10 ms command dispatcher.

``CarLink`` puts the sans-I/O ``EdgeProtocol`` on a ``Transport`` and runs what the protocol leaves
to the edge (docs/protocol.md section 14): when to synchronise clocks (right after a join or a
reboot, then whenever the best sample is older than ``sync_period_s``), how to treat ``Rejected``
frames (counted by reason, never raised: a forged or garbled frame must not stop the fleet), and
retransmission. ``dispatch`` sends a step's commands back to back, each valid until the step's
deadline in the car's own clock, then resends the *identical bytes* of an unacknowledged command
(the car answers a copy with a duplicate ACK and does not run it twice) until it is acknowledged
or the deadline is too close for a frame to arrive in time. Nothing is sent within
``send_margin_ns`` of the deadline, and the car refuses anything that arrives after it. ACKs
still on their way at the deadline are awaited ``ack_grace_ns`` longer, without resends: the
car accepts only what reached it in time, so an accepted command was on time however late its
ACK (a command sent in the last round trip before the deadline, or an edge held up by the OS).

Keepalive is the runtime's: it sends a command (``wait`` included) every step. If steps pause
past the cars' watchdog (300 ms) they stop and report WATCHDOG; the next command resumes them.

Sessions need no memory of an earlier edge process: a car still in a session this edge never
opened is sent HELLO and opens a new one (section 6), so a restarted edge has its cars back after
a few round trips, however many frames the old process had sent. A car the edge has stopped stays
stopped across its reboots: the stop is sent again in every new session until released.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from udan.edge import protocol as ep
from udan.edge.transport import Transport, TransportError
from udan.fleetfile import CarEntry

RETRY_NS = 2_000_000  # resend an unacked command after this long (loopback rtt is ~0.3 ms)
SEND_MARGIN_NS = 1_000_000  # no send this close to the deadline: it would arrive expired
ACK_GRACE_NS = 3_000_000  # ACKs in flight at the deadline are awaited this long (no resends)
SYNC_RETRY_NS = 200_000_000  # an unanswered time request is repeated after this long
TICK_S = 0.05  # housekeeping period: re-syncs, silence
ESTOP_REPEATS_S = (0.003, 0.006)  # an emergency stop is sent three times, in case one is lost
COUNTERS = (
    "joins",
    "reboots",
    "leaves",
    "syncs",
    "time_requests",
    "commands",
    "retransmits",
    "estops",
    "hellos",
    "renewals",
    "send_errors",
)
_ACCEPTING = (ep.AckResult.ACCEPTED, ep.AckResult.DUPLICATE)
log = logging.getLogger(__name__)


@dataclass(slots=True)
class SentCommand:
    """The last command sent to a car in its session; ``outcome`` is pending until an ACK.

    ``accepted``: the car took it (it runs, or ran); ``refused``: the car will never run it.
    """

    seq: int
    session: int  # seq counts in this session
    action: int
    deadline_us: int  # in the car's clock
    outcome: str = "pending"


@dataclass
class CarState:
    """What the link knows of one car (read-only for callers)."""

    car_id: int
    marker: int
    last_heard_ns: int | None = None
    status: ep.StatusReport | None = None  # newest STATUS: moving, done_seq, faults, battery
    command: SentCommand | None = None
    sync_requested_ns: int | None = None
    sync_rtt_ns: int | None = None  # round trip of the best sync sample: offset known to ±rtt/2
    left: str | None = None  # the LEAVE reason, until the car joins again


@dataclass(slots=True)
class CommandReport:
    """One car's command in one dispatch.

    ``result``: the car's ACK result (``accepted``, ``duplicate`` (a resend answered after the
    first ACK was lost: accepted once), ``expired``, ``estopped``, ``bad_time``, ``replay``), or
    ``no_ack`` (sent, nothing came back in time), ``not_ready`` (not joined, synced or heard from:
    nothing sent), ``too_late`` (the deadline was too close to send), ``no_leader`` (it waited
    for the car whose cell it enters to accept, in vain: nothing sent), ``rebooted`` / ``left``.
    """

    car_id: int
    action: int
    seq: int = 0
    first_sent_ns: int | None = None
    attempts: int = 0
    acked: bool = False  # the car accepted it, hence received it within its validity
    acked_ns: int | None = None  # edge clock when the ACK arrived
    car_received_ns: int | None = None  # car receive time converted to the edge clock
    result: str = "no_ack"
    car_deadline_us: int | None = None  # the deadline written in the frame (car clock)
    car_rx_us: int | None = None  # the car's receive time from the ACK (car clock)
    slow_sends: int = 0  # sends whose syscall returned at or after the deadline


@dataclass
class DispatchReport:
    """What became of one step's commands; every count is taken from what happened."""

    decision_ns: int
    deadline_ns: int
    cars: dict[int, CommandReport]  # per car id
    on_time: int = 0
    retried: int = 0
    missed: int = 0
    not_ready: int = 0
    slow_sends: int = 0  # sends whose syscall returned at or after the deadline
    late_sends: int = 0  # slow sends not proven on time by the car; must stay 0

    @property
    def all_acked_ns(self) -> int | None:
        """When the last ACK arrived, if every command sent was accepted."""
        sent = [r for r in self.cars.values() if r.attempts]
        if not sent or not all(r.acked for r in sent):
            return None
        return max(r.acked_ns for r in sent if r.acked_ns is not None)


def _proven_on_time(r: CommandReport) -> bool:
    """Whether the car's ACK proves the command's only copy arrived before its deadline.

    A send's syscall can return past the deadline although the datagram left in time: on
    loopback the woken receiver may run before the sender gets its core back. The car accepts
    only what arrives within the validity, so an accepted single send was not late; with
    resends the ACK does not say which copy arrived, and a slow one counts as late.
    """
    return r.acked and r.attempts == 1


@dataclass(slots=True)
class _Round:
    """The dispatch under way, as a command held back for its leader's ACK needs it."""

    report: DispatchReport
    cutoff: int
    guidance: Mapping[int, ep.Guidance]
    waiting: dict[int, int]  # car -> the car whose ACK it waits for
    ready: set[int]


@dataclass(slots=True)
class _Flight:
    report: CommandReport
    frame: bytes
    next_send_ns: int = 0


class CarLink:
    """Protocol + transport for a fleet; see the module docstring."""

    def __init__(
        self,
        cars: Sequence[CarEntry],
        transport: Transport,
        *,
        clock: Callable[[], int] = time.monotonic_ns,
        validity_ns: int = ep.DEFAULT_VALIDITY_NS,
        sync_period_s: float = 1.0,
        silence_s: float = 1.0,
        retry_ns: int = RETRY_NS,
        send_margin_ns: int = SEND_MARGIN_NS,
        ack_grace_ns: int = ACK_GRACE_NS,
    ) -> None:
        self.transport = transport
        self.validity_ns = validity_ns
        self.changed = asyncio.Event()
        self._clock = clock
        self._proto = ep.EdgeProtocol({c.car_id: c.key for c in cars}, clock=clock)
        self._cars = {c.car_id: CarState(c.car_id, c.marker) for c in cars}
        self._sync_period_ns = int(sync_period_s * 1e9)
        self._silence_ns = int(silence_s * 1e9)
        self._retry_ns = retry_ns
        self._send_margin_ns = send_margin_ns
        self._ack_grace_ns = ack_grace_ns
        self._rejected: Counter[str] = Counter()
        self._counts: Counter[str] = Counter({name: 0 for name in COUNTERS})
        self._flights: dict[int, _Flight] = {}
        self._round: _Round | None = None
        self._dispatching = False
        self._resolved = asyncio.Event()
        self._ready_seen: frozenset[int] = frozenset()
        self._stopped: set[int] = set()  # emergency stop engaged and not released
        self._logged: set[str] = set()
        self._task: asyncio.Task[None] | None = None
        self._open = False

    # --- lifecycle ---
    async def start(self) -> None:
        """Open the transport and start housekeeping; cars join by themselves (JOIN)."""
        await self.transport.open(self._on_frame)
        self._open = True
        self._task = asyncio.create_task(self._housekeeping(), name="car-link")

    async def close(self) -> None:
        """Stop housekeeping and close the transport (call ``estop_all`` first to stop cars)."""
        self._open = False
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        self.transport.close()

    # --- queries ---
    def ready_cars(self) -> set[int]:
        """Cars that can be commanded: joined, clock synchronised, heard within ``silence_s``."""
        now = self._clock()
        return {
            c
            for c, st in self._cars.items()
            if st.last_heard_ns is not None
            and now - st.last_heard_ns <= self._silence_ns
            and self._proto.synced(c)
        }

    def state(self, car_id: int) -> CarState:
        """The link's view of one car (``KeyError`` for a car not in the fleet)."""
        return self._cars[car_id]

    def move_finished(self, car_id: int) -> bool:
        """The car reported it is idle and will not start the last command sent to it later.

        True when the newest STATUS says not moving and either its ``done_seq`` reached the last
        command (or none was sent), or that command can no longer run: the car refused it, or it
        was never acknowledged and the STATUS was made after its deadline (a car never starts a
        command past its deadline, and an accepted one shows as moving or done). A STATUS of
        another session than the command's says nothing of its ``done_seq`` (each session counts
        on its own), so then only the deadline rule applies. An engaged emergency stop also
        counts as finished: nothing will move.
        """
        st = self._cars.get(car_id)
        if st is None or st.status is None or st.status.moving:
            return False
        status, cmd = st.status, st.command
        if cmd is None or status.faults & ep.Fault.ESTOP or cmd.outcome == "refused":
            return True
        if status.session == cmd.session and status.done_seq >= cmd.seq:
            return True
        unconfirmed = cmd.outcome == "pending" or status.session != cmd.session
        return unconfirmed and status.car_time_us > cmd.deadline_us

    def counters(self) -> dict[str, object]:
        """Everything counted: rejected frames by reason, events, sends, transport drops."""
        return {
            "rejected": dict(self._rejected),
            **self._counts,
            "transport_dropped": dict(self.transport.dropped),
        }

    # --- sending ---
    def _send(self, car_id: int, frame: bytes, *, back: bool = False) -> bool:
        try:
            if back:
                self.transport.send_back(car_id, frame)
            else:
                self.transport.send(car_id, frame)
        except (TransportError, OSError):
            self._counts["send_errors"] += 1
            return False
        return True

    def _request_sync(self, car_id: int, now: int) -> None:
        if car_id in self._flights:  # its seq would overtake the command's resends (replay)
            return
        self._cars[car_id].sync_requested_ns = now
        self._counts["time_requests"] += 1
        self._send(car_id, self._proto.encode_time_request(car_id))

    def _flush(self, *, back: bool = False) -> None:
        """Send what the protocol queued of its own accord (ACCEPT, HELLO).

        ``back``: they answer the frame being delivered, and go where it came from.
        """
        for car_id, frame in self._proto.datagrams_to_send():
            self._counts["hellos"] += frame[1] == ep.MsgType.HELLO
            self._send(car_id, frame, back=back)

    def estop_all(self, engage: bool = True) -> int:
        """Emergency stop (or release) every joined car now; returns how many it was sent to.

        Synchronous and best effort, for ``finally`` blocks and signal handlers installed with
        ``loop.add_signal_handler`` (a plain ``signal.signal`` handler could interrupt the
        protocol core mid-frame). When an event loop is running the round is repeated twice a
        few ms later with fresh frames (engaging twice is harmless, a lost frame is not). A
        release needs a synchronised clock, so cars without one are skipped. An engaged stop is
        remembered: a car that joins again (it rebooted, and its latch with it) is sent it.
        """
        if engage:
            self._stopped.update(self._cars)
        else:
            self._stopped.clear()
        sent = self._estop_round(engage)
        with contextlib.suppress(RuntimeError):  # no running loop: one round is all we can do
            loop = asyncio.get_running_loop()
            for delay in ESTOP_REPEATS_S:
                loop.call_later(delay, self._estop_round, engage)
        return sent

    def _estop_round(self, engage: bool) -> int:
        if not self._open:
            return 0
        sent = 0
        for car_id in self._proto.joined_cars():
            try:
                frame = self._proto.encode_estop(car_id, engage)
            except ep.NotReady:
                continue
            sent += self._send(car_id, frame)
        self._counts["estops"] += sent
        return sent

    # --- dispatch ---
    async def dispatch(
        self,
        actions: Mapping[int, int],
        decision_ns: int,
        deadline_ns: int | None = None,
        guidance: Mapping[int, ep.Guidance] | None = None,
        after: Mapping[int, int] | None = None,
    ) -> DispatchReport:
        """Send one step's commands, resend unacked ones while the deadline allows, report.

        Each command is valid until ``deadline_ns`` (default ``decision_ns + validity_ns``) in
        the car's clock, and carries the car's ``guidance`` if given (its target and measured
        pose). A car in ``after`` (car -> the car whose cell it enters) is sent its command
        only once that car has accepted its own: a car that does not move must not be driven
        into; if it never accepts, the follower gets nothing (``no_leader``) and stays too.
        Returns when every command sent is answered, or ``ack_grace_ns`` after the deadline.
        Cars that are not ready are reported, not raised; an action outside 0-5 is a
        ``ValueError`` before anything is sent.
        """
        if self._dispatching:
            raise RuntimeError("dispatch already in progress")
        deadline = decision_ns + self.validity_ns if deadline_ns is None else deadline_ns
        commands = {c: CommandReport(c, int(ep.Action(a))) for c, a in actions.items()}
        report = DispatchReport(decision_ns, deadline, commands)
        cutoff = deadline - self._send_margin_ns
        waiting = {c: leader for c, leader in (after or {}).items() if c in commands}
        self._round = _Round(report, cutoff, guidance or {}, waiting, self.ready_cars())
        self._dispatching = True
        try:
            for car_id, r in commands.items():
                if car_id not in self._round.ready:
                    r.result = "not_ready"
                elif car_id in waiting:
                    r.result = "no_leader"  # until its leader accepts (_release)
                else:
                    self._launch(car_id)
            for flight in self._flights.values():  # after the sends: they leave back to back
                self._book(flight)
            await self._await_acks(report, cutoff)
        finally:
            self._flights.clear()
            self._round = None
            self._dispatching = False
        for r in commands.values():
            if r.result == "not_ready":
                report.not_ready += 1
            elif r.acked:
                report.on_time += 1
            else:
                report.missed += 1
            report.retried += r.attempts > 1
            report.slow_sends += r.slow_sends
            report.late_sends += r.slow_sends > 0 and not _proven_on_time(r)
        return report

    def _launch(self, car_id: int) -> _Flight | None:
        """Encode the car's command of the dispatch under way and send it (unless too late)."""
        rnd = self._round
        assert rnd is not None
        r = rnd.report.cars[car_id]
        now = self._clock()
        if now >= rnd.cutoff:
            r.result = "too_late"
            return None
        deadline = rnd.report.deadline_ns
        guide = rnd.guidance.get(car_id)
        frame = self._proto.encode_command(car_id, r.action, deadline - now, guide)
        r.first_sent_ns = now
        self._flights[car_id] = flight = _Flight(r, frame)
        self._transmit(flight, rnd.report)
        self._counts["commands"] += 1
        return flight

    def _book(self, flight: _Flight) -> None:
        """Remember the command sent (its seq and deadline, for ``move_finished``)."""
        decoded = ep.decode(flight.frame)
        r = flight.report
        r.seq, r.car_deadline_us = decoded.seq, decoded.fields["deadline_us"]
        self._cars[r.car_id].command = SentCommand(
            r.seq, decoded.session, r.action, r.car_deadline_us
        )

    def _release(self, leader: int) -> None:
        """The car ``leader`` accepted its command: send the commands that waited for it."""
        rnd = self._round
        if rnd is None:
            return
        for car_id in [c for c, lead in rnd.waiting.items() if lead == leader]:
            del rnd.waiting[car_id]
            if car_id in rnd.ready and (flight := self._launch(car_id)) is not None:
                self._book(flight)

    def _transmit(self, flight: _Flight, report: DispatchReport) -> None:
        r = flight.report
        if self._clock() >= report.deadline_ns - self._send_margin_ns:
            return  # checked again right before the syscall: encoding may have been preempted
        sent = self._send(r.car_id, flight.frame)
        after = self._clock()
        if sent:
            r.attempts += 1
            r.slow_sends += after >= report.deadline_ns
        flight.next_send_ns = after + self._retry_ns

    async def _await_acks(self, report: DispatchReport, cutoff: int) -> None:
        while self._flights:
            for flight in list(self._flights.values()):
                now = self._clock()
                if now >= cutoff:
                    break
                if flight.next_send_ns <= now:
                    self._transmit(flight, report)
                    self._counts["retransmits"] += 1
            now = self._clock()
            last_ack = report.deadline_ns + self._ack_grace_ns
            if now >= last_ack:
                return
            resends = [f.next_send_ns for f in self._flights.values() if f.next_send_ns < cutoff]
            wake = min([last_ack, *resends])
            self._resolved.clear()
            if wake > now:
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout((wake - now) / 1e9):
                        await self._resolved.wait()

    def _resolve(self, car_id: int, result: str) -> None:
        """End the car's command in the dispatch under way, if it has one."""
        flight = self._flights.pop(car_id, None)
        if flight is not None:
            flight.report.result = result
            if not self._flights:
                self._resolved.set()

    # --- frames in ---
    def _on_frame(self, data: bytes) -> None:
        event = self._proto.receive(data)
        if isinstance(event, ep.Rejected):
            self._rejected[event.reason] += 1
            if event.detail and event.detail not in self._logged:
                self._logged.add(event.detail)
                log.warning("%s", event.detail)
            self._flush(back=True)
            return
        if isinstance(event, ep.Joining):  # maybe a replay: it moves nothing, not even the route
            self._flush(back=True)
            return
        now = self._clock()
        st = self._cars[event.car_id]
        st.last_heard_ns = now
        self.transport.confirm_source(event.car_id)
        if isinstance(event, ep.Acked):
            self._on_ack(event, st, now)
            return
        if isinstance(event, ep.Joined):
            self._on_join(event, st, now)
        elif isinstance(event, ep.TimeSynced):
            self._counts["syncs"] += 1
            st.sync_rtt_ns = event.rtt_ns
        elif isinstance(event, ep.StatusReport):
            if st.status is None or event.car_time_us >= st.status.car_time_us:
                st.status = event
        else:
            self._counts["leaves"] += 1
            self._forget(st, "left")
            st.left = event.reason
        self.changed.set()

    def _forget(self, st: CarState, why: str) -> None:
        """The car's session ended: what it reported and what was sent to it no longer apply."""
        st.status = st.command = st.sync_requested_ns = st.sync_rtt_ns = None
        self._resolve(st.car_id, why)

    def _on_join(self, event: ep.Joined, st: CarState, now: int) -> None:
        """A new session. After a reboot nothing of the old one holds; after a renewal (or a
        new edge) the car ran on: a command in flight is still answered, in its own session."""
        self._counts["joins"] += 1
        if event.previous_session is not None:
            self._counts["reboots" if event.reboot else "renewals"] += 1
        if event.reboot:
            self._forget(st, "rebooted")
        st.marker, st.left = event.marker, None
        if event.status is not None:
            st.status = event.status
        if st.car_id in self._stopped:
            self._send(st.car_id, self._proto.encode_estop(st.car_id))
            self._counts["estops"] += 1
        if not self._proto.synced(st.car_id):
            self._request_sync(st.car_id, now)

    def _on_ack(self, event: ep.Acked, st: CarState, now: int) -> None:
        cmd = st.command
        if cmd is None or (event.session, event.ref_seq) != (cmd.session, cmd.seq):
            return  # an estop's, a refused time request's, or an older command's
        accepted = event.result in _ACCEPTING
        if cmd.outcome == "pending":
            cmd.outcome = "accepted" if accepted else "refused"
        flight = self._flights.get(st.car_id)
        if flight is None:
            return
        r = flight.report
        r.acked, r.acked_ns = accepted, now
        r.car_received_ns, r.car_rx_us = event.received_at_ns, event.car_rx_us
        self._resolve(st.car_id, event.result.name.lower())
        if accepted:
            self._release(st.car_id)

    # --- housekeeping ---
    async def _housekeeping(self) -> None:
        while True:
            await asyncio.sleep(TICK_S)
            self._tick()

    def _tick(self) -> None:
        """Re-sync clocks that are due (or whose request went unanswered); notice silences.

        A best sample whose round trip is as long as the validity leaves no time for a command
        (the deadline is pulled in by half of it, section 7): such a car is synced again as soon
        as the retry pace allows, until a better sample comes, not after ``sync_period_s``.
        """
        self._flush()  # a renewal asked for while sending
        now = self._clock()
        for car_id in self._proto.joined_cars():
            st = self._cars[car_id]
            age = self._proto.sync_age_ns(car_id)
            poor = st.sync_rtt_ns is not None and st.sync_rtt_ns >= self.validity_ns
            due = age is None or age >= self._sync_period_ns or poor
            asked = st.sync_requested_ns
            if due and (asked is None or now - asked >= SYNC_RETRY_NS):
                self._request_sync(car_id, now)
        ready = frozenset(self.ready_cars())
        if ready != self._ready_seen:
            self._ready_seen = ready
            self.changed.set()
