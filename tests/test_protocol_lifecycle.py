"""The fleet's life cycle under protocol v2: edge restarts, replays, renewal, other versions.

An edge restarted after its previous process had sent 10, 10^6 or 2^32 - 10 frames to a car gets
the car back under command within a second on every transport: UDP (the cars in a
``udan-firmware-mock`` process), a serial line (pty pairs) and CAN FD (python-can's virtual bus).
The previous process's count is reached by sending, in its session and under its session key
(derived from the nonces its ACCEPT carried in the clear), one frame with that sequence number:
what the car keeps of those frames is the highest seq, and that is what it ends up holding
(``bench/protocol.py`` measures the same recovery and prints it).
"""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import os
import sys
import time
import tty
import uuid
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import can
import pytest
from test_link import FAST, LoopFleet, MockProcess, WiredCar, all_finished, fleet, until
from test_protocol_fuzz import bench

from udan.edge import protocol as ep
from udan.edge.link import CarLink
from udan.edge.transport import Transport, free_udp_port, open_transport
from udan.envs.rules import DOWN, UP
from udan.firmware_mock import wire
from udan.firmware_mock.can_car import CanCar
from udan.firmware_mock.core import RENEW_AT, SEQ_MAX, CarCore, Telemetry
from udan.firmware_mock.fleet import CarSpec
from udan.fleetfile import CarEntry, load_fleet

PREVIOUS_RUNS = [10, 10**6, 2**32 - 10]
RECOVERY_S = 1.0  # the design's target: edge restart -> every car back under command
MOCK = ["-m", "udan.firmware_mock.cli"]


class Rig:
    """Cars on one transport, and how to build the edge's end of it again and again."""

    entries: list[CarEntry]

    def transport(self) -> Transport:
        raise NotImplementedError


class UdpRig(Rig):
    """The cars in a ``udan-firmware-mock`` process; the edge binds one port every time."""

    def __init__(self, folder: Path) -> None:
        self.path = path = bench.fleet_file(folder, (1, 2))
        self.entries = load_fleet(path)
        self.listen = f"127.0.0.1:{free_udp_port()}"
        self.mock: MockProcess | None = None

    async def start(self) -> None:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, *MOCK, "--keys", str(self.path), "--base-port", "0",
            "--edge", self.listen, "--control-port", "0", "--cell-time-ms", "20",
            stdout=asyncio.subprocess.PIPE,
        )  # fmt: skip
        assert proc.stdout is not None
        self.mock = MockProcess(
            proc, json.loads(await asyncio.wait_for(proc.stdout.readline(), 20))
        )

    def transport(self) -> Transport:
        return open_transport("udp", self.entries, listen=self.listen)

    async def close(self) -> None:
        if self.mock is not None:
            await self.mock.stop()


class SerialRig(Rig):
    """Two cars wired to the edge by pty pairs; the edge reopens the same devices."""

    def __init__(self) -> None:
        self.ptys = [os.openpty() for _ in range(2)]
        for _, slave in self.ptys:
            tty.setraw(slave)
        self.entries = [
            CarEntry(c, c, bytes([c]) * 32, serial=os.ttyname(slave))
            for c, (_, slave) in enumerate(self.ptys, 1)
        ]
        self.cars: list[WiredCar] = []

    async def start(self) -> None:
        self.cars = [WiredCar(e, m) for e, (m, _) in zip(self.entries, self.ptys, strict=True)]
        for car in self.cars:
            car.firmware.start()

    def transport(self) -> Transport:
        return open_transport("serial", self.entries)

    async def close(self) -> None:
        for car in self.cars:
            car.close()
        for master, slave in self.ptys:
            os.close(master)
            os.close(slave)


class CanRig(Rig):
    """Two cars on a virtual CAN FD bus; the edge joins the same channel every time."""

    def __init__(self) -> None:
        self.channel = f"udan-{uuid.uuid4().hex}"
        self.entries = fleet(2)
        self.buses: list[can.BusABC] = []
        self.cars: list[CanCar] = []

    async def start(self) -> None:
        for e in self.entries:
            bus = can.Bus(
                interface="virtual", channel=self.channel, protocol=can.CanProtocol.CAN_FD
            )
            self.buses.append(bus)
            car = CanCar(CarSpec(e.car_id, e.marker, e.key), bus, timing=FAST, seed=e.car_id)
            await car.start()
            self.cars.append(car)

    def transport(self) -> Transport:
        return open_transport("can", self.entries, interface="virtual", channel=self.channel)

    async def close(self) -> None:
        for car in self.cars:
            car.close()
        for bus in self.buses:
            bus.shutdown()


def unsolicited(link: CarLink) -> int:
    return link.counters()["rejected"].get("unsolicited", 0)  # type: ignore[union-attr]


@pytest.fixture(params=["udp", "serial", "can"])
async def rig(request: pytest.FixtureRequest, tmp_path: Path) -> AsyncIterator[Rig]:
    made: Any = {"udp": lambda: UdpRig(tmp_path), "serial": SerialRig, "can": CanRig}[
        request.param
    ]()
    await made.start()
    try:
        yield made
    finally:
        await made.close()


@pytest.mark.parametrize("previous_frames", PREVIOUS_RUNS, ids=["10", "1e6", "2^32-10"])
async def test_a_restarted_edge_has_every_car_back_within_a_second(
    rig: Rig, previous_frames: int
) -> None:
    cars = {e.car_id for e in rig.entries}
    transport = rig.transport()
    sent, _ = bench.tap(transport)
    previous = CarLink(rig.entries, transport)
    await previous.start()
    try:
        await bench.under_command(previous, cars)
        for entry in rig.entries:  # what the previous process's frames left on each car
            transport.send(entry.car_id, bench.frame_at_seq(entry, sent, previous_frames))
        # a car answers a time request only when it took it: the answers' t1 is no request of
        # this edge's, so each comes back as unsolicited
        await until(previous, lambda: unsolicited(previous) == len(cars), timeout=2)
    finally:
        await previous.close()
    await asyncio.sleep(0.01)  # the old socket is released from the event loop
    started = time.monotonic()
    fresh = CarLink(rig.entries, rig.transport())
    await fresh.start()
    try:
        await bench.under_command(fresh, cars)
        recovery = time.monotonic() - started
        assert fresh.counters()["hellos"] >= len(cars)  # it asked the cars; they did not reboot
        assert fresh.counters()["reboots"] == 0
    finally:
        await fresh.close()
    print(f"{previous_frames} frames before: back under command after {recovery:.3f} s")
    assert recovery <= RECOVERY_S


# --- replays -----------------------------------------------------------------------------------
class Recorder:
    """Every frame on a loop fleet, both directions, as an eavesdropper keeps them."""

    def __init__(self, f: LoopFleet) -> None:
        self.to_cars: list[tuple[int, bytes]] = []
        self.to_edge: list[bytes] = []
        original = f.transport.car_send

        def car_send(frame: bytes) -> None:
            self.to_edge.append(frame)
            original(frame)

        f.transport.car_send = car_send  # type: ignore[method-assign]
        self.fleet = f

    def take_edge_frames(self) -> None:
        self.to_cars += self.fleet.transport.sent
        self.fleet.transport.sent = []


def snapshot(f: LoopFleet) -> dict[int, tuple[Any, ...]]:
    """What a replay must not change on any car (the edge's own re-syncs go on meanwhile)."""
    return {
        c: (
            car.firmware.core.session,
            car.drive.executed,
            car.drive.pose,
            car.firmware.core.estopped,
            car.drive.aborted,  # a replayed stop would cut a move
        )
        for c, car in f.cars.items()
    }


async def replay_everything(f: LoopFleet, rec: Recorder) -> None:
    recorded = list(rec.to_edge)  # the recorder goes on recording, the replays too
    for car_id, frame in list(rec.to_cars):
        f.cars[car_id].receive(frame)
    for frame in recorded:
        f.transport.car_send(frame)
    await asyncio.sleep(0.15)  # anything the replays could start has started


async def drive(f: LoopFleet, link: CarLink, steps: int) -> None:
    """``steps`` steps up and down, each dispatched again until every car took it in time (a
    loaded machine can make a car miss one now and then; here it must not miss for long)."""
    cars = set(f.cars)

    def ready() -> bool:
        return link.ready_cars() == cars and all_finished(link, cars)()

    async with asyncio.timeout(5 + steps):
        for i in range(steps):
            on_time = 0
            while on_time < len(cars):
                await until(link, ready)
                actions = dict.fromkeys(cars, (UP, DOWN)[i % 2])
                on_time = (await link.dispatch(actions, time.monotonic_ns())).on_time
                await asyncio.sleep(0)  # a dispatch that sent nothing awaited nothing
    await until(link, all_finished(link, cars))


async def test_recorded_frames_of_every_earlier_session_replayed_change_nothing() -> None:
    f = LoopFleet(2, time.monotonic_ns)
    rec = Recorder(f)
    await f.start()
    link = f.link
    try:
        await drive(f, link, 4)  # session 1
        link.estop_all()
        await asyncio.sleep(0.02)
        link.estop_all(engage=False)
        await asyncio.sleep(0.02)
        f.cars[1].firmware.reboot()  # car 1: session 2
        await until(link, lambda: link.counters()["reboots"] == 1)
        await drive(f, link, 2)
        await link.close()  # the edge restarts: session 3 with a new process
        link = f.link = CarLink(f.entries, f.transport)
        await link.start()
        await drive(f, link, 2)
        rec.take_edge_frames()
        kinds = {frame[1] for _, frame in rec.to_cars} | {frame[1] for frame in rec.to_edge}
        assert {ep.MsgType.JOIN, ep.MsgType.COMMAND, ep.MsgType.ACK, ep.MsgType.STATUS} <= kinds
        sessions = {wire.parse(frame).session for frame in rec.to_edge} - {0}
        assert len(sessions) >= 5  # two cars, three edges' worth of sessions

        await asyncio.sleep(0.6)  # past the new edge's own HELLOs
        before = snapshot(f)
        for _ in range(3):  # any time: now, and again after more steps
            await replay_everything(f, rec)
            assert snapshot(f) == before
            await drive(f, link, 2)
            before = snapshot(f)
        counters = {c: car.counters for c, car in f.cars.items()}
        assert all(c["rejected"]["wrong_session"] > 0 for c in counters.values())
        assert all(c["rejected"]["stale_accept"] > 0 for c in counters.values())
        assert link.counters()["rejected"]["unsolicited"] > 0  # replayed HELLOs went nowhere
    finally:
        await f.close()


def secret_forms(secret: bytes) -> dict[str, str]:
    """The ways a secret could show in a text: hex either case, base64, Python's bytes repr."""
    return {
        "hex": secret.hex(),
        "HEX": secret.hex().upper(),
        "base64": base64.b64encode(secret).decode(),
        "base64url": base64.urlsafe_b64encode(secret).decode().rstrip("="),
        "bytes repr": repr(secret)[2:-1],
    }


def session_secrets(f: LoopFleet, rec: Recorder) -> tuple[set[bytes], set[bytes]]:
    """The nonces of every ACCEPT on the wire, and the session keys they opened (derived from
    the car's key as both ends derive it)."""
    keys = {e.car_id: e.key for e in f.entries}
    nonces, session_keys = set(), set()
    for car_id, frame in rec.to_cars:
        if frame[1] == ep.MsgType.ACCEPT:
            fields = ep.decode(frame).fields
            car_nonce, edge_nonce = bytes(fields["car_nonce"]), bytes(fields["edge_nonce"])
            nonces |= {car_nonce, edge_nonce}
            session_keys.add(ep.derive_session(keys[car_id], car_nonce, edge_nonce)[1])
    return nonces, session_keys


async def test_no_key_nonce_or_session_key_in_any_log_or_count(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Everything either side logs or counts through a fleet's life — sessions opened, a car
    rebooted, the edge restarted, every frame replayed, frames forged and of another version —
    holds no car key, no session nonce and no session key, in any spelling."""
    caplog.set_level(logging.DEBUG)
    f = LoopFleet(2, time.monotonic_ns)
    rec = Recorder(f)
    await f.start()
    links = [f.link]
    try:
        await drive(f, f.link, 3)
        f.cars[1].firmware.reboot()
        await until(f.link, lambda: f.link.counters()["reboots"] == 1)
        await drive(f, f.link, 2)
        await f.link.close()
        f.link = CarLink(f.entries, f.transport)
        links.append(f.link)
        await f.link.start()
        await drive(f, f.link, 2)
        rec.take_edge_frames()
        await replay_everything(f, rec)
        for car_id, frame in list(rec.to_cars)[:8]:
            f.cars[car_id].receive(frame[:-1] + bytes([frame[-1] ^ 1]))  # a forged tag
            f.cars[car_id].receive(bytes([1]) + frame[1:])  # a v1 frame
        for frame in list(rec.to_edge)[:8]:
            f.transport.car_send(frame[:-1] + bytes([frame[-1] ^ 1]))
            f.transport.car_send(bytes([3]) + frame[1:])  # a frame of a version to come
        await asyncio.sleep(0.15)
        outputs = {
            "logs": caplog.text,
            "edge counts": json.dumps([link.counters() for link in links], default=repr),
            "car counts": repr({c: car.counters for c, car in f.cars.items()}),
        }
    finally:
        await f.close()
    nonces, session_keys = session_secrets(f, rec)
    assert len(session_keys) >= 5 and len(nonces) >= 10  # two cars, three edges' sessions
    assert "refused" in caplog.text  # the refusals were logged: there was something to search
    car_keys = {e.key for e in f.entries}
    for name, text in outputs.items():
        for secret in car_keys | nonces | session_keys:
            shown = [kind for kind, form in secret_forms(secret).items() if form in text]
            assert not shown, f"{name} shows a secret spelt as {shown[0]}"


async def test_a_fresh_edge_fed_old_joins_first_still_gets_every_car() -> None:
    f = LoopFleet(2, time.monotonic_ns)
    rec = Recorder(f)
    await f.start()
    try:
        await drive(f, f.link, 2)
        f.cars[2].firmware.reboot()
        await until(f.link, lambda: f.link.counters()["reboots"] == 1)
        await f.link.close()
        joins = [frame for frame in rec.to_edge if frame[1] == ep.MsgType.JOIN]
        assert len(joins) >= 3
        fresh = f.link = CarLink(f.entries, f.transport)
        await fresh.start()
        started = time.monotonic()
        for join in list(joins):  # the attacker is first on the new edge
            f.transport.car_send(join)
        await bench.under_command(fresh, set(f.cars))
        assert time.monotonic() - started <= RECOVERY_S
    finally:
        await f.close()


# --- renewal before the counters end -----------------------------------------------------------
async def test_counters_near_their_end_renew_the_session_without_a_miss() -> None:
    f = LoopFleet(1, time.monotonic_ns)
    await f.start()
    link, car = f.link, f.cars[1].firmware.core
    try:
        first = car.session
        # the edge's counter starts just short of the renewal point (2^32 frames would take
        # days to send): every frame from here on is one the spec says must never wrap
        link._proto._peers[1].current.tx_seq = ep.RENEW_AT - 5
        sent_before = len(f.transport.sent)
        await drive(f, link, 10)
        await until(link, lambda: car.session not in (0, first))
        seqs = [ep.decode(frame).seq for _, frame in f.transport.sent[sent_before:]]
        assert max(seqs) < ep.SEQ_MAX and link.counters()["renewals"] == 1
        assert car.counters.reboots == 0 and 1 in link.ready_cars()  # the sync carried over
        await drive(f, link, 2)

        second = car.session
        car._current.tx_seq = RENEW_AT - 3  # now the car's side
        await until(link, lambda: car.session not in (0, second), timeout=3)
        assert link.counters()["renewals"] == 2
        await drive(f, link, 2)
    finally:
        await f.close()


def test_neither_side_sends_past_the_last_sequence_number() -> None:
    key = bytes(range(32))
    edge = ep.EdgeProtocol({1: key}, clock=lambda: 10**9)
    car = CarCore(1, key, 3)
    edge.receive(car.boot(0))
    ((_, accept),) = edge.datagrams_to_send()
    car.handle(accept, 0)
    edge.receive(car.status(0, Telemetry()))
    edge._peers[1].current.tx_seq = ep.SEQ_MAX - 1
    assert ep.decode(edge.encode_time_request(1)).seq == ep.SEQ_MAX
    with pytest.raises(ep.NotReady, match="used up"):
        edge.encode_time_request(1)
    car._current.tx_seq = SEQ_MAX - 1
    assert wire.parse(car.status(1, Telemetry())).seq == SEQ_MAX
    assert car.status(2, Telemetry()) is None and not car.joined  # it asks for a new session
    assert wire.parse(car.join(3)).payload["cause"] == wire.JOIN_RENEW


# --- other protocol versions -------------------------------------------------------------------
V1_JOIN = bytes.fromhex("0183030000011234abcd00000001002a00010000000003e85668708df1c8")
V1_COMMAND = bytes.fromhex(
    "0101090000011234abcd00000002000000000000002e7b000000000007d0e423de072ed4"
)


async def test_a_v1_car_and_a_v2_edge_refuse_each_other_in_one_logged_line(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING)
    f = LoopFleet(1, time.monotonic_ns)
    await f.start()
    try:
        for _ in range(5):  # a v1 car announcing itself every 250 ms
            f.transport.car_send(V1_JOIN)
        f.cars[1].receive(V1_COMMAND)  # a v1 edge commanding a v2 car
        f.cars[1].receive(V1_COMMAND)
        await asyncio.sleep(0.05)
        assert f.link.counters()["rejected"]["wrong_version"] == 5
        counters = f.cars[1].counters
        assert counters["rejected"]["wrong_version"] == 2 and counters["executed"] == 0
        lines = [r.getMessage() for r in caplog.records if "protocol v1" in r.getMessage()]
        assert sorted(lines) == [  # once each, however many frames came
            "car 1 sent a protocol v1 frame, this edge speaks v2: refused",
            "car 1: a protocol v1 frame refused, this firmware speaks v2",
        ]
        assert all("\n" not in line for line in lines)
        await drive(f, f.link, 1)  # the v2 car is unaffected
    finally:
        await f.close()
