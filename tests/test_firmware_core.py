"""The car's sans-I/O core with an injected clock (frames built by the firmware's own encoder)."""

from __future__ import annotations

import pytest

from udan.firmware_mock import wire
from udan.firmware_mock.core import DUPLICATE_CACHE, CarCore, Telemetry

KEY = bytes(range(100, 132))
EDGE_NONCE = bytes(range(16))


def accept(join: bytes, edge_nonce: bytes = EDGE_NONCE, key: bytes = KEY) -> bytes:
    """The edge's ACCEPT answering ``join``, as the spec describes it."""
    car_nonce = wire.parse(join).payload["car_nonce"]
    return wire.encode(
        wire.ACCEPT, 1, 0, 0, 0, key, car_nonce=car_nonce, edge_nonce=edge_nonce, version=2
    )


class Edge:
    """Edge frames for car 1 in the session a JOIN and an ACCEPT opened."""

    def __init__(self, join: bytes, edge_nonce: bytes = EDGE_NONCE, key: bytes = KEY) -> None:
        car_nonce = wire.parse(join).payload["car_nonce"]
        self.session, self.key = wire.session_for(KEY, car_nonce, edge_nonce)
        if key != KEY:
            self.key = key
        self.seq = 0

    def command(self, action: int, now_us: int, validity_us: int = 10_000) -> bytes:
        self.seq += 1
        return wire.encode(
            wire.COMMAND,
            1,
            self.session,
            self.seq,
            now_us,
            self.key,
            action=action,
            deadline_us=now_us + validity_us,
        )


@pytest.fixture
def joined() -> tuple[CarCore, bytes]:
    """A car in a session, and the JOIN that opened it."""
    core = CarCore(1, KEY, marker=9)  # the default watchdog: 300 ms, as the spec says
    join = core.boot(0)
    assert core.handle(accept(join), 0).verdict == "joined"
    return core, join


@pytest.fixture
def car(joined: tuple[CarCore, bytes]) -> CarCore:
    return joined[0]


@pytest.fixture
def edge(joined: tuple[CarCore, bytes]) -> Edge:
    return Edge(joined[1])


def test_boot_announces_join_and_resets(car: CarCore, edge: Edge) -> None:
    assert car.handle(edge.command(0, 100), 100).verdict == "accepted"
    join = wire.parse(car.boot(5))
    assert (join.type, join.session, join.seq, join.payload["marker"]) == (wire.JOIN, 0, 0, 9)
    assert join.payload["cause"] == wire.JOIN_BOOT and len(join.payload["car_nonce"]) == 16
    assert not car.joined and car.counters.reboots == 1
    assert car.handle(edge.command(0, 200), 200).verdict == "wrong_session"


def test_duplicate_cache_is_bounded_then_replay(car: CarCore, edge: Edge) -> None:
    first = edge.command(4, 10, validity_us=900_000)
    assert car.handle(first, 10).verdict == "accepted"
    assert car.handle(first, 20).verdict == "duplicate"
    for i in range(DUPLICATE_CACHE):
        assert car.handle(edge.command(4, 30 + i), 30 + i).verdict == "accepted"
    out = car.handle(first, 100)
    assert out.verdict == "replay" and out.motor is None
    ack = wire.parse(out.replies[0])
    assert wire.RESULTS[ack.payload["result"]] == "replay"
    assert car.counters.duplicates == 1 and car.counters.rejected["replay"] == 1


def test_the_resend_of_a_command_that_came_expired_is_a_replay(car: CarCore, edge: Edge) -> None:
    """Spec section 4: a frame refused after step 7 still advances the replay window, and step 6
    answers copies of accepted frames only. So when a loaded machine delivers a command after
    its deadline and the edge's resend (sent before the refusal's ACK came back) follows, the
    car refuses the first as expired and the copy as a replay; neither moves anything."""
    late = edge.command(2, 1_000, validity_us=5_000)
    first = car.handle(late, 7_000)
    assert first.verdict == "expired" and first.motor is None
    copy = car.handle(late, 7_400)
    assert copy.verdict == "replay" and copy.motor is None
    assert car.counters.rejected["expired"] == 1 and car.counters.rejected["replay"] == 1
    assert car.counters.duplicates == 0


def test_watchdog_trips_once_and_rearms_on_the_next_command(car: CarCore, edge: Edge) -> None:
    assert car.next_wakeup_us() is None
    car.handle(edge.command(0, 1_000), 1_000)
    assert car.next_wakeup_us() == 301_000
    assert not car.poll(300_999)
    assert car.poll(301_000)
    assert not car.poll(400_000)
    status = wire.parse(car.status(400_000, Telemetry()))
    assert status.payload["faults"] & wire.FAULT_WATCHDOG
    car.handle(edge.command(0, 500_000), 500_000)
    assert not car.watchdog_tripped and car.counters.watchdog_stops == 1


def test_unauthenticated_frames_get_no_answer(car: CarCore, edge: Edge, joined) -> None:
    forged = bytearray(edge.command(0, 10))
    forged[-2] ^= 0x10
    other_key = Edge(joined[1], key=bytes(32)).command(0, 10)
    for data in (bytes(forged), other_key, b"\x02" * 30, b""):
        out = car.handle(data, 10)
        assert out.replies == () and out.motor is None and out.verdict != "accepted"
    assert car.counters.accepted == 0 and car.counters.received == 5  # the ACCEPT, then these


def test_time_request_is_answered_with_car_times(car: CarCore, edge: Edge) -> None:
    req = wire.encode(wire.TIME_REQ, 1, edge.session, 1, 50, edge.key, t1_ns=123_456)
    out = car.handle(req, 777)
    resp = wire.parse(out.replies[0])
    assert resp.type == wire.TIME_RESP
    assert resp.payload == {"t1_ns": 123_456, "t2_us": 777, "t3_us": 777}
    assert car.joined and out.motor is None


def test_counters_list_every_reason(car: CarCore) -> None:
    counters = car.counters.as_dict()
    assert set(counters["rejected"]) >= {
        "bad_tag",
        "replay",
        "expired",
        "malformed",
        "unknown_car",
        "wrong_session",
        "bad_time",
        "estopped",
    }


def test_key_length_is_checked() -> None:
    with pytest.raises(ValueError, match="32 bytes"):
        CarCore(1, b"short", marker=1)
