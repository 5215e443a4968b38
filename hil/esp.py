"""The fleet's ESP8266 mocks in a process of their own, beside the world's process.

A real car's radio is a chip of its own: it receives, checks and acknowledges a command while
another car's motors start. In one event loop with the motor controllers and the world, a car's
datagram waited behind every other car's move start (docs/timing.md, "The slowest steps"). So
the world process keeps the motor controllers (``MotorEnd``, on the master ends of the cars'
pty serial lines) and this process runs the ``EspCar`` of every car, which opens its serial
line by name, as the ESP8266 opens its UART. The world talks to it over a pipe for what only
the radio knows (faults, reboots, counters, state); the car protocol never crosses the pipe.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
from dataclasses import asdict
from multiprocessing.connection import Connection
from typing import Any

from udan.edge.pauses import freeze_garbage, run_realtime, scheduler
from udan.firmware_mock.faults import Faults
from udan.firmware_mock.firmware import CarTiming
from udan.firmware_mock.fleet import CarSpec
from udan.firmware_mock.udp import EspCar
from udan.hil.children import Child

ANSWER_TIMEOUT_S = 10.0


class EspProcess:
    """The ESP8266s of ``specs`` in a child process, each on its motor controller's ``tty_paths``
    entry; ``addresses`` are their bound UDP addresses by car id. ``realtime``: the child runs
    SCHED_RR at the edge loop's priority, as the world process does."""

    def __init__(
        self,
        specs: list[CarSpec],
        tty_paths: dict[int, str],
        *,
        edge: tuple[str, int],
        timing: CarTiming,
        seed: int,
        realtime: bool,
    ) -> None:
        config = {
            "cars": [(spec, tty_paths[spec.car_id], seed + i) for i, spec in enumerate(specs)],
            "edge": edge,
            "timing": asdict(timing),
            "realtime": realtime,
        }
        self._child = Child(
            _esp_main, config, name="esp8266-mocks", what="the cars' ESP8266 process"
        )
        self._conn = self._child.conn
        self.addresses: dict[int, tuple[str, int]] = self._child.ready
        self._lock = asyncio.Lock()
        self._asked = 0

    async def ask(self, kind: str, car: int | None = None, value: Any = None) -> Any:
        """One request to the ESP8266s; ``ValueError`` with their refusal, or if they do not
        answer (an answer that comes after its time is dropped when the next one is read)."""
        async with self._lock:
            self._asked += 1
            fd = self._conn.fileno()
            try:
                self._conn.send((self._asked, kind, car, value))
                async with asyncio.timeout(ANSWER_TIMEOUT_S):
                    while True:
                        await _readable(fd)
                        number, status, answer = self._conn.recv()
                        if number == self._asked:
                            break
            except TimeoutError:
                raise ValueError(f"the cars' ESP8266 process did not answer {kind!r}") from None
            except (EOFError, OSError):
                raise ValueError("the cars' ESP8266 process has ended") from None
        if status != "ok":
            raise ValueError(answer)
        return answer

    def stop(self) -> dict[str, Any]:
        """Power the ESP8266s off (each says LEAVE and stops its motors); their final counters
        by car id and the process's scheduler (empty if it had already gone)."""
        return self._child.stop((0, "stop", None, None)) or {}


async def _readable(fd: int) -> None:
    """Until ``fd`` has something to read."""
    loop = asyncio.get_running_loop()
    ready: asyncio.Future[None] = loop.create_future()
    loop.add_reader(fd, lambda: ready.done() or ready.set_result(None))
    try:
        await ready
    finally:
        loop.remove_reader(fd)


def _esp_main(conn: Connection, config: dict[str, Any]) -> None:
    """The ESP8266 process: serve the cars until told to stop (or the world is gone)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the world, which stops us
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # so does SIGTERM: the world says LEAVE first
    if config["realtime"]:
        try:
            run_realtime()
        except PermissionError:
            conn.send(("error", "--realtime: not permitted (needs CAP_SYS_NICE)"))
            return
    freeze_garbage()  # real cars have no garbage collector to pause them
    asyncio.run(_serve(conn, config))


async def _serve(conn: Connection, config: dict[str, Any]) -> None:
    timing = CarTiming(**config["timing"])
    cars: dict[int, EspCar] = {}
    try:
        for spec, tty_path, seed in config["cars"]:
            car = EspCar(
                spec, tty_path, Faults.from_mapping(spec.faults), edge=config["edge"],
                timing=timing, seed=seed,
            )  # fmt: skip
            await car.start()
            cars[spec.car_id] = car
    except OSError as err:
        for car in cars.values():
            car.close()
        conn.send(("error", err.strerror or str(err)))
        return
    conn.send(("ready", {c: car.address for c, car in cars.items()}))
    loop = asyncio.get_running_loop()
    stopped = asyncio.Event()

    def answer(kind: str, car_id: int | None, value: Any) -> Any:
        if kind == "counters":
            return {c: car.counters() for c, car in cars.items()}
        if kind == "state":
            return {c: car.state() for c, car in cars.items()}
        car = cars[car_id]  # type: ignore[index]
        if kind == "faults":
            car.firmware.apply_faults(value)
            return None
        if kind == "reboot":
            car.firmware.reboot()
            return None
        raise ValueError(f"unknown request {kind!r}")

    def readable() -> None:
        try:
            number, kind, car_id, value = conn.recv()
        except (EOFError, OSError):  # the world is gone: power off
            number, kind, car_id, value = 0, "stop", None, None
        if kind == "stop":
            stopped.set()
            loop.remove_reader(conn.fileno())
            return
        try:
            reply = (number, "ok", answer(kind, car_id, value))
        except (ValueError, KeyError) as err:
            reply = (number, "error", str(err))
        conn.send(reply)

    loop.add_reader(conn.fileno(), readable)
    await stopped.wait()
    for car in cars.values():
        car.close()
    final = {"cars": {c: car.counters() for c, car in cars.items()}, "scheduler": scheduler()}
    with contextlib.suppress(OSError):
        conn.send(("ok", final))
