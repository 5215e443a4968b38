"""``udan-firmware-mock``: run a fleet of mock WiFi cars as one process.

    udan-firmware-mock --cars 5 --base-port 9100 --keys fleet.toml --edge 127.0.0.1:9000

When every socket is bound it prints one JSON line on stdout (``{"ready": true, "cars": [...]}``)
with the real ports, so a harness can start it with ``--base-port 0`` and read where the cars
are. ``--control-port`` opens a loopback-only JSON-over-UDP hook for tests and the HIL harness
(counters, state, faults, reboot); it is part of the mock, not of the car protocol. SIGTERM or
SIGINT: every joined car sends LEAVE, then the process exits 0. A bad fleet file or option: one
line on stderr, exit code 2.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import signal
import socket
import sys
from collections.abc import Sequence
from typing import Any

from udan.envs.errors import OneLineParser
from udan.firmware_mock.firmware import DEFAULT_TIMING, CarTiming
from udan.firmware_mock.fleet import load_fleet
from udan.firmware_mock.udp import MockCar
from udan.fleetfile import FleetFileError

PROG = "udan-firmware-mock"


class UsageError(ValueError):
    """A command-line value that cannot be used."""


def _positive_ms(text: str) -> float:
    """A time in milliseconds > 0: a zero period would spin the event loop."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a time > 0 ms, got {text!r}")
    return value


def _port(text: str) -> int:
    """A UDP port number, 0 (any free port) to 65535."""
    if not text.isdigit() or int(text) > 65535:
        raise argparse.ArgumentTypeError(f"must be a port 0-65535, got {text!r}")
    return int(text)


async def _edge_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` resolved once to an IPv4 address (a name left in would be looked up, and
    block the loop, at every datagram the cars send)."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise UsageError(f"--edge must be HOST:PORT, got {text!r}")
    loop = asyncio.get_running_loop()
    try:
        infos = await loop.getaddrinfo(
            host, int(port), family=socket.AF_INET, type=socket.SOCK_DGRAM
        )
    except OSError as err:
        raise UsageError(f"--edge {text}: cannot resolve {host!r}: {err.strerror}") from None
    addr = infos[0][4]
    return str(addr[0]), int(addr[1])


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog=PROG, description=__doc__.splitlines()[0])
    p.add_argument("--keys", required=True, help="fleet.toml with one [[car]] table per car")
    p.add_argument("--cars", type=int, help="run the first N cars of the fleet (default: all)")
    p.add_argument("--base-port", type=int, help="port = base + car id when a car has none; 0: any")
    p.add_argument("--edge", help="HOST:PORT the cars announce themselves (JOIN) to")
    defaults = DEFAULT_TIMING
    for flag, default, what in (
        ("--cell-time-ms", defaults.cell_time_s, "time to drive one cell"),
        ("--watchdog-ms", defaults.watchdog_s, "stop the motors after this long without commands"),
        ("--status-ms", defaults.status_period_s, "heartbeat period"),
        ("--join-ms", defaults.join_period_s, "JOIN repeat period until joined"),
    ):
        p.add_argument(flag, type=_positive_ms, default=default * 1000, help=what)
    p.add_argument("--control-port", type=_port, help="loopback JSON control port (0: any)")
    p.add_argument(
        "--seed", type=int, help="seed for the fault draws (session nonces are always fresh)"
    )
    return p


class _Control(asyncio.DatagramProtocol):
    """Loopback JSON requests: counters, state, faults, reboot."""

    def __init__(self, cars: dict[int, MockCar]) -> None:
        self.cars = cars
        self.transport: Any = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport

    def _answer(self, request: Any) -> dict[str, Any]:
        if not isinstance(request, dict):
            raise UsageError("request must be a JSON object")
        op = request.get("op")
        if op == "counters":
            return {"cars": {str(c): car.counters() for c, car in self.cars.items()}}
        if op == "state":
            return {"cars": {str(c): car.state() for c, car in self.cars.items()}}
        car_id = request.get("car")
        car = self.cars.get(car_id) if isinstance(car_id, int) else None
        if car is None:
            raise UsageError(f"unknown car {request.get('car')!r}")
        if op == "faults":
            car.firmware.apply_faults(request.get("set", {}))
            return {"faults": vars(car.faults).copy()}
        if op == "reboot":
            car.firmware.reboot()
            return {"session": car.firmware.core.session}
        raise UsageError(f"unknown op {op!r}")

    def datagram_received(self, data: bytes, addr: Any) -> None:
        try:
            reply = {"ok": True, **self._answer(json.loads(data))}
        except (ValueError, TypeError, AttributeError) as err:
            reply = {"ok": False, "error": str(err)}
        self.transport.sendto(json.dumps(reply).encode(), addr)


async def _run(args: argparse.Namespace) -> None:
    specs = load_fleet(args.keys, args.base_port)
    if args.cars is not None:
        if not 0 < args.cars <= len(specs):
            raise UsageError(f"--cars {args.cars}: the fleet file has {len(specs)} car(s)")
        specs = specs[: args.cars]
    edge = await _edge_address(args.edge) if args.edge else None
    timing = CarTiming(
        cell_time_s=args.cell_time_ms / 1000,
        watchdog_s=args.watchdog_ms / 1000,
        status_period_s=args.status_ms / 1000,
        join_period_s=args.join_ms / 1000,
    )
    cars: dict[int, MockCar] = {}
    for i, spec in enumerate(specs):
        seed = None if args.seed is None else args.seed + i
        cars[spec.car_id] = MockCar(spec, edge=edge, timing=timing, seed=seed)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    control = None
    try:
        for car in cars.values():
            try:
                await car.start()
            except OSError as err:
                raise UsageError(
                    f"car {car.spec.car_id}: cannot bind {car.spec.host}:"
                    f"{car.spec.port}: {err.strerror}"
                ) from None
        if args.control_port is not None:
            try:
                control, _ = await loop.create_datagram_endpoint(
                    lambda: _Control(cars), local_addr=("127.0.0.1", args.control_port)
                )
            except OSError as err:
                raise UsageError(
                    f"--control-port {args.control_port}: cannot bind: {err.strerror}"
                ) from None
        ready = {
            "ready": True,
            "cars": [
                {"id": c, "marker": car.spec.marker, "address": list(car.address or ())}
                for c, car in cars.items()
            ],
            "control_port": control.get_extra_info("sockname")[1] if control else None,
        }
        print(json.dumps(ready), flush=True)
        await stop.wait()
    finally:
        for car in cars.values():
            if car.address is not None:
                car.close()
        if control is not None:
            control.close()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (2 on a bad fleet file or option)."""
    args = _parser().parse_args(argv)
    try:
        asyncio.run(_run(args))
    except (FleetFileError, UsageError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
