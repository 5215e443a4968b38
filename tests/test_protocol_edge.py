"""The edge's sans-I/O core with an injected clock: sessions, reboots, time sync, replay window."""

from __future__ import annotations

import time

import pytest

from udan.edge import protocol as ep
from udan.envs.rules import ACTIONS

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))


class FakeClock:
    """Edge clock under test control (nanoseconds)."""

    def __init__(self, ns: int = 10_000_000_000) -> None:
        self.ns = ns

    def __call__(self) -> int:
        return self.ns


class Car:
    """Builds car -> edge frames the way the spec says (with the edge module's own encoder)."""

    def __init__(self, car_id: int = 1, nonce: bytes = b"n" * 16, key: bytes = KEY) -> None:
        self.car_id, self.nonce, self.key = car_id, nonce, key
        self.session, self.session_key, self.seq = 0, b"", 0

    def frame(self, kind: ep.MsgType, car_us: int, **fields: int) -> bytes:
        self.seq += 1
        return ep.encode(
            kind, self.car_id, self.session, self.seq, car_us, self.session_key, fields
        )

    def join(self, car_us: int, marker: int = 5, cause: int = 0) -> bytes:
        fields = {"marker": marker, "cause": cause, "min_version": 2, "max_version": 2}
        fields["car_nonce"] = self.nonce
        return ep.encode(ep.MsgType.JOIN, self.car_id, 0, 0, car_us, self.key, fields)

    def take(self, accept: bytes) -> None:
        """Open the session an ACCEPT for our nonce offers."""
        d = ep.decode(accept)
        assert d.type == ep.MsgType.ACCEPT and d.fields["car_nonce"] == self.nonce
        self.session, self.session_key = ep.derive_session(
            self.key, self.nonce, d.fields["edge_nonce"]
        )
        self.seq = 0

    def status(self, car_us: int, done_seq: int = 0) -> bytes:
        return self.frame(
            ep.MsgType.STATUS, car_us, row=0, col=0, battery_mv=1, faults=0, state=0,
            done_seq=done_seq,
        )  # fmt: skip

    def open(self, edge: ep.EdgeProtocol, car_us: int, cause: int = 0) -> ep.Event:
        """JOIN, take the ACCEPT, confirm with a STATUS: the edge's verdict on the STATUS."""
        assert isinstance(edge.receive(self.join(car_us, cause=cause)), ep.Joining)
        ((car_id, accept),) = edge.datagrams_to_send()
        assert car_id == self.car_id
        self.take(accept)
        return edge.receive(self.status(car_us))


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def edge(clock: FakeClock) -> ep.EdgeProtocol:
    return ep.EdgeProtocol({1: KEY, 2: OTHER_KEY}, clock=clock)


def _sync(edge: ep.EdgeProtocol, clock: FakeClock, car: Car, offset_ns: int, rtt_ns: int) -> None:
    """One time-sync round trip with a symmetric path and zero car turnaround."""
    req = ep.decode(edge.encode_time_request(car.car_id))
    t1 = req.fields["t1_ns"]
    car_us = (t1 + rtt_ns // 2 + offset_ns) // 1000
    clock.ns = t1 + rtt_ns
    event = edge.receive(
        car.frame(ep.MsgType.TIME_RESPONSE, car_us, t1_ns=t1, t2_us=car_us, t3_us=car_us)
    )
    assert isinstance(event, ep.TimeSynced)


def test_actions_match_the_world_rules() -> None:
    assert [a.name.lower() for a in ep.Action][: len(ACTIONS)] == list(ACTIONS)


def test_join_then_commands_need_a_clock_sync(edge: ep.EdgeProtocol, clock: FakeClock) -> None:
    car = Car()
    with pytest.raises(ep.NotReady):
        edge.encode_time_request(1)
    event = edge.receive(car.join(1_000))
    assert event == ep.Joining(1, 5, ep.JoinCause.BOOT) and not edge.joined(1)  # an offer only
    ((_, accept),) = edge.datagrams_to_send()
    car.take(accept)
    event = edge.receive(car.status(1_000))
    assert isinstance(event, ep.Joined) and event.status is not None  # the confirming STATUS
    assert event == ep.Joined(1, 5, car.session, None, reboot=False, status=event.status)
    assert (event.status.session, event.status.battery_mv) == (car.session, 1)
    assert edge.joined(1) and not edge.synced(1)
    with pytest.raises(ep.NotReady):
        edge.encode_command(1, ep.Action.UP)
    _sync(edge, clock, car, offset_ns=-3_000_000_000, rtt_ns=400_000)
    assert edge.synced(1)
    frame = ep.decode(edge.encode_command(1, ep.Action.LEFT, validity_ns=10_000_000))
    assert (frame.car_id, frame.session, frame.seq) == (1, car.session, 2)
    assert frame.fields["action"] == ep.Action.LEFT


def test_time_sync_offset_and_conservative_deadline(
    edge: ep.EdgeProtocol, clock: FakeClock
) -> None:
    car = Car()
    car.open(edge, 1_000)
    offset = -7_000_123_000
    _sync(edge, clock, car, offset_ns=offset, rtt_ns=2_000_000)
    _sync(edge, clock, car, offset_ns=offset, rtt_ns=300_000)  # the better sample wins
    _sync(edge, clock, car, offset_ns=offset, rtt_ns=5_000_000)
    assert abs(edge.car_time_us(1) - (clock.ns + offset) // 1000) <= 1
    sent_at = clock.ns
    frame = ep.decode(edge.encode_command(1, ep.Action.UP, validity_ns=10_000_000))
    true_deadline_us = (sent_at + 10_000_000 + offset) // 1000
    # pulled in by rtt/2 (150 us) plus drift over the sample's age (5 ms * 50 ppm, < 1 us)
    assert true_deadline_us - 152 <= frame.fields["deadline_us"] <= true_deadline_us - 149


def test_reboot_is_detected_and_forces_a_new_sync(edge: ep.EdgeProtocol, clock: FakeClock) -> None:
    old = Car(nonce=b"o" * 16)
    old_join = old.join(5_000)
    old.open(edge, 5_000)
    _sync(edge, clock, old, offset_ns=0, rtt_ns=100_000)
    edge.encode_command(1, ep.Action.UP)
    new = Car(nonce=b"r" * 16)
    event = new.open(edge, 300)
    assert isinstance(event, ep.Joined) and event.reboot
    assert (event.previous_session, event.session) == (old.session, new.session)
    assert edge.session(1) == new.session != old.session and not edge.synced(1)
    with pytest.raises(ep.NotReady):
        edge.encode_command(1, ep.Action.UP)
    assert ep.decode(edge.encode_time_request(1)).seq == 1  # sequence restarts per session
    # frames of the old session are stale now: refused, and no HELLO (the car is live)
    assert edge.receive(old.status(6_000)) == ep.Rejected("wrong_session", 1)
    # the old JOIN replayed gets an offer nobody takes; the session stays
    assert isinstance(edge.receive(old_join), ep.Joining)
    assert [f[1] for _, f in edge.datagrams_to_send()] == [ep.MsgType.ACCEPT]
    assert edge.session(1) == new.session


def test_repeated_join_gets_the_same_offer_and_a_replayed_one_changes_nothing(
    edge: ep.EdgeProtocol, clock: FakeClock
) -> None:
    car = Car()
    first = car.join(1_000)
    edge.receive(first)
    edge.receive(car.join(1_250))  # the car repeats its JOIN: one nonce, one offer
    offers = [f for _, f in edge.datagrams_to_send()]
    assert len(offers) == 2 and offers[0] == offers[1]
    car.take(offers[0])
    assert isinstance(edge.receive(car.status(1_300)), ep.Joined)
    session = edge.session(1)
    for _ in range(3):
        assert isinstance(edge.receive(first), ep.Joining)
    assert edge.session(1) == session and edge.joined(1)
    assert isinstance(edge.receive(car.status(1_400)), ep.StatusReport)


def test_acks_carry_round_trip_and_receive_time(edge: ep.EdgeProtocol, clock: FakeClock) -> None:
    car = Car()
    car.open(edge, 1_000)
    _sync(edge, clock, car, offset_ns=-1_000_000_000, rtt_ns=200_000)
    cmd = ep.decode(edge.encode_command(1, ep.Action.DOWN))
    sent = clock.ns
    clock.ns += 300_000
    car_rx_us = (sent + 100_000 - 1_000_000_000) // 1000
    ack = edge.receive(
        car.frame(ep.MsgType.ACK, car_rx_us, ref_seq=cmd.seq, result=0, action=1, rx_us=car_rx_us)
    )
    assert isinstance(ack, ep.Acked)
    assert ack.result is ep.AckResult.ACCEPTED and ack.round_trip_ns == 300_000
    assert abs(ack.received_at_ns - (sent + 100_000)) <= 1_000


def test_replay_window_takes_reordered_frames_once(edge: ep.EdgeProtocol, clock: FakeClock) -> None:
    car = Car()
    car.open(edge, 1_000)
    frames = [car.status(1_000 + i) for i in range(70)]
    assert isinstance(edge.receive(frames[5]), ep.StatusReport)
    assert isinstance(edge.receive(frames[3]), ep.StatusReport)  # late but unseen
    assert edge.receive(frames[3]) == ep.Rejected("replay", 1)
    assert isinstance(edge.receive(frames[69]), ep.StatusReport)
    assert edge.receive(frames[4]) == ep.Rejected("replay", 1)  # fell out of the 64 window


def test_rejections(edge: ep.EdgeProtocol, clock: FakeClock) -> None:
    car = Car()
    assert edge.receive(b"") == ep.Rejected("malformed")
    assert edge.receive(b"\x09" * 40) == ep.Rejected("wrong_version")
    assert edge.receive(Car(car_id=3).join(1)) == ep.Rejected("unknown_car", 3)
    assert edge.receive(Car(key=OTHER_KEY).join(1)) == ep.Rejected("bad_tag", 1)
    car.session, car.session_key = 99, bytes(32)
    assert edge.receive(car.status(1)) == ep.Rejected("not_joined", 1)
    hello = [ep.decode(f) for _, f in edge.datagrams_to_send()]
    assert [(h.type, h.fields["reason"]) for h in hello] == [(ep.MsgType.HELLO, 0)]
    car.open(edge, 1_000)
    far = car.frame(
        ep.MsgType.STATUS,
        1_000 + 61_000_000,
        row=0,
        col=0,
        battery_mv=1,
        faults=0,
        state=0,
        done_seq=0,
    )
    assert edge.receive(far) == ep.Rejected("bad_time", 1)
    unsolicited = car.frame(ep.MsgType.TIME_RESPONSE, 1_000, t1_ns=1, t2_us=1_000, t3_us=1_000)
    assert edge.receive(unsolicited) == ep.Rejected("unsolicited", 1)


def test_estop_all_and_leave(edge: ep.EdgeProtocol, clock: FakeClock) -> None:
    one, two = Car(1, b"1" * 16), Car(2, b"2" * 16, OTHER_KEY)
    one.open(edge, 1_000)
    two.open(edge, 1_000)
    frames = edge.encode_estop_all()
    assert sorted(frames) == [1, 2]
    for car_id, frame in frames.items():
        d = ep.decode(frame)
        assert (d.type, d.car_id, d.fields["engage"]) == (ep.MsgType.ESTOP, car_id, 1)
    with pytest.raises(ep.NotReady):
        edge.encode_estop(1, engage=False)  # a release needs a synchronised clock
    assert edge.receive(two.frame(ep.MsgType.LEAVE, 2_000, reason=1)) == ep.Left(2, "low_battery")
    assert edge.joined_cars() == [1]


def test_add_car_checks_the_key() -> None:
    with pytest.raises(ValueError, match="32 bytes"):
        ep.EdgeProtocol({1: b"short"})
    with pytest.raises(ValueError, match="outside"):
        ep.EdgeProtocol({0: KEY})


def test_can_mapping_round_trip_and_checks() -> None:
    car = Car(car_id=5)
    car.session, car.session_key = 7, bytes(32)
    frame = car.status(10)  # 40 bytes: padded to 48
    can_id, data = ep.can_pack(frame)
    assert can_id == 0x185 and len(data) == 48
    assert ep.can_unpack(can_id, data) == frame
    with pytest.raises(ep.FrameError):
        ep.can_unpack(0x186, data)
    with pytest.raises(ep.FrameError):
        ep.can_unpack(can_id, data[:-1] + b"\x01")
    with pytest.raises(ValueError):
        ep.can_pack(Car(car_id=200).join(10))


def test_a_jump_in_sequence_numbers_costs_no_time(edge: ep.EdgeProtocol) -> None:
    """A frame 2^32 - 10 ahead must not make the replay window shift by billions of bits."""
    car = Car()
    car.open(edge, 1_000)
    car.seq = 2**32 - 11
    started = time.perf_counter()
    assert isinstance(edge.receive(car.status(1_000)), ep.StatusReport)
    assert time.perf_counter() - started < 0.05  # it took seconds and gigabytes before
    car.seq = 2**32 - 13
    assert isinstance(edge.receive(car.status(1_000)), ep.StatusReport)  # inside the window


def test_guidance_fields_are_what_the_spec_says_and_never_out_of_range() -> None:
    """Millimetres and milliradians, headings wrapped into -pi..pi; a pose older than a
    second (or off the 16-bit range) is left out rather than sent; a target or start delay no
    frame can carry is a bug: ValueError before anything is sent."""
    now = 5_000_000_000
    fields = ep.guide_fields(
        ep.Guidance((1.4, 1.0889, 6.2), (1.4123, 1.0851, -3.5), now - 18_500_000, 0.65), now
    )
    assert fields == {
        "guide": 3, "target_x_mm": 1400, "target_y_mm": 1089, "target_heading_mrad": -83,
        "pose_x_mm": 1412, "pose_y_mm": 1085, "pose_heading_mrad": 2783, "pose_age_us": 18_500,
        "delay_pct": 65,
    }  # fmt: skip
    stale = ep.guide_fields(ep.Guidance((1.4, 1.0, 0.0), (1.4, 1.0, 0.0), now - 1_000_001_000), now)
    assert stale["guide"] == ep.GUIDE_TARGET and stale["pose_age_us"] == 0
    far = ep.guide_fields(ep.Guidance((1.4, 1.0, 0.0), (40.0, 1.0, 0.0), now), now)
    assert far["guide"] == ep.GUIDE_TARGET
    with pytest.raises(ValueError, match="target"):
        ep.guide_fields(ep.Guidance((33.0, 1.0, 0.0)), now)
    with pytest.raises(ValueError, match="delay"):
        ep.guide_fields(ep.Guidance((1.0, 1.0, 0.0), delay=2.5), now)
    assert ep.guide_fields(None, now) == dict.fromkeys(fields, 0)
