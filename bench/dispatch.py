"""Dispatch benchmark: the edge's ``CarLink`` over real UDP to a ``udan-firmware-mock`` process.

Prints one JSON object. Five mock cars run in their own process (cell time 20 ms, so they really
move between steps); this process runs the link on uvloop when it is installed. A step is
dispatched every 25 ms (the camera's 40 FPS) with a random action per car, 400 steps without
faults and 400 with 10 % loss on every car in each direction, after a warm-up that lets clock
sync settle. Per run: decision -> every ACK received (steps where all cars acked), decision ->
car received (per command, the car's receive time in the edge clock), the share of commands
accepted within the 10 ms deadline, retransmissions, misses and late sends (must be 0). The
car-receive times are estimates: the clock offset is known to half the best sync round trip
(``sync_rtt_ms_max``). ``cars_expired`` counts resends that reached a car after their deadline and
were refused there, ``cars_duplicates`` resends answered without running the command again.
"""

from __future__ import annotations

import asyncio
import json
import random
import signal
import socket
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from udan.edge.link import CarLink, DispatchReport
from udan.edge.transport import open_transport
from udan.fleetfile import load_fleet

CARS = 5
STEPS = 400
WARMUP_STEPS = 40
PERIOD_NS = 25_000_000
LOSS = 0.1
MOCK = Path(sys.executable).with_name("udan-firmware-mock")


def _percentiles(values_ns: list[int]) -> dict[str, float | None]:
    if not values_ns:
        return {"p50_ms": None, "p99_ms": None, "max_ms": None}
    ms = sorted(v / 1e6 for v in values_ns)
    return {
        "p50_ms": round(ms[len(ms) // 2], 3),
        "p99_ms": round(ms[min(len(ms) - 1, int(0.99 * len(ms)))], 3),
        "max_ms": round(ms[-1], 3),
    }


def _control(port: int, request: dict[str, Any]) -> dict[str, Any]:
    """The mock's control hook; blocking, only called between series (uvloop has no sendto)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.settimeout(2)
        sock.sendto(json.dumps(request).encode(), ("127.0.0.1", port))
        return json.loads(sock.recv(65536))


async def _steps(link: CarLink, steps: int, rng: random.Random) -> list[DispatchReport]:
    """One dispatch every ``PERIOD_NS`` to every ready car, on a fixed schedule."""
    reports = []
    start = time.monotonic_ns()
    for i in range(steps):
        wait_ns = start + i * PERIOD_NS - time.monotonic_ns()
        if wait_ns > 0:
            await asyncio.sleep(wait_ns / 1e9)
        actions = {c: rng.randrange(5) for c in range(1, CARS + 1)}
        reports.append(await link.dispatch(actions, time.monotonic_ns()))
    return reports


def _summary(
    reports: list[DispatchReport], before: dict[str, Any], after: dict[str, Any]
) -> dict[str, Any]:
    commands = [r for rep in reports for r in rep.cars.values()]
    all_acked = [rep.all_acked_ns - rep.decision_ns for rep in reports if rep.all_acked_ns]
    received = [
        r.car_received_ns - rep.decision_ns
        for rep in reports
        for r in rep.cars.values()
        if r.acked and r.car_received_ns is not None
    ]
    on_time = sum(rep.on_time for rep in reports)
    return {
        "steps": len(reports),
        "commands": len(commands),
        "on_time_share": round(on_time / len(commands), 5),
        "steps_all_on_time_share": round(
            sum(rep.on_time == len(rep.cars) for rep in reports) / len(reports), 5
        ),
        "missed": sum(rep.missed for rep in reports),
        "not_ready": sum(rep.not_ready for rep in reports),
        "slow_sends": sum(rep.slow_sends for rep in reports),
        "late_sends": sum(rep.late_sends for rep in reports),
        "retried_commands": sum(rep.retried for rep in reports),
        "retransmits": after["retransmits"] - before["retransmits"],
        "decision_to_all_acked": _percentiles(all_acked),
        "decision_to_car_received": _percentiles(received),
    }


async def bench() -> dict[str, Any]:
    """Start the mock fleet, warm up, run the clean and the lossy series."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fleet.toml"
        path.write_text(
            "".join(
                f'[[car]]\nid = {c}\nmarker = {c}\nkey = "{bytes([c] * 32).hex()}"\n'
                for c in range(1, CARS + 1)
            )
        )
        cars = load_fleet(path)
        transport = open_transport("udp", cars, listen="127.0.0.1:0")
        link = CarLink(cars, transport)
        await link.start()
        edge_port = transport.address[1]  # type: ignore[attr-defined]
        proc = await asyncio.create_subprocess_exec(
            str(MOCK),
            *("--cars", str(CARS), "--base-port", "0", "--keys", str(path), "--seed", "1"),
            *("--edge", f"127.0.0.1:{edge_port}", "--control-port", "0"),
            *("--cell-time-ms", "20"),
            stdout=asyncio.subprocess.PIPE,
        )
        try:
            assert proc.stdout is not None
            ready = json.loads(await asyncio.wait_for(proc.stdout.readline(), 30))
            async with asyncio.timeout(10):
                while len(link.ready_cars()) < CARS:
                    link.changed.clear()
                    await link.changed.wait()
            rng = random.Random(1)
            await _steps(link, WARMUP_STEPS, rng)
            before = link.counters()
            clean = await _steps(link, STEPS, rng)
            middle = link.counters()
            for c in range(1, CARS + 1):
                lossy_car = {"op": "faults", "car": c, "set": {"loss": LOSS}}
                _control(ready["control_port"], lossy_car)
            lossy = await _steps(link, STEPS, rng)
            after = link.counters()
            sync_rtt = [link.state(c).sync_rtt_ns for c in range(1, CARS + 1)]
            link.estop_all()
            await asyncio.sleep(0.02)
            mock = (_control(ready["control_port"], {"op": "counters"}))["cars"]
        finally:
            if proc.returncode is None:
                proc.send_signal(signal.SIGTERM)
                await asyncio.wait_for(proc.wait(), 5)
            await link.close()
    return {
        "bench": "dispatch",
        "event_loop": type(asyncio.get_running_loop()).__module__.split(".")[0],
        "cars": CARS,
        "period_ms": PERIOD_NS / 1e6,
        "validity_ms": link.validity_ns / 1e6,
        "no_faults": _summary(clean, before, middle),
        f"loss_{round(LOSS * 100)}pct": _summary(lossy, middle, after),
        "sync_rtt_ms_max": round(max(r or 0 for r in sync_rtt) / 1e6, 3),
        "cars_expired": sum(m["rejected"]["expired"] for m in mock.values()),
        "cars_duplicates": sum(m["duplicates"] for m in mock.values()),
        "target_on_time_share_no_faults": 1.0,
    }


def main() -> None:
    """Run on uvloop when it is installed (the edge runtime does), print the JSON object."""
    try:
        import uvloop
    except ImportError:
        result = asyncio.run(bench())
    else:
        result = uvloop.run(bench())
    print(json.dumps(result))


if __name__ == "__main__":
    main()
