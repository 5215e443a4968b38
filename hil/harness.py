"""udan-hil run: the closed loop, every part its own process, and what it measured.

    udan-hil run --task find_water --cars 1-5 --obstacles 0-9 --episodes 20 \\
        [--model policy.onnx] [--faults loss=0.1,jitter=3ms] [--motion-error lab] [--camera gige] \\
        [--record] --report out/hil

starts the HIL world (``python -m udan.hil.world``: simulated arena, mock cars on loopback UDP, the
virtual camera) and ``udan-edge`` through its own command line, lets the edge play the world's
episodes (``--episodes`` per cell of cars x obstacles, or random ones for ``--duration``
seconds), applies the fault spec (:mod:`udan.hil.faults`) through the world's control port, then
stops both and writes the report (:mod:`udan.hil.report`): the edge's spans and deadline counts, the
cars' own counters, the world's collisions, how far the cars strayed from their cells' centres
and how often they were re-centred (``--motion-error``: :mod:`udan.hil.motion`), and the score
table through the full loop beside the pure simulation of the same policy on the same layouts.

It says up front how many episodes it plans (``--episodes`` counts per cell), then shows its
progress as it goes (episodes done of planned, the time left, the share of commands on time so
far; read from the edge's telemetry file): a bar on a terminal, a line every
``PROGRESS_LINE_S`` otherwise. SIGINT or SIGTERM stops the run: the edge first (it stops the cars
and writes its report), then the world, and the report covers the episodes completed (exit code
128 + the signal's number). The world and the edge end with the harness however it ends, even
SIGKILLed: they are started asking the kernel to send them SIGTERM when it dies
(:func:`udan.edge.sidecar.exit_with_parent`).

``--camera gige`` puts a real GigE Vision stream between the world and the edge: the virtual
camera's frames are served by Aravis's fake GigE camera on loopback (``python -m
udan.hil.gige``) and the edge reads ``aravis://127.0.0.1`` in the same mode; the fault spec can
then drop its stream packets, hold frames, or unplug it for a while. ``--record`` has the edge
write its flight recording (``run.mcap``) and the world where every car really was
(``truth.jsonl``); the report then checks every confident sighting of the recording against
it (:mod:`udan.hil.truth`).

Bad input (a report folder that cannot be written, an unknown task, a fault spec that does not
parse, an unknown motion level, a missing model) is one line on stderr and exit code 2, and
every process the harness started is stopped.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from udan.edge import protocol as ep
from udan.edge.episodes import world_request
from udan.edge.sidecar import parent_watch_env
from udan.edge.transport import free_udp_port
from udan.envs.errors import EnvConfigError, OneLineParser, parse_range
from udan.export.runtime import OnnxPolicy
from udan.fleetfile import write_fleet
from udan.hil.faults import FaultPlan, FaultSpecError, parse_faults
from udan.hil.motion import LEVELS, motion_level
from udan.hil.world import Episode, episode_arena
from udan.models import DEFAULT_POLICY, bundled_policy

PROG = "udan-hil"
TASKS = ("find_water",)
MARKER_BASE = 10
POLL_S = 0.2
"""How often the harness looks at its processes and the edge's telemetry."""
PROGRESS_LINE_S = 10.0
"""Without a terminal, a progress line this often."""
FIRST_EPISODE_POLL_S = 0.02
"""How often the fault injector asks the world whether the first episode has started."""


DELAY_BLOCK_S = 0.1
"""``frame_delay`` holds the fake GigE camera's frames in every other block of this long: short
blocks, so that both kinds meet the same load (on a shared machine it changes from second to
second)."""


class HarnessError(RuntimeError):
    """The loop could not be run; one line."""


class Stopped(RuntimeError):
    """A signal stopped the run before it started (nothing to report)."""

    def __init__(self, sig: str) -> None:
        super().__init__(f"stopped by {sig} before the run started")
        self.signal = sig


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog=PROG, description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run the closed loop and write the report")
    run.add_argument("--task", default="find_water", help=f"one of {', '.join(TASKS)}")
    run.add_argument("--cars", default="5", help="cars per episode, a number or a range 1-5")
    run.add_argument("--obstacles", default="0-9", help="obstacles per episode, a range")
    run.add_argument("--episodes", type=int, help="episodes per (cars, obstacles) cell")
    run.add_argument("--duration", type=float, help="instead: random episodes for this long (s)")
    run.add_argument("--episode-steps", type=int, default=50)
    run.add_argument(
        "--model",
        type=Path,
        default=bundled_policy(),
        help=f"exported policy (default: the bundled {DEFAULT_POLICY} policy)",
    )
    run.add_argument("--faults", default="", help="e.g. loss=0.1,jitter=3ms,reboot=car2@10s")
    run.add_argument("--report", type=Path, default=Path("out/hil"), help="report folder")
    run.add_argument("--seed", type=int, default=0)
    run.add_argument("--cell-time-ms", type=float, default=200.0)
    run.add_argument(
        "--motion-error", default="0", metavar="LEVEL",
        help=f"how far the cars' moves stray: {', '.join(LEVELS)} (docs/motion.md)",
    )  # fmt: skip
    run.add_argument("--settle-mm", type=float, default=30.0, help="udan-edge --settle-mm")
    run.add_argument("--settle-deg", type=float, default=5.0, help="udan-edge --settle-deg")
    run.add_argument("--fps", type=float, default=40.0)
    run.add_argument(
        "--video", action="store_true", help="record the camera, annotated by the edge (run.mp4)"
    )
    run.add_argument("--tilt", type=float, default=0.0, help="camera tilt (degrees)")
    run.add_argument("--noise", type=float, default=2.0, help="camera noise sigma")
    run.add_argument("--timeout", type=float, help="give up after this long (s)")
    run.add_argument(
        "--edge-realtime", action="store_true",
        help="udan-edge --realtime, and the mock cars' processes and the virtual camera at "
        "real-time priority too (needs CAP_SYS_NICE)",
    )  # fmt: skip
    run.add_argument(
        "--camera", choices=("virtual", "gige"), default="virtual",
        help="the edge reads the virtual camera's shared memory, or a GigE Vision stream of it",
    )  # fmt: skip
    run.add_argument(
        "--record", action="store_true",
        help="the edge's flight recording (run.mcap) and the world's truth, checked",
    )  # fmt: skip
    run.add_argument(
        "--edge-perception",
        choices=("process", "thread"),
        default="process",
        help="udan-edge --perception: camera and vision in their own process, or in threads",
    )
    return p


def forged_datagrams(count: int, car_ids: Sequence[int], seed: int) -> list[tuple[int, bytes]]:
    """``count`` hostile datagrams, each for the edge (0) or a car: random bytes, well-formed
    frames signed with a wrong key, and truncated frames. None may ever be acted on."""
    rng = random.Random(seed)
    out = []
    for i in range(count):
        car = rng.choice(list(car_ids))
        key = rng.randbytes(32)
        session, seq, ts = rng.getrandbits(31) + 1, rng.getrandbits(20) + 1, rng.getrandbits(40)
        if i % 3 == 0:
            out.append((rng.choice([0, car]), rng.randbytes(rng.randint(1, 80))))
        elif i % 3 == 1:
            fields = {"action": rng.randrange(5), "deadline_us": ts + 5000}
            frame = ep.encode(ep.MsgType.COMMAND, car, session, seq, ts, key, fields)
            out.append((car, frame))
        else:
            fields = {
                "row": 1,
                "col": 1,
                "battery_mv": 8000,
                "faults": 0,
                "state": 0,
                "done_seq": 0,
            }
            frame = ep.encode(ep.MsgType.STATUS, car, session, seq, ts, key, fields)
            out.append((0, frame[: rng.randint(1, len(frame))] if i % 2 else frame))
    return out


def slot_order(record: dict[str, Any]) -> list[int] | None:
    """The cars of an episode record in the order of the policy slots the edge gave them at
    its first step (None: a record without slots)."""
    slots = record.get("slots")
    return [int(c) for c, _ in sorted(slots.items(), key=lambda kv: kv[1])] if slots else None


def simulate(
    task: str,
    model: Path,
    episodes: Sequence[Episode],
    steps: int,
    orders: Sequence[Sequence[int] | None] | None = None,
) -> list[float]:
    """Pure-simulation scores (average agent return) of the same policy on the same layouts.

    ``orders``: per episode, its cars in the edge's slot order (:func:`slot_order`). The policy
    is not indifferent to the order of its slots (ties in forming groups and ordering their
    members are broken by slot), and the edge gives slots in the order the cars joined, not by
    car id: the simulation's agents take the same order, so the two play the same game."""
    policy = OnnxPolicy(model)
    scores = []
    for episode, order in zip(episodes, orders or [None] * len(episodes), strict=True):
        arena = episode_arena(task, episode, steps)
        if order:
            by_id = sorted(order)  # the world places the i-th car by id on agent i's start
            start = arena.pos[0, : len(order)].copy()
            arena.pos[0, : len(order)] = start[[by_id.index(car) for car in order]]
        policy.reset(arena.slots)
        fresh = np.ones(arena.slots, bool)
        for _ in range(steps):
            obs = arena.observe()[0]
            actions = policy.act(obs, arena.present[0], arena.pos[0], fresh)
            fresh[:] = False
            arena.step(actions[None])
        scores.append(float(arena.episode_return[0][arena.present[0]].mean()))
    return scores


class Loop:
    """The processes of one run, started and always stopped."""

    def __init__(self, args: argparse.Namespace, folder: Path, faults: FaultPlan) -> None:
        self.args = args
        self.folder = folder
        self.faults = faults
        self.procs: dict[str, subprocess.Popen] = {}
        self.tmp = Path(tempfile.mkdtemp(prefix="udan-hil-"))
        self.cars = parse_range(args.cars, "cars")
        self.fleet = write_fleet(self.tmp / "fleet.toml", self.cars[1], MARKER_BASE)
        self.camera = f"udan-hil-{os.getpid()}"
        self.edge_port = free_udp_port()
        self.events_done: list[dict[str, Any]] = []
        self.car_addresses: dict[int, tuple[str, int]] = {}

    def _spawn(self, name: str, cmd: list[str]) -> subprocess.Popen:
        """``cmd`` in a session of its own (a Ctrl-C is the harness's to handle), ending with
        the harness however it ends."""
        log = open(self.folder / f"{name}.log", "w", encoding="utf-8")  # noqa: SIM115
        proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=log, text=True, start_new_session=True,
            env=parent_watch_env(),
        )  # fmt: skip
        self.procs[name] = proc
        return proc

    async def start_world(self, stopping: asyncio.Event) -> int | None:
        """Start the world; its control port once it is ready, None if stopped before."""
        a = self.args
        cmd = [
            sys.executable, "-m", "udan.hil.world", "--fleet", str(self.fleet),
            "--edge", f"127.0.0.1:{self.edge_port}", "--camera-name", self.camera,
            "--agents", f"{self.cars[0]}-{self.cars[1]}", "--obstacles", a.obstacles,
            "--seed", str(a.seed), "--cell-time-ms", str(a.cell_time_ms), "--fps", str(a.fps),
            "--tilt", str(a.tilt), "--noise", str(a.noise), "--motion-error", a.motion_error,
        ]  # fmt: skip
        if a.episodes is not None:
            cmd += ["--episodes-per-cell", str(a.episodes)]
        if a.record:
            cmd += ["--truth", str(self.folder / "truth.jsonl")]
        if a.edge_realtime:  # the cars too: each real one is a microcontroller of its own
            cmd.append("--realtime")
        proc = self._spawn("world", cmd)
        reading = asyncio.get_running_loop().run_in_executor(None, proc.stdout.readline)
        stopped = asyncio.ensure_future(stopping.wait())
        await asyncio.wait({reading, stopped}, return_when=asyncio.FIRST_COMPLETED)
        stopped.cancel()
        if not reading.done():  # a signal while the world starts: stop() ends it
            return None
        line = reading.result()
        try:
            ready = json.loads(line)
            self.car_addresses = {c["id"]: tuple(c["address"]) for c in ready["cars"]}
            return int(ready["control_port"])
        except (json.JSONDecodeError, KeyError, TypeError):
            raise HarnessError(
                f"the HIL world did not start; see {self.folder / 'world.log'}"
            ) from None

    def start_gige(self) -> None:
        """The fake GigE camera serving the virtual camera on loopback; waits for it."""
        camera = self.faults.camera
        cmd = [
            sys.executable, "-m", "udan.hil.gige", "--camera-name", self.camera,
            "--lost-ratio", str(camera.get("lost_ratio", 0.0)),
            "--delay-ms", str(camera.get("delay_ms", 0.0)),
            "--delay-block-s", str(DELAY_BLOCK_S),
            "--max-lag-ms", str(picture_lag_ns(self.args) / 1e6),
        ]  # fmt: skip
        proc = self._spawn("gige", cmd)
        line = proc.stdout.readline() if proc.stdout else ""
        if not line.startswith("{"):
            raise HarnessError(f"the fake GigE camera did not start; see {self.folder}/gige.log")

    def camera_url(self) -> str:
        if self.args.camera == "virtual":
            return f"virtual://{self.camera}"
        return f"aravis://127.0.0.1?width=1920&height=1200&fps={self.args.fps:g}"

    def start_edge(self, control_port: int) -> subprocess.Popen:
        a = self.args
        edge = Path(sys.executable).with_name("udan-edge")
        cmd = [
            str(edge), "--camera", self.camera_url(), "--model", str(a.model),
            "--fleet", str(self.fleet), "--listen", f"127.0.0.1:{self.edge_port}",
            "--world", f"127.0.0.1:{control_port}", "--episode-steps", str(a.episode_steps),
            "--report", str(self.folder / "edge.json"),
            "--telemetry", str(self.folder / "telemetry.jsonl"), "--quiet",
            "--settle-mm", str(a.settle_mm), "--settle-deg", str(a.settle_deg),
            "--cell-time-ms", str(a.cell_time_ms),
            "--accel-share", str(motion_level(a.motion_error).accel_share),
        ]  # fmt: skip
        if a.duration is not None:
            cmd += ["--duration", str(a.duration)]
        if a.edge_realtime:
            cmd.append("--realtime")
        if a.video:
            cmd += ["--video", str(self.folder / "run.mp4")]
        if a.record:
            cmd += ["--record", str(self.folder / "run.mcap")]
        cmd += ["--perception", a.edge_perception]
        return self._spawn("edge", cmd)

    async def apply_faults(self, control: tuple[str, int]) -> None:
        """Network faults on every car now, then the timed events as their time comes, counted
        from the first episode's start (the edge can take seconds to start on a loaded machine:
        a forged datagram sent before it listens would be lost, not refused)."""
        if self.faults.network:
            for car in range(1, self.cars[1] + 1):
                await world_request(
                    control, {"op": "faults", "car": car, "set": self.faults.network}
                )
        if self.faults.events:
            while (await world_request(control, {"op": "state"}))["episode"] < 0:
                if self.procs["edge"].poll() is not None:
                    return
                await asyncio.sleep(FIRST_EPISODE_POLL_S)
        start = time.monotonic()
        for event in sorted(self.faults.events, key=lambda e: e.at_s):
            await asyncio.sleep(max(0.0, start + event.at_s - time.monotonic()))
            if self.procs["edge"].poll() is not None:
                return
            now_ns = time.monotonic_ns()
            if event.kind == "forge":
                sent = self.forge(event.count or 0)
                self.events_done.append(
                    {"kind": "forge", "at_s": event.at_s, "t_ns": now_ns, **sent}
                )
                continue
            if event.kind == "unplug":
                self.procs["gige"].kill()  # a camera unplugged says nothing first
                self.procs["gige"].wait()
                await asyncio.sleep(event.seconds or 0.0)
                self.start_gige()
                self.events_done.append(
                    {"kind": "unplug", "at_s": event.at_s, "t_ns": now_ns,
                     "back_ns": time.monotonic_ns()}
                )  # fmt: skip
                continue
            request: dict[str, Any] = {"op": event.kind}
            if event.car is not None:
                request["car"] = event.car
            if event.kind == "stall":
                request["seconds"] = event.seconds
            answer = await world_request(control, request)
            answer.pop("ok", None)
            self.events_done.append(
                {"kind": event.kind, "at_s": event.at_s, "t_ns": now_ns, **answer}
            )

    def forge(self, count: int) -> dict[str, int]:
        """Send forged datagrams from a socket of our own to the edge and the cars; how many
        went to each side."""
        import socket

        targets = {0: ("127.0.0.1", self.edge_port), **self.car_addresses}
        sent = {"to_edge": 0, "to_cars": 0}
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            for target, data in forged_datagrams(count, sorted(self.car_addresses), self.args.seed):
                sock.sendto(data, targets[target])
                sent["to_edge" if target == 0 else "to_cars"] += 1
        return sent

    def stop(self) -> dict[str, str]:
        """SIGTERM every process still running, the last started (the edge: it stops the cars)
        first, then wait for each (SIGKILL after a grace period); their exits."""
        exits = {}
        for name, proc in reversed(self.procs.items()):
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            exits[name] = proc.returncode
        return dict(reversed(exits.items()))


class Progress:
    """Episodes done of planned, the time left and the commands on time so far, from the
    edge's telemetry file as it grows: a bar on a terminal, a line now and then otherwise."""

    def __init__(self, planned: int | None, duration_s: float | None, stream: TextIO) -> None:
        self.planned = planned
        self.duration_s = duration_s
        self.stream = stream
        self.episodes = 0
        self.on_time = 0
        self.missed = 0
        self._offset = 0
        self._partial = b""
        self._started = time.monotonic()
        self._next_line = self._started + PROGRESS_LINE_S
        self._bar = None
        if stream.isatty():
            from tqdm import tqdm

            total = planned if planned is not None else duration_s
            unit = "episode" if planned is not None else "s"
            self._bar = tqdm(total=total, unit=unit, file=stream, dynamic_ncols=True)

    def read(self, telemetry: Path) -> None:
        """Take in what the edge has written since the last call."""
        try:
            with telemetry.open("rb") as f:
                f.seek(self._offset)
                data = f.read()
        except OSError:
            return
        self._offset += len(data)
        *lines, self._partial = (self._partial + data).split(b"\n")
        for line in lines:
            record = json.loads(line)
            if record["kind"] == "episode":
                self.episodes += 1
            elif record["kind"] == "step":
                self.on_time += record.get("on_time", 0)
                self.missed += record.get("missed", 0)
        self._show()

    def share(self) -> str:
        sent = self.on_time + self.missed
        return f"{100 * self.on_time / sent:.2f} %" if sent else "-"

    def _show(self) -> None:
        elapsed = time.monotonic() - self._started
        if self._bar is not None:
            self._bar.n = (
                self.episodes
                if self.planned is not None
                else min(round(elapsed), self.duration_s or 0)
            )
            self._bar.set_postfix_str(
                f"episodes {self.episodes}, on time {self.share()}", refresh=False
            )
            self._bar.refresh()
            return
        if time.monotonic() < self._next_line:
            return
        self._next_line += PROGRESS_LINE_S
        print(f"{PROG}: {self.line(elapsed)}", file=self.stream, flush=True)

    def line(self, elapsed: float) -> str:
        """Episodes done (of planned), the time left, the share on time so far."""
        from tqdm import tqdm

        if self.planned is not None:
            left = (
                tqdm.format_interval(elapsed / self.episodes * (self.planned - self.episodes))
                if self.episodes
                else "?"
            )
            done = f"{self.episodes}/{self.planned} episodes"
        else:
            left = tqdm.format_interval(max(0.0, (self.duration_s or 0) - elapsed))
            done = f"{self.episodes} episodes"
        return f"{done}, {left} left, commands on time {self.share()}"

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


async def run_loop(
    args: argparse.Namespace, folder: Path, faults: FaultPlan, progress: Progress
) -> dict[str, Any]:
    """Start world and edge, apply faults, wait for the edge to finish or a signal, stop all,
    collect. ``interrupted`` in the result names the signal that stopped the run, if one did."""
    loop = Loop(args, folder, faults)
    aio = asyncio.get_running_loop()
    stopping = asyncio.Event()
    interrupted: list[str] = []

    def interrupt(sig: signal.Signals) -> None:
        interrupted.append(sig.name)
        stopping.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        aio.add_signal_handler(sig, interrupt, sig)
    world_summary: dict[str, Any] | None = None
    try:
        port = await loop.start_world(stopping)
        if port is None:
            raise Stopped(interrupted[0])
        control = ("127.0.0.1", port)
        if args.camera == "gige":
            loop.start_gige()
        edge = loop.start_edge(port)
        injector = asyncio.ensure_future(loop.apply_faults(control))
        deadline = None if args.timeout is None else time.monotonic() + args.timeout
        telemetry = folder / "telemetry.jsonl"
        while edge.poll() is None and not stopping.is_set():
            if deadline is not None and time.monotonic() > deadline:
                break
            if injector.done() and injector.exception() is not None:
                raise HarnessError(f"fault injection failed: {injector.exception()}")
            progress.read(telemetry)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stopping.wait(), POLL_S)
        injector.cancel()
        if not stopping.is_set():
            with contextlib.suppress(Exception):
                world_summary = {"state": await world_request(control, {"op": "state"}, 1.0)}
    finally:
        exits = loop.stop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            aio.remove_signal_handler(sig)
        world_out = loop.procs.get("world")
        if world_out is not None and world_out.stdout is not None:
            for line in world_out.stdout.read().splitlines()[::-1]:
                with contextlib.suppress(json.JSONDecodeError):
                    world_summary = {**(world_summary or {}), **json.loads(line)}
                    break
    progress.read(folder / "telemetry.jsonl")
    edge_report_path = folder / "edge.json"
    if not edge_report_path.is_file():
        raise HarnessError(f"udan-edge wrote no report (exit {exits.get('edge')}); see edge.log")
    result = {
        "edge": json.loads(edge_report_path.read_text()),
        "world": world_summary or {},
        "exits": exits,
        "events": loop.events_done,
        "interrupted": interrupted[0] if interrupted else None,
    }
    if args.record:
        result["sightings"] = check_recording(args, folder)
    return result


def picture_lag_ns(args: argparse.Namespace) -> int:
    """How much older than its timestamp a frame's picture may be: 0 for the virtual camera
    (it stamps the instant it draws), two frame periods for the fake GigE camera (it serves the
    newest render when its own clock fires, and stamps an older one with the render's time)."""
    return 0 if args.camera == "virtual" else round(2e9 / args.fps)


def check_recording(args: argparse.Namespace, folder: Path) -> dict[str, Any]:
    """The edge's recorded sightings against the world's truth, within `picture_lag_ns`."""
    from udan.edge.flightlog import FlightLogError, read_flight_log
    from udan.hil.truth import Truth, check_sightings

    try:
        log = read_flight_log(folder / "run.mcap")
    except FlightLogError as err:
        return {"error": str(err)}
    return check_sightings(log, Truth(folder / "truth.jsonl"), picture_lag_ns(args))


def planned_episodes(args: argparse.Namespace) -> int | None:
    """Episodes the run plays: ``--episodes`` per cell of cars x obstacles (None with
    ``--duration``: random ones until the time is up)."""
    if args.episodes is None:
        return None
    cars, obstacles = parse_range(args.cars, "cars"), parse_range(args.obstacles, "obstacles")
    cells = (cars[1] - cars[0] + 1) * (obstacles[1] - obstacles[0] + 1)
    return args.episodes * cells


def _check(args: argparse.Namespace) -> FaultPlan:
    if args.task not in TASKS:
        raise HarnessError(f"unknown task {args.task!r}; the HIL world plays {', '.join(TASKS)}")
    cars = parse_range(args.cars, "cars")
    parse_range(args.obstacles, "obstacles")
    if not 1 <= cars[0] <= cars[1] <= 5:
        raise HarnessError(f"--cars {args.cars}: the arena plays 1-5 cars")
    if (args.episodes is None) == (args.duration is None):
        raise HarnessError("give exactly one of --episodes (per cell) or --duration")
    if not args.model.is_file():
        raise HarnessError(f"model {args.model}: no such file")
    motion_level(args.motion_error)
    faults = parse_faults(args.faults)
    if args.camera != "gige" and (faults.camera or any(e.kind == "unplug" for e in faults.events)):
        raise HarnessError("gige_loss, frame_delay and unplug are faults of --camera gige")
    try:
        args.report.mkdir(parents=True, exist_ok=True)
        probe = args.report / ".write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as err:
        raise HarnessError(f"report folder {args.report}: {err.strerror or err}") from None
    return faults


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: 0 when the run completed (the report says how well), 2 on bad input,
    128 + the signal's number when a signal stopped it (the report covers what was done)."""
    args = _parser().parse_args(argv)
    try:
        faults = _check(args)
    except (HarnessError, FaultSpecError, EnvConfigError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    planned = planned_episodes(args)
    if planned is not None:
        cars, obstacles = parse_range(args.cars, "cars"), parse_range(args.obstacles, "obstacles")
        print(
            f"{PROG}: {planned} episodes planned ({args.episodes} per cell: cars "
            f"{cars[0]}-{cars[1]} x obstacles {obstacles[0]}-{obstacles[1]}); report in "
            f"{args.report}",
            file=sys.stderr,
            flush=True,
        )
    else:
        print(f"{PROG}: random episodes for {args.duration:g} s; report in {args.report}",
              file=sys.stderr, flush=True)  # fmt: skip
    progress = Progress(planned, args.duration, sys.stderr)
    try:
        result = asyncio.run(run_loop(args, args.report, faults, progress))
    except HarnessError as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    except Stopped as stopped:
        print(f"{PROG}: {stopped}", file=sys.stderr)
        return 128 + signal.Signals[stopped.signal].value
    finally:
        progress.close()
    result["planned"] = planned
    from udan.hil.report import can_plot, write_report

    records = result["edge"]["episodes"]
    episodes = [Episode(e["agents"], e["obstacles"], e["seed"]) for e in records]
    orders = [slot_order(e) for e in records]
    sim = simulate(args.task, args.model, episodes, args.episode_steps, orders)
    summary = write_report(args, result, sim, args.report)
    if not can_plot():
        print(
            f"{PROG}: no PNGs: matplotlib is missing (pip install 'udan-edge[hil]')",
            file=sys.stderr,
        )
    print(json.dumps(summary["headline"], indent=1))
    if result["interrupted"] is not None:
        print(
            f"{PROG}: stopped by {result['interrupted']} after {len(episodes)} of "
            f"{planned if planned is not None else '?'} episodes; the report covers them",
            file=sys.stderr,
        )
        return 128 + signal.Signals[result["interrupted"]].value
    return 0
