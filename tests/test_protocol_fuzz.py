"""Property tests: random and mutated frames through both parsers and both stateful cores.

Nothing may raise, the two independent parsers must agree on every input, and no input that is
not byte-for-byte a frame the real sender produced may be accepted (a forgery needs the key).
The genuine frames are the ones ``make bench`` fuzzes (bench/protocol.py, loaded from its path:
bench/ is scripts, not a package), and a short round of that fuzz runs here too, so the JSON the
bench prints comes from a harness that is itself tested.
"""

from __future__ import annotations

import benches
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from udan.edge import protocol as ep
from udan.firmware_mock import wire

bench = benches.load("protocol")
CAR, EDGE, GENUINE, CAR_NOW_US = bench.genuine_frames()
GENUINE_SET = frozenset(GENUINE)


def _flip(frame: bytes, at: int, mask: int) -> bytes:
    b = bytearray(frame)
    b[at % len(b)] ^= mask
    return bytes(b)


def _overwrite(frame: bytes, at: int, chunk: bytes) -> bytes:
    at %= len(frame)
    return frame[:at] + chunk + frame[at + len(chunk) :]


frames = st.sampled_from(GENUINE)
inputs = st.one_of(
    st.binary(max_size=80),
    st.builds(_flip, frames, st.integers(0, 63), st.integers(1, 255)),
    st.builds(lambda f, n: f[:n], frames, st.integers(0, 70)),
    st.builds(lambda f, extra: f + extra, frames, st.binary(min_size=1, max_size=8)),
    st.builds(_overwrite, frames, st.integers(0, 63), st.binary(min_size=1, max_size=8)),
    st.builds(lambda a, b, n: a[:n] + b[n:], frames, frames, st.integers(0, 64)),
)


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(inputs)
def test_parsers_agree_and_never_raise(data: bytes) -> None:
    try:
        fw = wire.parse(data).describe()
    except wire.Malformed as err:
        fw = err.reason
    try:
        edge = ep.decode(data).as_vector()
    except ep.FrameError as err:
        edge = err.reason
    assert fw == edge


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(inputs)
def test_no_forgery_is_accepted_by_either_core(data: bytes) -> None:
    if data in GENUINE_SET:
        return
    out = CAR.handle(data, CAR_NOW_US)
    assert out.verdict not in ("accepted", "duplicate")
    assert out.motor is None and not out.halt
    assert isinstance(EDGE.receive(data), ep.Rejected)


def test_genuine_frames_are_accepted_so_the_property_is_not_vacuous() -> None:
    car, edge, pool, car_now = bench.genuine_frames()
    command = next(f for f in reversed(pool) if f[1] == wire.COMMAND)
    assert car.handle(command, car_now).verdict == "accepted"
    status = next(f for f in reversed(pool) if f[1] == wire.STATUS)  # not the confirming one
    assert isinstance(edge.receive(status), ep.StatusReport)


def test_bench_fuzz_round_finds_no_crash_and_no_forgery() -> None:
    result = bench.fuzz(5_000, seed=3)
    assert (result["inputs"], result["crashes"], result["accepted_forgeries"]) == (5_000, 0, 0)
    verdicts = result["car_verdicts"]
    # the mutations reach every stage of the car's checks, the tag check included
    assert all(verdicts.get(r, 0) > 0 for r in ("malformed", "wrong_version", "bad_tag"))
    assert sum(verdicts.values()) == 5_000
