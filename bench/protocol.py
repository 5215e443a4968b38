"""Protocol benchmark: a fuzz round through both cores, and one mock car process's ack latency.

Prints one JSON object. Fuzz: 1,000,000 inputs (random bytes and mutations of genuine frames of
every type, both directions), each fed to the car's core (``udan.firmware_mock.core``) and to the
edge's core (``udan.edge.protocol``); an exception escaping is a crash, an input that is not a
genuine frame byte for byte but is accepted is a forgery. Latency: ``udan-firmware-mock`` with
one car as a separate process, the edge side in this process on a plain UDP socket, round trip from
sending a command to receiving its ack, over 2000 commands after a warm-up.
"""

from __future__ import annotations

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
from pathlib import Path

from udan.edge import protocol as ep
from udan.firmware_mock.core import CarCore, Telemetry

FUZZ_INPUTS = 1_000_000
LATENCY_COMMANDS = 2000
WARMUP_COMMANDS = 200
KEY = bytes(range(200, 232))


def genuine_frames() -> tuple[CarCore, ep.EdgeProtocol, list[bytes], int]:
    """A joined, synchronised car/edge pair, genuine frames of every type, and the car's clock.

    Shared with tests/test_protocol_fuzz.py, so the hypothesis tests and this fuzz round mutate
    the same frames. The car has handled the time request and the second command; the other
    edge frames are still fresh to it. Every type is there, the handshake's (JOIN, ACCEPT,
    HELLO) included.
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
    return proto.receive(sock.recv(2048))


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


def main() -> None:
    """Run both parts and print the JSON object."""
    n = int(os.environ.get("UDAN_BENCH_FUZZ_INPUTS", FUZZ_INPUTS))
    result = {
        "bench": "protocol",
        "fuzz": fuzz(n),
        "ack_latency_loopback": ack_latency(LATENCY_COMMANDS, WARMUP_COMMANDS),
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
