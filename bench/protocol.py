"""Protocol benchmark: fuzz, ack latency, recovery after an edge restart, a JOIN replay attack.

Prints one JSON object. Fuzz: 1,000,000 inputs (random bytes and mutations of genuine frames of
every type, both directions), each fed to the car's core (``udan.firmware_mock.core``) and to the
edge's core (``udan.edge.protocol``); an exception escaping is a crash, an input that is not a
genuine frame byte for byte but is accepted is a forgery. Latency: ``udan-firmware-mock`` with
one car as a separate process, the edge side in this process on a plain UDP socket, round trip from
sending a command to receiving its ack, over 2000 commands after a warm-up.

Restart: two cars in a ``udan-firmware-mock`` process and the edge's ``CarLink`` on real UDP in
this one. The previous edge drives them, then leaves each car holding a sequence number of 10,
10^3, 10^6 or 2^32 - 10 (one frame at that number in its session, signed with the session key the
nonces of its ACCEPT give), and closes; a new ``CarLink`` binds the same port. Recovery is the time
from its start to the first dispatch every car accepts on time; target 1 s, whatever came before.
JOIN replay: every JOIN recorded so far is sent to a fresh edge before the cars are heard from, and
to a running one; nobody may be cut off (recovery within 1 s, then every dispatch on time).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import random
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path

from udan.edge import protocol as ep
from udan.edge.link import CarLink
from udan.edge.transport import Transport, free_udp_port, open_transport
from udan.firmware_mock.core import CarCore, Telemetry
from udan.fleetfile import CarEntry, load_fleet

FUZZ_INPUTS = 1_000_000
LATENCY_COMMANDS = 2000
WARMUP_COMMANDS = 200
KEY = bytes(range(200, 232))
PREVIOUS_RUNS = (10, 10**3, 10**6, 2**32 - 10)
RECOVERY_TARGET_S = 1.0


def genuine_frames() -> tuple[CarCore, ep.EdgeProtocol, list[bytes], int]:
    """A joined, synchronised car/edge pair, genuine frames of every type, and the car's clock.

    Shared with tests/test_protocol_fuzz.py, so the hypothesis tests and this fuzz round mutate
    the same frames. The car has handled the time request and the second command; the other
    edge frames are still fresh to it. Every type is there, the handshake's (JOIN, ACCEPT,
    HELLO) included, and commands with and without their target, pose and start delay.
    """
    car_now = 80_000
    car = CarCore(1, KEY, marker=3)
    edge = ep.EdgeProtocol({1: KEY}, clock=lambda: 5_000_000_000)
    pool = [car.boot(car_now)]
    edge.receive(pool[0])
    pool += [frame for _, frame in edge.datagrams_to_send()]  # the ACCEPT
    car.handle(pool[-1], car_now)
    pool.append(car.status(car_now, Telemetry()))
    edge.receive(pool[-1])
    req = edge.encode_time_request(1)
    pool += [req, *car.handle(req, car_now).replies]
    edge.receive(pool[-1])
    for action in range(6):
        pool.append(edge.encode_command(1, action, validity_ns=900_000_000))
    pool += [edge.encode_estop(1, True), edge.encode_estop(1, False)]
    seen = ep.Guidance((1.4, 1.089, 0.0), (1.412, 1.085, 0.035), 4_990_000_000, 0.65)
    for guidance in (seen, ep.Guidance((0.156, 2.644, -3.1))):  # target, pose, delay; target
        pool.append(edge.encode_command(1, 3, 900_000_000, guidance))
    pool.append(car.status(car_now, Telemetry(row=1, col=2, moving=True, done_seq=3)))
    pool.append(car.leave(car_now, 1))
    pool += list(car.handle(pool[6], car_now).replies)
    pool.append(ep.encode(ep.MsgType.HELLO, 1, 0, 0, 0, KEY, {"reason": 0}))
    return car, edge, pool, car_now


def _mutate(rng: random.Random, pool: list[bytes]) -> bytes:
    kind = rng.randrange(8)
    if kind == 0:
        return rng.randbytes(rng.randrange(0, 80))
    f = bytearray(rng.choice(pool))
    if kind == 1:
        for _ in range(rng.randrange(1, 4)):
            f[rng.randrange(len(f))] ^= 1 << rng.randrange(8)
    elif kind == 2:
        f[rng.randrange(len(f))] = rng.randrange(256)
    elif kind == 3:
        del f[rng.randrange(len(f)) :]
    elif kind == 4:
        f += rng.randbytes(rng.randrange(1, 9))
    elif kind == 5:
        at = rng.randrange(len(f))
        f[at : at + 6] = rng.randbytes(6)
    elif kind == 6:
        f[-6:] = rng.randbytes(6)  # a guessed tag
    else:
        other = rng.choice(pool)
        cut = rng.randrange(min(len(f), len(other)))
        f = f[:cut] + bytearray(other[cut:])
    return bytes(f)


def fuzz(n: int, seed: int = 1) -> dict[str, object]:
    """Feed ``n`` non-genuine inputs to both cores; count crashes and acceptances."""
    car, edge, pool, car_now = genuine_frames()
    genuine = frozenset(pool)
    rng = random.Random(seed)
    crashes = forgeries = inputs = 0
    first_crash = None
    verdicts: Counter[str] = Counter()
    start = time.perf_counter()
    while inputs < n:
        data = _mutate(rng, pool)
        if data in genuine:
            continue
        inputs += 1
        try:
            out = car.handle(data, car_now)
            verdicts[out.verdict] += 1
            if out.verdict in ("accepted", "duplicate", "joined") or out.motor or out.halt:
                forgeries += 1
        except Exception as err:  # counting them is the point
            crashes += 1
            first_crash = first_crash or repr(err)
        try:
            if not isinstance(edge.receive(data), ep.Rejected):
                forgeries += 1
        except Exception as err:
            crashes += 1
            first_crash = first_crash or repr(err)
    seconds = time.perf_counter() - start
    return {
        "inputs": inputs,
        "crashes": crashes,
        "first_crash": first_crash,
        "accepted_forgeries": forgeries,
        "car_verdicts": dict(verdicts.most_common()),
        "seconds": round(seconds, 2),
        "parse_rate_per_s": round(inputs / seconds),
    }


def _recv_event(sock: socket.socket, proto: ep.EdgeProtocol) -> ep.Event:
    data, source = sock.recvfrom(2048)
    event = proto.receive(data)
    for _car, frame in proto.datagrams_to_send():  # ACCEPT: answers go back to the source
        sock.sendto(frame, source)
    return event


def ack_latency(commands: int, warmup: int) -> dict[str, object]:
    """Round trip command -> ack against one ``udan-firmware-mock`` car in its own process."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    proto = ep.EdgeProtocol({1: KEY})
    with tempfile.TemporaryDirectory() as tmp:
        fleet = Path(tmp) / "fleet.toml"
        fleet.write_text(f'[[car]]\nid = 1\nmarker = 1\nport = 0\nkey = "{KEY.hex()}"\n')
        edge_addr = f"127.0.0.1:{sock.getsockname()[1]}"
        cmd = [
            sys.executable,
            "-m",
            "udan.firmware_mock.cli",
            "--keys",
            str(fleet),
            "--edge",
            edge_addr,
        ]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
        try:
            assert proc.stdout is not None
            car_addr = tuple(json.loads(proc.stdout.readline())["cars"][0]["address"])
            while not isinstance(_recv_event(sock, proto), ep.Joined):
                pass
            sock.sendto(proto.encode_time_request(1), car_addr)
            while not isinstance(_recv_event(sock, proto), ep.TimeSynced):
                pass
            rtts, lost = [], 0
            for i in range(commands + warmup):
                frame = proto.encode_command(1, i % 5, validity_ns=50_000_000)
                seq = int.from_bytes(frame[10:14], "big")
                sent = time.perf_counter_ns()
                sock.sendto(frame, car_addr)
                try:
                    while True:
                        event = _recv_event(sock, proto)
                        if isinstance(event, ep.Acked) and event.ref_seq == seq:
                            break
                except TimeoutError:
                    lost += 1
                    continue
                if i >= warmup:
                    rtts.append((time.perf_counter_ns() - sent) / 1e6)
        finally:
            proc.terminate()
            proc.wait(5)
            if proc.stdout is not None:
                proc.stdout.close()
            sock.close()
    rtts.sort()
    p99 = rtts[min(len(rtts) - 1, int(0.99 * len(rtts)))]
    return {
        "commands": len(rtts),
        "lost": lost,
        "median_ms": round(statistics.median(rtts), 4),
        "p99_ms": round(p99, 4),
        "max_ms": round(rtts[-1], 4),
        "target_p99_ms": 1.0,
        "target_met": p99 <= 1.0,
    }


def tap(transport: Transport) -> tuple[list[tuple[int, bytes]], list[bytes]]:
    """What an eavesdropper on ``transport`` keeps: frames sent (car id, frame) and received."""
    sent: list[tuple[int, bytes]] = []
    received: list[bytes] = []
    for name in ("send", "send_back"):
        original = getattr(transport, name)

        def recording(car_id: int, frame: bytes, original: Callable = original) -> None:
            sent.append((car_id, frame))
            original(car_id, frame)

        setattr(transport, name, recording)
    opening = transport.open

    async def open_recording(on_frame: Callable[[bytes], None]) -> None:
        def heard(frame: bytes) -> None:
            received.append(frame)
            on_frame(frame)

        await opening(heard)

    transport.open = open_recording  # type: ignore[method-assign]
    return sent, received


def frame_at_seq(entry: CarEntry, sent: list[tuple[int, bytes]], seq: int) -> bytes:
    """A TIME_REQUEST at ``seq`` in the car's session with the edge that sent ``sent``.

    The session key follows from the car's key and the two nonces of the edge's last ACCEPT to
    the car (both in the clear); the car booted seconds ago, so timestamp 0 is in its window.
    """
    accept = next(
        ep.decode(f) for c, f in reversed(sent) if c == entry.car_id and f[1] == ep.MsgType.ACCEPT
    )
    session, key = ep.derive_session(
        entry.key, bytes(accept.fields["car_nonce"]), bytes(accept.fields["edge_nonce"])
    )
    return ep.encode(ep.MsgType.TIME_REQUEST, entry.car_id, session, seq, 0, key, {"t1_ns": seq})


async def under_command(link: CarLink, cars: set[int], timeout_s: float = 10.0) -> None:
    """Until one dispatch (every car: wait) is accepted on time by every car."""
    async with asyncio.timeout(timeout_s):
        while True:
            if link.ready_cars() == cars and all(link.move_finished(c) for c in cars):
                report = await link.dispatch(dict.fromkeys(cars, 4), time.monotonic_ns())
                if report.on_time == len(cars):
                    return
            link.changed.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.05):
                    await link.changed.wait()


def fleet_file(folder: Path, car_ids: Sequence[int]) -> Path:
    """A fleet.toml in ``folder``: car ``c`` has marker ``c``, any free port, key ``c`` x 32."""
    path = folder / "fleet.toml"
    path.write_text(
        "".join(
            f'[[car]]\nid = {c}\nmarker = {c}\nport = 0\nkey = "{(bytes([c]) * 32).hex()}"\n'
            for c in car_ids
        )
    )
    return path


class _MockFleet:
    """Two mock cars in their own ``udan-firmware-mock`` process, announcing to ``listen``."""

    def __init__(self, folder: Path) -> None:
        path = fleet_file(folder, (1, 2))
        self.entries = load_fleet(path)
        self.listen = f"127.0.0.1:{free_udp_port()}"
        cmd = [sys.executable, "-m", "udan.firmware_mock.cli", "--keys", str(path)]
        cmd += ["--edge", self.listen, "--cell-time-ms", "20"]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        json.loads(self.proc.stdout.readline())

    def transport(self) -> Transport:
        return open_transport("udp", self.entries, listen=self.listen)

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


async def _restart(cars: _MockFleet, previous_frames: int, joins: list[bytes]) -> float:
    """One edge drives the cars, leaves them at ``previous_frames``, a new one takes over."""
    ids = {e.car_id for e in cars.entries}
    transport = cars.transport()
    sent, received = tap(transport)
    previous = CarLink(cars.entries, transport)
    await previous.start()
    try:
        await under_command(previous, ids)
        for entry in cars.entries:
            transport.send(entry.car_id, frame_at_seq(entry, sent, previous_frames))
        await asyncio.sleep(0.05)
    finally:
        await previous.close()
    joins += [f for f in received if f[:2] == bytes([ep.PROTOCOL_VERSION, ep.MsgType.JOIN])]
    await asyncio.sleep(0.01)
    started = time.monotonic()
    fresh = CarLink(cars.entries, cars.transport())
    await fresh.start()
    try:
        await under_command(fresh, ids)
        return time.monotonic() - started
    finally:
        await fresh.close()
        await asyncio.sleep(0.01)  # the port is free again once the loop has run


async def _join_replay(cars: _MockFleet, joins: list[bytes]) -> dict[str, object]:
    """Recorded JOINs to a fresh edge first, then to the running one: is anyone cut off?"""
    ids = {e.car_id for e in cars.entries}
    link = CarLink(cars.entries, cars.transport())
    await link.start()
    started = time.monotonic()
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as attacker:
            host, port = cars.listen.rsplit(":", 1)
            for join in joins:
                attacker.sendto(join, (host, int(port)))
            await under_command(link, ids)
            recovery = time.monotonic() - started
            on_time = 0
            for _ in range(20):
                for join in joins:
                    attacker.sendto(join, (host, int(port)))
                await asyncio.sleep(0.03)
                try:
                    await under_command(link, ids, timeout_s=1.0)
                except TimeoutError:
                    continue
                on_time += 1
    finally:
        await link.close()
    return {
        "joins_replayed": len(joins) * 21,
        "fresh_edge_recovery_s": round(recovery, 3),
        "steps_on_time_under_replay": f"{on_time}/20",
        "target_met": recovery <= RECOVERY_TARGET_S and on_time == 20,
    }


def restart_recovery() -> dict[str, object]:
    """Recovery after an edge restart per previous run length, and the JOIN replay attack."""

    async def run() -> dict[str, object]:
        with tempfile.TemporaryDirectory() as tmp:
            cars = _MockFleet(Path(tmp))
            joins: list[bytes] = []
            try:
                recovery = {str(n): round(await _restart(cars, n, joins), 3) for n in PREVIOUS_RUNS}
                replay = await _join_replay(cars, joins)
            finally:
                cars.close()
        return {
            "recovery_s_by_previous_frames": recovery,
            "target_s": RECOVERY_TARGET_S,
            "target_met": max(recovery.values()) <= RECOVERY_TARGET_S,
            "join_replay": replay,
        }

    return asyncio.run(run())


def main() -> None:
    """Run every part and print the JSON object."""
    n = int(os.environ.get("UDAN_BENCH_FUZZ_INPUTS", FUZZ_INPUTS))
    result = {
        "bench": "protocol",
        "fuzz": fuzz(n),
        "ack_latency_loopback": ack_latency(LATENCY_COMMANDS, WARMUP_COMMANDS),
        "edge_restart": restart_recovery(),
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
