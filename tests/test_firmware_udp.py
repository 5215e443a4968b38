"""Mock WiFi cars over real UDP sockets on loopback, driven by the edge's protocol core.

In-process cars (``MockCar``) for the fine-grained checks, and the ``udan-firmware-mock`` CLI as a
separate process for the end-to-end one and for its error handling.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from udan.edge import protocol as ep
from udan.edge.geometry import ArenaGeometry
from udan.firmware_mock.cli import _parser
from udan.firmware_mock.firmware import CarTiming
from udan.firmware_mock.fleet import CarSpec
from udan.firmware_mock.udp import MockCar
from udan.hil.motion import LEVELS
from udan.hil.world import HilWorld

KEYS = {1: bytes(range(32)), 2: bytes(range(50, 82))}
MOCK_CLI = [
    sys.executable,
    "-c",
    "import sys; from udan.firmware_mock.cli import main; sys.exit(main())",
]


class EdgeClient(asyncio.DatagramProtocol):
    """A minimal edge: one UDP socket and the edge's sans-I/O core."""

    def __init__(self, keys: dict[int, bytes]) -> None:
        self.proto = ep.EdgeProtocol(keys)
        self.events: asyncio.Queue[ep.Event] = asyncio.Queue()
        self.cars: dict[int, Any] = {}
        self.joins: dict[int, ep.Joined] = {}
        self.transport: Any = None
        self.address: tuple[str, int] = ("", 0)

    def datagram_received(self, data: bytes, addr: Any) -> None:
        event = self.proto.receive(data)
        for _car, frame in self.proto.datagrams_to_send():  # ACCEPT, HELLO: answers
            self.transport.sendto(frame, addr)
        if isinstance(event, ep.Joined):
            self.cars[event.car_id] = addr
            self.joins[event.car_id] = event
        self.events.put_nowait(event)

    @classmethod
    async def open(cls, keys: dict[int, bytes]) -> EdgeClient:
        client = cls(keys)
        transport, _ = await asyncio.get_running_loop().create_datagram_endpoint(
            lambda: client, local_addr=("127.0.0.1", 0)
        )
        client.transport = transport
        client.address = transport.get_extra_info("sockname")[:2]
        return client

    def send(self, car_id: int, frame: bytes) -> None:
        self.transport.sendto(frame, self.cars[car_id])

    async def expect(
        self, kind: type, where: Callable[[Any], bool] = lambda e: True, timeout: float = 2.0
    ) -> Any:
        """The next event of ``kind`` matching ``where`` (others are skipped)."""
        async with asyncio.timeout(timeout):
            while True:
                event = await self.events.get()
                if isinstance(event, kind) and where(event):
                    return event

    async def quiet(self, kind: type, seconds: float) -> list[Any]:
        """Every event of ``kind`` that arrives within ``seconds``."""
        seen = []
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                event = await asyncio.wait_for(self.events.get(), left)
            except TimeoutError:
                break
            if isinstance(event, kind):
                seen.append(event)
        return seen

    async def join(self, car_id: int) -> ep.Joined:
        """Wait for the car's JOIN (unless it came already), then synchronise its clock."""
        if car_id not in self.joins:
            await self.expect(ep.Joined, lambda e: e.car_id == car_id)
        self.send(car_id, self.proto.encode_time_request(car_id))
        await self.expect(ep.TimeSynced, lambda e: e.car_id == car_id)
        return self.joins[car_id]

    async def command(self, car_id: int, action: int, validity_ns: int = 500_000_000) -> ep.Acked:
        """Send a command and wait for its ack.

        The validity is generous: these tests are about what the car does with a command, and a
        loaded machine can take longer than the 10 ms default between encoding and receiving.
        """
        frame = self.proto.encode_command(car_id, action, validity_ns)
        self.send(car_id, frame)
        seq = ep.decode(frame).seq
        return await self.expect(ep.Acked, lambda e: e.car_id == car_id and e.ref_seq == seq)

    def close(self) -> None:
        self.transport.close()


@pytest.fixture
async def edge() -> AsyncIterator[EdgeClient]:
    client = await EdgeClient.open(KEYS)
    yield client
    client.close()


@pytest.fixture
async def make_car(edge: EdgeClient) -> AsyncIterator[Callable[..., Any]]:
    cars: list[MockCar] = []

    async def make(
        car_id: int = 1, faults: dict[str, Any] | None = None, world: Any = None, **timing: Any
    ) -> MockCar:
        spec = CarSpec(car_id, 40 + car_id, KEYS[car_id], faults=faults or {})
        timing.setdefault("cell_time_s", 0.02)
        car = MockCar(spec, edge=edge.address, world=world, timing=CarTiming(**timing), seed=car_id)
        await car.start()
        cars.append(car)
        return car

    yield make
    for car in cars:
        car.close()


async def test_valid_command_is_executed_and_acked(edge: EdgeClient, make_car) -> None:
    car = await make_car()
    joined = await edge.join(1)
    assert (joined.marker, joined.session) == (41, car.state()["session"])
    ack = await edge.command(1, ep.Action.UP)
    assert ack.result is ep.AckResult.ACCEPTED and ack.action == ep.Action.UP
    status = await edge.expect(ep.StatusReport, lambda s: s.done_seq == ack.ref_seq)
    assert (status.row, status.col) == (3, 4) == tuple(car.state()["pose"])
    counters = car.counters()
    assert (counters["accepted"], counters["executed"]) == (2, 1)
    assert sum(counters["rejected"].values()) == 0


async def test_forged_replayed_expired_malformed_are_rejected_never_executed(
    edge: EdgeClient, make_car
) -> None:
    car = await make_car()
    await edge.join(1)
    first = edge.proto.encode_command(1, ep.Action.DOWN, validity_ns=900_000_000)
    edge.send(1, first)
    await edge.expect(ep.Acked, lambda e: e.result is ep.AckResult.ACCEPTED)
    for _ in range(20):  # push ``first`` out of the duplicate cache
        last = await edge.command(1, ep.Action.WAIT)
    await edge.expect(ep.StatusReport, lambda s: s.done_seq == last.ref_seq and not s.moving)
    executed = car.counters()["executed"]
    pose = car.state()["pose"]

    forged = bytearray(edge.proto.encode_command(1, ep.Action.LEFT))
    forged[-1] ^= 0x80
    wrong_key = ep.encode(
        ep.MsgType.COMMAND,
        1,
        car.state()["session"],
        999,
        0,
        KEYS[2],
        {"action": 3, "deadline_us": 1 << 40},
    )
    stale = edge.proto.encode_command(1, ep.Action.RIGHT, validity_ns=1_000_000)
    await asyncio.sleep(0.01)
    for frame in (bytes(forged), wrong_key, first, stale, first[:-3], b"\x01" + first[1:], b"\x02"):
        edge.send(1, frame)
    replay = await edge.expect(ep.Acked, lambda e: e.result is ep.AckResult.REPLAY)
    expired = await edge.expect(ep.Acked, lambda e: e.result is ep.AckResult.EXPIRED)
    assert replay.ref_seq == ep.decode(first).seq and expired.ref_seq == ep.decode(stale).seq
    assert await edge.quiet(ep.Acked, 0.1) == []  # forged and malformed frames: no answer
    counters = car.counters()
    rejected = counters["rejected"]
    assert rejected["bad_tag"] == 2 and rejected["replay"] == 1 and rejected["expired"] == 1
    assert rejected["malformed"] == 2 and rejected["wrong_version"] == 1
    assert counters["executed"] == executed and car.state()["pose"] == pose


async def test_duplicates_execute_once(edge: EdgeClient, make_car) -> None:
    car = await make_car(faults={"duplicate": 1.0})  # the link doubles every datagram
    await edge.join(1)
    before = car.counters()["duplicates"]  # the time request was doubled too
    frame = edge.proto.encode_command(1, ep.Action.LEFT, validity_ns=500_000_000)
    edge.send(1, frame)
    edge.send(1, frame)
    results = [(await edge.expect(ep.Acked)).result for _ in range(4)]
    assert sorted(results) == [ep.AckResult.ACCEPTED] + [ep.AckResult.DUPLICATE] * 3
    await edge.expect(ep.StatusReport, lambda s: s.done_seq == ep.decode(frame).seq)
    await asyncio.sleep(0.05)
    counters = car.counters()
    assert counters["executed"] == 1 and counters["duplicates"] - before == 3
    assert car.state()["pose"] == [4, 3]


async def test_reboot_is_detected_by_the_edge_and_the_car_must_rejoin(
    edge: EdgeClient, make_car
) -> None:
    car = await make_car(watchdog_s=5.0)
    first = await edge.join(1)
    await edge.command(1, ep.Action.UP)
    old_frame = edge.proto.encode_command(1, ep.Action.UP, validity_ns=900_000_000)
    car.firmware.apply_faults({"reboot_at_s": 0.05})
    rejoined = await edge.expect(ep.Joined)
    assert rejoined.reboot and rejoined.previous_session == first.session
    assert rejoined.session == car.state()["session"] != first.session
    assert not edge.proto.synced(1)
    edge.send(1, old_frame)  # a frame of the old session: refused, unanswered
    assert await edge.quiet(ep.Acked, 0.1) == []
    assert car.counters()["rejected"]["wrong_session"] == 1
    edge.send(1, edge.proto.encode_time_request(1))
    await edge.expect(ep.TimeSynced)
    assert (await edge.command(1, ep.Action.UP)).result is ep.AckResult.ACCEPTED
    assert car.counters()["reboots"] == 1


async def test_watchdog_stops_a_moving_car(edge: EdgeClient, make_car) -> None:
    car = await make_car(cell_time_s=2.0, watchdog_s=0.1)
    await edge.join(1)
    started = time.monotonic()
    await edge.command(1, ep.Action.RIGHT)
    status = await edge.expect(
        ep.StatusReport, lambda s: s.faults & ep.Fault.WATCHDOG and not s.moving
    )
    assert 0.09 <= time.monotonic() - started < 1.0
    assert (status.row, status.col) == (4, 4)
    counters = car.counters()
    assert counters["watchdog_stops"] == 1 and counters["aborted"] == 1
    assert counters["executed"] == 0
    await edge.command(1, ep.Action.WAIT)
    status = await edge.expect(ep.StatusReport)
    assert not status.faults & ep.Fault.WATCHDOG


async def test_estop_halts_and_latches(edge: EdgeClient, make_car) -> None:
    car = await make_car(cell_time_s=2.0)
    await edge.join(1)
    await edge.command(1, ep.Action.DOWN)
    for car_id, frame in edge.proto.encode_estop_all().items():
        edge.send(car_id, frame)
    await edge.expect(ep.Acked, lambda e: e.result is ep.AckResult.ACCEPTED and e.action is None)
    assert (await edge.command(1, ep.Action.DOWN)).result is ep.AckResult.ESTOPPED
    await edge.expect(ep.StatusReport, lambda s: s.faults & ep.Fault.ESTOP and not s.moving)
    assert car.counters()["aborted"] == 1
    edge.send(1, edge.proto.encode_estop(1, engage=False))
    await edge.expect(ep.Acked, lambda e: e.action is None)
    assert (await edge.command(1, ep.Action.WAIT)).result is ep.AckResult.ACCEPTED


async def test_stuck_wheel_dead_car_and_lossy_link(edge: EdgeClient, make_car) -> None:
    stuck = await make_car(1, faults={"stuck_wheel": True})
    lossy = await make_car(2, faults={"delay_ms": 30.0, "jitter_ms": 5.0})
    await edge.join(1)
    t0 = time.monotonic()
    await edge.join(2)
    assert time.monotonic() - t0 >= 0.045  # the time request and its answer were delayed
    ack = await edge.command(1, ep.Action.UP)
    status = await edge.expect(
        ep.StatusReport, lambda s: s.car_id == 1 and s.done_seq == ack.ref_seq
    )
    assert status.faults & ep.Fault.STALL and stuck.state()["pose"] == [4, 4]
    lossy.firmware.apply_faults({"delay_ms": 0.0, "jitter_ms": 0.0, "loss": 1.0})
    edge.send(2, edge.proto.encode_command(2, ep.Action.UP))
    stuck.firmware.apply_faults({"dead_at_s": 0.0})
    edge.send(1, edge.proto.encode_command(1, ep.Action.UP))
    assert await edge.quiet(ep.Acked, 0.15) == []
    assert stuck.counters()["dead_dropped"] == 1
    assert lossy.counters()["link_in"]["lost"] >= 1 and lossy.counters()["accepted"] == 1


async def test_reordered_command_is_refused_as_a_replay(edge: EdgeClient, make_car) -> None:
    car = await make_car(faults={"reorder": 1.0, "reorder_ms": 150.0})
    car.firmware.apply_faults({"reorder": 0.0})  # the join exchange goes through in order
    await edge.join(1)
    car.firmware.apply_faults({"reorder": 1.0})
    held = edge.proto.encode_command(1, ep.Action.UP, validity_ns=500_000_000)
    edge.send(1, held)  # held back 150 ms on the way in
    await asyncio.sleep(0.005)
    car.firmware.apply_faults({"reorder": 0.0})
    newer = await edge.command(1, ep.Action.DOWN)
    assert newer.result is ep.AckResult.ACCEPTED
    late = await edge.expect(ep.Acked, lambda e: e.ref_seq == ep.decode(held).seq)
    assert late.result is ep.AckResult.REPLAY  # the newer command won; the overtaken one is not run
    await edge.expect(ep.StatusReport, lambda s: s.done_seq == newer.ref_seq)
    assert car.counters()["executed"] == 1 and car.state()["pose"] == [5, 4]


# --- the CLI as a separate process ---------------------------------------------------------
def _fleet(tmp: Path, cars: list[dict[str, Any]]) -> Path:
    lines = []
    for car in cars:
        lines.append("[[car]]")
        lines += [f"{k} = {json.dumps(v)}" for k, v in car.items()]
    path = tmp / "fleet.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def spawn(tmp_path: Path):
    procs: list[subprocess.Popen] = []

    def start(edge_address: tuple[str, int]) -> tuple[subprocess.Popen, dict[str, Any]]:
        fleet = _fleet(
            tmp_path, [{"id": c, "marker": 40 + c, "key": k.hex()} for c, k in KEYS.items()]
        )
        host, port = edge_address
        args = ["--keys", str(fleet), "--base-port", "0", "--edge", f"{host}:{port}"]
        args += ["--control-port", "0", "--cell-time-ms", "20", "--seed", "7"]
        proc = subprocess.Popen(MOCK_CLI + args, stdout=subprocess.PIPE, text=True)
        procs.append(proc)
        assert proc.stdout is not None
        return proc, json.loads(proc.stdout.readline())

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
        proc.wait(5)
        if proc.stdout is not None:
            proc.stdout.close()


def _control(port: int, request: dict[str, Any]) -> dict[str, Any]:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(2)
        s.sendto(json.dumps(request).encode(), ("127.0.0.1", port))
        return json.loads(s.recv(1 << 16))


async def test_cli_process_cars_execute_ack_and_leave(edge: EdgeClient, spawn) -> None:
    proc, ready = spawn(edge.address)
    assert ready["ready"] and [c["id"] for c in ready["cars"]] == [1, 2]
    for car_id in (1, 2):
        await edge.join(car_id)
    acks = [await edge.command(c, ep.Action.DOWN) for c in (1, 2)]
    assert all(a.result is ep.AckResult.ACCEPTED for a in acks)
    forged = bytearray(edge.proto.encode_command(2, ep.Action.UP))
    forged[20] ^= 1
    edge.send(2, bytes(forged))
    await edge.expect(ep.StatusReport, lambda s: s.car_id == 2 and s.done_seq == acks[1].ref_seq)
    counters = await asyncio.to_thread(_control, ready["control_port"], {"op": "counters"})
    assert counters["cars"]["2"]["executed"] == 1
    assert counters["cars"]["2"]["rejected"]["bad_tag"] == 1
    state = await asyncio.to_thread(_control, ready["control_port"], {"op": "state"})
    assert state["cars"]["1"]["pose"] == [5, 4]
    proc.send_signal(signal.SIGTERM)
    left = {(await edge.expect(ep.Left)).car_id for _ in range(2)}
    assert left == {1, 2}
    assert await asyncio.to_thread(proc.wait, 5) == 0


GOOD_KEY = "ab" * 32


@pytest.mark.parametrize(
    ("name", "content"),
    [
        ("missing key", "[[car]]\nid = 1\nmarker = 1\nport = 9101\n"),
        ("short key", f'[[car]]\nid = 1\nmarker = 1\nport = 9101\nkey = "{GOOD_KEY[:40]}"\n'),
        ("not hex", f'[[car]]\nid = 1\nmarker = 1\nport = 9101\nkey = "{"zz" * 32}"\n'),
        (
            "duplicate id",
            f'[[car]]\nid = 1\nmarker = 1\nport = 9101\nkey = "{GOOD_KEY}"\n'
            f'[[car]]\nid = 1\nmarker = 2\nport = 9102\nkey = "{GOOD_KEY}"\n',
        ),
        (
            "duplicate port",
            f'[[car]]\nid = 1\nmarker = 1\nport = 9101\nkey = "{GOOD_KEY}"\n'
            f'[[car]]\nid = 2\nmarker = 2\nport = 9101\nkey = "{GOOD_KEY}"\n',
        ),
        ("short key file", '[[car]]\nid = 1\nmarker = 1\nport = 9101\nkey_file = "k.bin"\n'),
        ("malformed toml", "[[car]\nid = 1\n"),
        ("no cars", "title = 'fleet'\n"),
        ("unreadable", None),
    ],
)
def test_cli_bad_fleet_file_is_one_line_exit_2(tmp_path: Path, name: str, content: str) -> None:
    path = tmp_path / "fleet.toml"
    (tmp_path / "k.bin").write_bytes(os.urandom(16))
    if content is not None:
        path.write_text(content)
    _fails_with_one_line("--keys", str(path))


def _fails_with_one_line(*args: str) -> str:
    """Run the CLI expecting a usage error: exit 2, one line on stderr, nothing on stdout."""
    proc = subprocess.run([*MOCK_CLI, *args], capture_output=True, text=True, timeout=20)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith("udan-firmware-mock: error:") and proc.stdout == ""
    return proc.stderr


def test_cli_port_in_use_is_one_line_exit_2(tmp_path: Path) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
        busy.bind(("127.0.0.1", 0))
        port = busy.getsockname()[1]
        fleet = _fleet(tmp_path, [{"id": 1, "marker": 1, "port": port, "key": GOOD_KEY}])
        assert f"cannot bind 127.0.0.1:{port}" in _fails_with_one_line("--keys", str(fleet))
        fleet = _fleet(tmp_path, [{"id": 1, "marker": 1, "port": 0, "key": GOOD_KEY}])
        error = _fails_with_one_line("--keys", str(fleet), "--control-port", str(port))
        assert f"--control-port {port}: cannot bind" in error


@pytest.mark.parametrize(
    "option",
    [
        ["--cars", "abc"],
        ["--cars", "2"],
        ["--watchdog-ms", "0"],
        ["--status-ms", "-5"],
        ["--cell-time-ms", "nan"],
        ["--control-port", "70000"],
        ["--edge", "127.0.0.1"],
    ],
    ids=" ".join,
)
def test_cli_bad_option_is_one_line_exit_2(tmp_path: Path, option: list[str]) -> None:
    fleet = _fleet(tmp_path, [{"id": 1, "marker": 1, "port": 0, "key": GOOD_KEY}])
    _fails_with_one_line("--keys", str(fleet), *option)


def test_cli_defaults_are_the_spec_timings() -> None:
    args = _parser().parse_args(["--keys", "fleet.toml"])
    assert (args.watchdog_ms, args.cell_time_ms, args.status_ms, args.join_ms) == (
        300,
        200,
        100,
        250,
    )


async def test_a_guided_command_crosses_the_serial_line_and_a_bad_pose_is_dropped_and_counted(
    edge: EdgeClient, make_car
) -> None:
    """A command's target and measured pose reach the motor controller over the pty (the car
    drives from the measured pose to the target); one whose pose field is out of range is
    malformed (checked before its tag, spec section 4; the vectors show one signed with the
    session key): counted, unanswered, never executed."""
    car = await make_car()
    await edge.join(1)
    cell = 2.8 / 9
    target = ((4 + 0.5) * cell, (3 + 0.5) * cell, 0.0)  # the cell above the start (4, 4)
    seen = ((4 + 0.5) * cell + 0.02, (4 + 0.5) * cell, 0.0)  # 2 cm right of (4, 4)'s centre
    frame = edge.proto.encode_command(
        1, ep.Action.UP, 500_000_000, ep.Guidance(target, seen, time.monotonic_ns())
    )
    edge.send(1, frame)
    await edge.expect(ep.StatusReport, lambda s: s.done_seq == ep.decode(frame).seq)
    drive = car.controller.drive
    assert drive.corrections == 1 and drive.pose == (3, 4)
    assert drive.belief == pytest.approx(target, abs=1e-3)
    executed = car.counters()["executed"]
    later = bytearray(edge.proto.encode_command(1, ep.Action.UP, 500_000_000))
    later[23] = ep.GUIDE_POSE  # the pose given, its heading (bytes 34-35) beyond pi
    later[34:36] = (3200).to_bytes(2, "big")
    edge.send(1, bytes(later))
    assert await edge.quiet(ep.Acked, 0.1) == []
    counters = car.counters()
    assert counters["rejected"]["malformed"] == 1 and counters["executed"] == executed


async def test_an_estop_mid_move_leaves_the_car_where_it_stopped_until_it_is_released(
    edge: EdgeClient, make_car
) -> None:
    """Through the whole car (UDP, the ESP8266's checks, the pty, the controller) in a world
    with continuous poses: an ESTOP engaged half-way through a move leaves the car across the
    border; commands while the stop is latched are refused and nothing moves it; after the
    release, its next command drives it from where it stands to its target."""
    geometry = ArenaGeometry()
    world = HilWorld(geometry, {1: 41}, LEVELS["low"], seed=2)
    world.place(np.zeros((9, 9), np.uint8), {1: (4, 4)})
    await make_car(world=world, cell_time_s=0.3, accel_share=0.25)
    await edge.join(1)
    target = (*geometry.cell_centre(4, 5), 0.0)
    ahead = ep.Guidance(target, tuple(world.pose[1]), time.monotonic_ns())
    edge.send(1, edge.proto.encode_command(1, ep.Action.RIGHT, 500_000_000, ahead))
    await edge.expect(ep.StatusReport, lambda st: st.moving)
    await asyncio.sleep(0.14)
    edge.send(1, edge.proto.encode_estop(1, True))
    await edge.expect(ep.StatusReport, lambda st: st.faults & ep.Fault.ESTOP and not st.moving)
    stopped = world.pose[1]
    border = geometry.cell_centre(4, 4)[0] + geometry.cell_m / 2
    assert abs(stopped.x - border) < 0.3 * geometry.cell_m and 1 not in world.motion
    for action in (ep.Action.RIGHT, ep.Action.WAIT):  # refused while latched
        refused = await edge.command(1, action)
        assert refused.result is ep.AckResult.ESTOPPED
    await asyncio.sleep(0.4)
    assert world.pose[1] == stopped and world.counts["moves"] == 0
    edge.send(1, edge.proto.encode_estop(1, False, 500_000_000))
    await edge.expect(ep.Acked, lambda a: a.result is ep.AckResult.ACCEPTED)
    seen = ep.Guidance(target, tuple(stopped), time.monotonic_ns())
    frame = edge.proto.encode_command(1, ep.Action.WAIT, 500_000_000, seen)
    edge.send(1, frame)
    await edge.expect(ep.StatusReport, lambda st: st.done_seq == ep.decode(frame).seq)
    assert math.dist(world.pose[1][:2], target[:2]) < 0.02
