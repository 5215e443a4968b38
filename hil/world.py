"""The simulated arena the mock cars drive in, seen by the virtual camera:
``python -m udan.hil.world``.

One process holds the world and every mock car's motor controller (``MotorEnd``, on its end of
a pty serial line); it starts the cars' ESP8266 mocks (each a real UDP socket and the firmware,
``udan.firmware_mock.udp.EspCar``) as a process of their own, which opens those serial lines by
name (``udan.hil.esp``), and the virtual camera as another, which renders a mirror of the world
at 40 FPS into shared memory (``virtual://NAME``).
The edge runs as a separate process and sees none of this except camera frames and UDP.

Where moves end is decided here (``HilWorld``, the firmware's ``World``): each car has a true,
continuous pose; a move drives from it along the car's speed profile and ends where the run's
motion level makes it (``--motion-error 0|low|lab|rough``, :mod:`udan.hil.motion`: level ``0``
exactly on the target cell's centre, as the earlier grid world did), unless the cell it ends in
is off the grid, an obstacle, or held by a car that is not itself leaving it (the arena's rules
make such a move a wait). A move cut short (stop, watchdog, reboot) leaves the car where it is.
Car bodies that touch are collisions, and counted: the edge must never cause one.

Episodes come from the same code as the simulation: episode ``i`` of the plan is the arena
``ArenaBatch(agents=n, obstacles=m, seed=s)`` lays out, its first ``n`` cars of the fleet placed
on its start cells (the others parked off the arena, unseen), so the full loop and the pure
simulation play the very same layouts. A loopback JSON control port (not the car protocol)
serves the edge's episode requests and the harness's faults, like the mock firmware's.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import json
import math
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from udan.edge.geometry import ArenaGeometry
from udan.edge.pauses import freeze_garbage, run_process_realtime, run_realtime, scheduler
from udan.edge.sidecar import exit_with_parent
from udan.envs.arena import ArenaBatch, ArenaConfig
from udan.envs.errors import EnvConfigError, OneLineParser, parse_range
from udan.envs.rules import FREE, OBSTACLE, WALL, WATER
from udan.firmware_mock.faults import Faults
from udan.firmware_mock.firmware import CarTiming
from udan.firmware_mock.fleet import load_fleet
from udan.firmware_mock.motor import Pose, Trajectory, wrap
from udan.firmware_mock.udp import MotorEnd, car_counters
from udan.fleetfile import FleetFileError
from udan.hil.children import Child
from udan.hil.esp import EspProcess
from udan.hil.motion import (
    LEVELS,
    CarMotion,
    MotionLevel,
    bodies_touch,
    may_meet,
    may_touch,
    motion_level,
    poses_at,
    reach_box,
)
from udan.hil.render import CameraModel, Renderer
from udan.hil.vcam import VirtualCamera

PROG = "hil-world"
Cell = tuple[int, int]
_KINDS = {"obstacle": OBSTACLE, "wall": WALL, "water": WATER}
#: A world for the camera: layout, cars' poses at rest, moves in progress.
Scene = tuple[np.ndarray, dict[int, Pose], dict[int, Trajectory]]
CONTACT_STEP_NS = 5_000_000
"""Contacts are sampled this often while cars move (7 mm at the fastest cars' top speed)."""
STOPS_KEPT = 200
"""Moves cut short, and contacts, kept for the state (its answer fits one datagram)."""


@dataclass(frozen=True)
class Episode:
    """One planned episode: how many cars and obstacles, and the layout seed."""

    agents: int
    obstacles: int
    seed: int


def plan(
    agents: tuple[int, int],
    obstacles: tuple[int, int],
    seed: int,
    per_cell: int | None = None,
) -> Iterator[Episode]:
    """Episodes: ``per_cell`` of every (agents, obstacles) cell in turn, or random ones forever.
    Episode ``i`` has layout seed ``seed + i`` either way."""
    if per_cell is not None:
        cells = itertools.product(
            range(obstacles[0], obstacles[1] + 1), range(agents[0], agents[1] + 1)
        )
        for i, ((m, n), _) in enumerate(itertools.product(cells, range(per_cell))):
            yield Episode(n, m, seed + i)
        return
    rng = np.random.default_rng(seed)
    for i in itertools.count():
        n = int(rng.integers(agents[0], agents[1] + 1))
        m = int(rng.integers(obstacles[0], obstacles[1] + 1))
        yield Episode(n, m, seed + i)


def episode_arena(task: str, episode: Episode, steps: int = 50) -> ArenaBatch:
    """The simulated arena of ``episode`` after its reset: layout and start cells; its episode
    lasts ``steps`` decisions (the HIL run's ``--episode-steps``)."""
    config = ArenaConfig(
        task=task,
        agents=(episode.agents, episode.agents),
        obstacles=(episode.obstacles, episode.obstacles),
        max_steps=steps,
    )
    arena = ArenaBatch(config, 1, seed=episode.seed)
    arena.reset()
    return arena


class HilWorld:
    """Where every car truly is, where moves end, what the camera sees (thread-safe snapshot),
    and which car bodies touched.

    Poses are continuous (arena metres and radians). A move begun by a car's controller runs
    along the controller's speed profile from where the car truly is to where the motion
    ``level`` makes it end (:class:`udan.hil.motion.CarMotion`; at level ``0`` exactly on the
    centre of its target's cell). A move cut short leaves the car where it is at that instant.
    Contacts are checked between every two events (a move begun, ended or cut, a car placed or
    taken away), sampling the moves in force every ``CONTACT_STEP_NS``: every new contact of two
    bodies is a collision, counted once however long they touch.
    """

    def __init__(
        self,
        geometry: ArenaGeometry,
        markers: dict[int, int],
        level: MotionLevel = LEVELS["0"],
        seed: int = 0,
    ) -> None:
        self.geometry = geometry
        self.cell_m = geometry.cell_m
        self.markers = markers
        self.level = level
        self.seed = seed
        self.layout = np.zeros((geometry.rows, geometry.cols), np.uint8)
        self.pose: dict[int, Pose] = {}
        """Every car's true pose at rest (for a car in a move: where the move started)."""
        self.motion: dict[int, Trajectory] = {}
        self.counts = {"moves": 0, "blocked": 0, "collisions": 0, "aborted": 0, "slips": 0}
        self.stops: deque[list[float]] = deque(maxlen=STOPS_KEPT)
        """Where moves were cut short: [car, t_ns, x, y, heading], the latest ones."""
        self.refusals: deque[list[Any]] = deque(maxlen=STOPS_KEPT)
        """Moves the rules refused: [car, t_ns, start row, col, end row, col, why, holders]."""
        self.contacts: deque[list[float]] = deque(maxlen=STOPS_KEPT)
        """Every collision: [t_ns, car, other, x, y, heading, other's x, y, heading]."""
        self.settled: dict[int, list[tuple[float, float]]] = {}
        """Per car and per minute of the run: the largest (off-centre metres, |heading|
        radians) a move ended with, in truth."""
        self.listener: Callable[[Scene], None] | None = None
        """Called with the new :meth:`scene` after every change (the camera process's mirror)."""
        self._errors: dict[int, CarMotion] = {}
        self._touching: set[tuple[int, int]] = set()
        self._swept_ns = time.monotonic_ns()  # contacts are counted up to here
        self._started_ns = self._swept_ns
        self.history: list[tuple[int, dict[int, Cell], dict[int, tuple[Cell, Cell, int]]]] = []
        """Every change, once :attr:`keep_history` is set: (when, every car's cell, the moves in
        progress as their start and end cells), the truth a recording's sightings are checked
        against (:mod:`udan.hil.truth`)."""
        self.keep_history = False
        self._lock = threading.Lock()

    def scene(self) -> Scene:
        """What the camera needs to draw any instant until the next change: the layout, every
        car's pose at rest, and the moves in progress."""
        with self._lock:
            return self.layout.copy(), dict(self.pose), dict(self.motion)

    def restore(self, scene: Scene) -> None:
        """Take over ``scene`` (a mirror of another process's world)."""
        layout, pose, motion = scene
        with self._lock:
            self.layout, self.pose, self.motion = layout, pose, motion

    def _changed(self) -> None:
        scene = self.scene()
        if self.keep_history:
            cells = {car: self._cell(pose) for car, pose in scene[1].items()}
            moves = {car: (self._cell(m.start), self._cell(m.end), m.started_ns)
                     for car, m in scene[2].items()}  # fmt: skip
            self.history.append((time.monotonic_ns(), cells, moves))
        if self.listener is not None:
            self.listener(scene)

    def write_history(self, path: Path) -> None:
        """The history as JSON lines: ``{"t_ns", "pose": {car: cell}, "motion": {car: [from,
        to, start_ns]}}``."""
        with path.open("w", encoding="utf-8") as out:
            for t_ns, pose, motion in self.history:
                record = {
                    "t_ns": t_ns,
                    "pose": {str(c): list(p) for c, p in pose.items()},
                    "motion": {str(c): [list(a), list(b), t0] for c, (a, b, t0) in motion.items()},
                }
                out.write(json.dumps(record, separators=(",", ":")) + "\n")

    def _cell(self, pose: Pose) -> Cell:
        return math.floor(pose.y / self.cell_m), math.floor(pose.x / self.cell_m)

    def _centre(self, cell: Cell) -> Pose:
        return Pose(*self.geometry.cell_centre(*cell), 0.0)

    # -- the firmware's World --------------------------------------------------------------
    def begin(self, car_id: int, plan: Trajectory) -> None:
        """A car in the arena started driving ``plan``: its true move, from where it is."""
        with self._lock:
            self._sweep(time.monotonic_ns())
            start = self.pose.get(car_id)
            if start is not None:
                if self.level.exact:
                    end = self._centre(self._cell(plan.end))._replace(heading=plan.end.heading)
                else:
                    errors = self._errors.get(car_id)
                    if errors is None:
                        errors = CarMotion(self.level, self.seed, car_id, self.cell_m)
                        self._errors[car_id] = errors
                    slips = errors.slips
                    end = errors.true_end(start, plan)
                    self.counts["slips"] += errors.slips - slips
                self.motion[car_id] = replace(plan, start=start, end=end)
        self._changed()

    def abort(self, car_id: int) -> None:
        """A move was cut: the car stays where it is now."""
        with self._lock:
            now = time.monotonic_ns()
            self._sweep(now)
            move = self.motion.pop(car_id, None)
            if move is not None and car_id in self.pose:
                here = move.at(now)
                self.pose[car_id] = here
                self.counts["aborted"] += 1
                self.stops.append([car_id, now, *(round(v, 4) for v in here)])
        self._changed()

    def end(self, car_id: int) -> bool:
        """A car's move is over: it stands where the move ended, unless the rules refuse the
        cell that is (off the grid, an obstacle, held by a car not itself leaving it): then it
        is back where it started, as the arena's rules make such a move a wait."""
        with self._lock:
            now = time.monotonic_ns()
            self._sweep(now)
            move = self.motion.pop(car_id, None)
            moved = False
            if move is not None and car_id in self.pose:
                dest = self._cell(move.end)
                inside = 0 <= dest[0] < self.geometry.rows and 0 <= dest[1] < self.geometry.cols
                holders = [
                    c
                    for c, p in self.pose.items()
                    if c != car_id
                    and self._cell(p) == dest
                    and not (c in self.motion and self._cell(self.motion[c].start) == dest)
                ]
                moved = inside and self.layout[dest] == FREE and not holders
                if not moved:
                    why = "held" if holders else "off the grid" if not inside else "not free"
                    start = self._cell(move.start)
                    self.refusals.append([car_id, now, *start, *dest, why, *holders])
                self.pose[car_id] = move.end if moved else move.start
                self.counts["moves" if moved else "blocked"] += 1
                self._settled(car_id, self.pose[car_id], now)
        self._changed()
        return moved

    def _settled(self, car_id: int, pose: Pose, now: int) -> None:
        """Keep the minute's worst off-centre distance and heading of the car's moves."""
        cx, cy, _ = self._centre(self._cell(pose))
        off, turned = math.hypot(pose.x - cx, pose.y - cy), abs(wrap(pose.heading))
        minutes = self.settled.setdefault(car_id, [])
        minute = (now - self._started_ns) // 60_000_000_000
        minutes.extend([(0.0, 0.0)] * (minute + 1 - len(minutes)))
        worst = minutes[minute]
        minutes[minute] = (max(worst[0], off), max(worst[1], turned))

    # -- contacts --------------------------------------------------------------------------
    def _sweep(self, now: int) -> None:
        """Count the contacts since the last event: the moves in force have not changed since,
        so sampling them is the whole story (cars at rest are checked once). Pairs that cannot
        have come close (:func:`may_meet`, no numpy) are not sampled: usually every pair, and
        the sweep runs inside a car's move start or end, which the cars' other commands wait
        behind (the sampled sweep cost ~0.3 ms there, ~0.9 ms at its 99th percentile)."""
        since, self._swept_ns = self._swept_ns, now
        cars = sorted(self.pose)
        boxes = [reach_box(self.motion.get(c), self.pose[c], since, now) for c in cars]
        if not any(may_meet(a, b) for a, b in itertools.combinations(boxes, 2)):
            self._touching.clear()
            return
        if self.motion and now > since:
            times = np.append(np.arange(since + CONTACT_STEP_NS, now, CONTACT_STEP_NS), now)
        else:
            times = np.array([now])
        poses = np.stack(
            [
                poses_at(self.motion[c], times) if c in self.motion
                else np.broadcast_to(np.asarray(self.pose[c]), (len(times), 3))
                for c in cars
            ],
            1,
        )  # fmt: skip
        touching = set()
        first, second = np.triu_indices(len(cars), 1)
        close = may_touch(poses[:, first], poses[:, second]).any(axis=0)
        for i, j in zip(first[close].tolist(), second[close].tolist(), strict=True):
            a, b = poses[:, i], poses[:, j]
            near = may_touch(a, b)
            contact = np.zeros(len(times), bool)
            contact[near] = bodies_touch(a[near], b[near])
            pair = (cars[i], cars[j])
            before = np.concatenate([[pair in self._touching], contact[:-1]])
            for k in np.flatnonzero(contact & ~before):
                self.counts["collisions"] += 1
                where = np.round(np.concatenate([a[k], b[k]]), 4).tolist()
                self.contacts.append([int(times[k]), *pair, *where])
            if contact[-1]:
                touching.add(pair)
        self._touching = touching

    # -- episodes and the harness ----------------------------------------------------------
    def place(self, layout: np.ndarray, cells: dict[int, Cell]) -> None:
        """A new layout with these cars on these cells' centres; every other car is parked
        (unseen)."""
        with self._lock:
            self.layout = layout.copy()
            self.pose = {car: self._centre(cell) for car, cell in cells.items()}
            self.motion.clear()
            self._touching.clear()
            self._swept_ns = time.monotonic_ns()
        self._changed()

    def remove(self, car_id: int) -> None:
        """Take a car off the arena (it leaves the camera's view)."""
        with self._lock:
            self._sweep(time.monotonic_ns())
            self.pose.pop(car_id, None)
            self.motion.pop(car_id, None)
        self._changed()

    def add(self, car_id: int, cell: Cell | None = None) -> Cell:
        """Put a car on ``cell`` (default: the free start cell nearest the bottom-right)."""
        with self._lock:
            self._sweep(time.monotonic_ns())
            taken = {self._cell(p) for p in self.pose.values()}
            if cell is None:
                free = [
                    (r, c)
                    for r in range(self.geometry.rows - 1, -1, -1)
                    for c in range(self.geometry.cols - 1, -1, -1)
                    if self.layout[r, c] == FREE and (r, c) not in taken
                ]
                cell = free[0]
            if self.layout[cell] != FREE or cell in taken:
                raise ValueError(f"cell {cell} is not free")
            self.pose[car_id] = self._centre(cell)
        self._changed()
        return cell

    # -- what the camera sees ----------------------------------------------------------------
    def snapshot(self, now_ns: int) -> tuple[list[tuple[int, float, float, float]], dict]:
        """Cars as (marker, x, y, heading) with moves in progress where they are at
        ``now_ns``, and the static cells by kind."""
        with self._lock:
            cars = []
            for car, pose in self.pose.items():
                x, y, heading = self.motion[car].at(now_ns) if car in self.motion else pose
                cars.append((self.markers[car], x, y, heading))
            cells = {
                kind: [tuple(rc) for rc in np.argwhere(self.layout == code).tolist()]
                for kind, code in _KINDS.items()
            }
        return cars, cells

    def state(self) -> dict[str, Any]:
        """Truth for the harness: every car's cell and pose, moves in progress, counts, where
        moves were cut, and each minute's worst end of a move per car."""
        with self._lock:
            return {
                "pose": {str(c): list(self._cell(p)) for c, p in self.pose.items()},
                "xy": {str(c): list(p) for c, p in self.pose.items()},
                "moving": sorted(self.motion),
                "counts": dict(self.counts),
                "stops": list(self.stops),
                "refusals": list(self.refusals),
                "contacts": list(self.contacts),
                "settled": {str(c): m for c, m in self.settled.items()},
            }


#: The camera process yields the CPU to the cars and the edge (Unix niceness, higher is nicer).
CAMERA_NICENESS = 10
CAMERA_PRIORITY = 7
"""Under ``--realtime`` the camera is SCHED_RR at this priority instead: a camera's readout is
its own hardware's, never held up by the host's load, so the renderer that stands for it runs
above the perception process (5) and ordinary processes, below the edge's loop and the cars
(10), whose CPU it must not take."""
CAMERA_SLOTS = 8
"""Frames the virtual camera's shared memory holds (200 ms at 40 FPS): the perception process
is lent its frame in place, and the flight recorder's frame ring copies a decision's frame out
of its slot only when the edge asks for it, tens of milliseconds later."""


class CameraProcess:
    """The virtual camera in a process of its own, rendering a mirror of the world at 40 FPS.

    As a thread of the cars' process, rendering (about 10 ms of CPU a frame, part of it holding
    the GIL) delayed the cars' receive loop: a command that reaches a car after its deadline is
    a miss. Its own process, at a lower priority, leaves the cars' process nearly idle. The
    world sends every change of its :meth:`HilWorld.scene` down a pipe; the camera interpolates
    moves in progress itself from their start times (``time.monotonic_ns`` is one clock for all
    processes on the machine).
    """

    def __init__(self, world: HilWorld, config: dict[str, Any]) -> None:
        self._child = Child(_camera_main, config, name="virtual-camera", what="virtual camera")
        self._conn = self._child.conn
        world.listener = self._send_scene
        self._send_scene(world.scene())

    def _send(self, kind: str, value: Any) -> None:
        with contextlib.suppress(OSError):  # a camera that died shows as a stream that stopped
            self._conn.send((kind, value))

    def _send_scene(self, scene: Scene) -> None:
        self._send("scene", scene)

    def stall(self, seconds: float) -> None:
        """Camera fault: publish nothing for ``seconds`` from now."""
        self._send("stall", seconds)

    def stop(self) -> dict[str, Any]:
        """Stop rendering, remove the shared memory; the camera's counters."""
        return self._child.stop(("stop", None)) or {}


def _camera_main(conn: Connection, config: dict[str, Any]) -> None:
    """The camera process: render the mirrored world until told to stop (or the world dies)."""
    if config["realtime"]:
        run_process_realtime(CAMERA_PRIORITY)
    else:
        os.nice(CAMERA_NICENESS)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the world, which stops us
    try:
        model = CameraModel(**config["model"])
        renderer = Renderer(config["geometry"], model)
        camera = VirtualCamera(
            config["name"], model.width, model.height, slots=CAMERA_SLOTS, fps=config["fps"]
        )
    except (OSError, ValueError) as err:
        conn.send(("error", str(err)))
        return
    world = HilWorld(config["geometry"], config["markers"])
    halt = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: halt.set())
    render_ns: deque[int] = deque(maxlen=20_000)

    def listen() -> None:
        while not halt.is_set():
            try:
                kind, value = conn.recv()
            except (EOFError, OSError):
                kind, value = "stop", None
            if kind == "scene":
                world.restore(value)
            elif kind == "stall":
                camera.stall(value)
            else:
                halt.set()

    def render(t_ns: int, out: np.ndarray) -> None:
        cars, cells = world.snapshot(t_ns)
        renderer.render(cars, cells, out=out)
        render_ns.append(time.monotonic_ns() - t_ns)

    threading.Thread(target=listen, name="world mirror", daemon=True).start()
    try:
        conn.send(("ready", None))
    except OSError:  # the world was stopped while this process started: nobody to render for
        camera.close()
        return
    try:
        camera.run(render, stop=halt)
    finally:
        camera.close()
    ms = np.asarray(render_ns or [0]) / 1e6
    summary = {
        "frames": camera.frames,
        "frames_faulted": camera.faulted,
        "render_ms": {
            "p50": round(float(np.median(ms)), 3),
            "p99": round(float(np.percentile(ms, 99)), 3),
        },
        "camera_scheduler": scheduler(),
    }
    with contextlib.suppress(OSError):
        conn.send(("summary", summary))


class _Control(asyncio.DatagramProtocol):
    """Loopback JSON control: the edge's episode requests and the harness's faults."""

    def __init__(self, server: WorldServer) -> None:
        self.server = server
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: Any) -> None:
        task = asyncio.ensure_future(self._answer(data, addr))
        self.server.requests.add(task)
        task.add_done_callback(self.server.requests.discard)

    async def _answer(self, data: bytes, addr: Any) -> None:
        try:
            reply = {"ok": True, **await self.server.handle(json.loads(data))}
        except (ValueError, KeyError, TypeError) as err:
            reply = {"ok": False, "error": str(err)}
        if self.transport is not None:
            self.transport.sendto(json.dumps(reply).encode(), addr)


class WorldServer:
    """The world process: motor controllers, world, episodes, control; the cars' ESP8266s and
    the camera in processes of their own."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.specs = load_fleet(args.fleet, base_port=0)
        self.geometry = ArenaGeometry()
        markers = {s.car_id: s.marker for s in self.specs}
        self.level = motion_level(args.motion_error)
        self.world = HilWorld(self.geometry, markers, self.level, seed=args.seed)
        self.world.keep_history = args.truth is not None
        self.episodes = plan(
            parse_range(args.agents, "agents"),
            parse_range(args.obstacles, "obstacles"),
            args.seed,
            args.episodes_per_cell,
        )
        self.episode_index = -1
        self.motors: dict[int, MotorEnd] = {}
        self.requests: set[asyncio.Task[None]] = set()

    def _motor(self, request: dict[str, Any]) -> tuple[int, MotorEnd]:
        car = int(request["car"])
        if car not in self.motors:
            raise ValueError(f"unknown car {car}")
        return car, self.motors[car]

    async def handle(self, request: dict[str, Any]) -> dict[str, Any]:
        """One control request -> the answer's fields."""
        op = request["op"]
        if op == "episode":
            return self._episode(int(request["index"]))
        if op == "state":
            return {**self.world.state(), "episode": self.episode_index}
        if op == "counters":
            radios = await self.esp.ask("counters")
            counters = {c: car_counters(radios[c], m.counters()) for c, m in self.motors.items()}
            return {"cars": {str(c): v for c, v in counters.items()}}
        if op == "cars":
            radios = await self.esp.ask("state")
            return {"cars": {str(c): {**radios[c], **m.state()} for c, m in self.motors.items()}}
        if op == "faults":
            car, motor = self._motor(request)
            motor.faults.update(request["set"])  # checked here first: both halves or neither
            await self.esp.ask("faults", car, request["set"])
            return {}
        if op == "reboot":
            await self.esp.ask("reboot", self._motor(request)[0])
            return {}
        if op == "cut":
            share = float(request.get("share", 0.5))
            if not 0 < share < 1:
                raise ValueError(f"cut share {share} outside 0-1")
            self._motor(request)[1].controller.drive.cut_next_move(share)
            return {}
        if op == "leave":
            self.world.remove(int(request["car"]))
            return {}
        if op == "join":
            cell = tuple(request["cell"]) if request.get("cell") else None
            return {"cell": list(self.world.add(int(request["car"]), cell))}
        if op == "stall":
            self.camera.stall(float(request["seconds"]))
            return {}
        raise ValueError(f"unknown op {op!r}")

    def _episode(self, index: int) -> dict[str, Any]:
        """Lay out episode ``index`` (the plan is walked forward only)."""
        if index <= self.episode_index:
            raise ValueError(f"episode {index} already played")
        episode = None
        while self.episode_index < index:
            episode = next(self.episodes, None)
            self.episode_index += 1
            if episode is None:
                return {"done": True}
        assert episode is not None
        arena = episode_arena(self.args.task, episode)
        cars = sorted(self.motors)[: episode.agents]
        if len(cars) < episode.agents:
            raise ValueError(f"episode needs {episode.agents} cars, the fleet has {len(cars)}")
        cells = {car: tuple(int(v) for v in arena.pos[0, i]) for i, car in enumerate(cars)}
        self.world.place(arena.layout[0], cells)
        return {
            "cars": cars,
            "agents": episode.agents,
            "obstacles": episode.obstacles,
            "seed": episode.seed,
        }

    async def run(self) -> dict[str, Any]:
        """Start everything, print the ready line, serve until SIGTERM; the final counters."""
        args = self.args
        loop = asyncio.get_running_loop()
        edge_host, _, edge_port = args.edge.rpartition(":")
        timing = CarTiming(cell_time_s=args.cell_time_ms / 1000, accel_share=self.level.accel_share)
        freeze_garbage()  # real cars have no garbage collector to pause them
        model = {
            "tilt_deg": args.tilt, "k1": args.k1, "noise_sigma": args.noise,
            "blur_sigma": args.blur, "seed": args.seed,
        }  # fmt: skip
        camera_config = {
            "model": model,
            "geometry": self.geometry,
            "name": args.camera_name,
            "fps": args.fps,
            "markers": self.world.markers,
            "realtime": args.realtime,
        }
        with contextlib.ExitStack() as started:  # a part that fails to start stops the others
            started.callback(self._close_motors)
            for spec in self.specs:
                faults = Faults.from_mapping(spec.faults)
                self.motors[spec.car_id] = MotorEnd(spec, self.world, timing, faults)
            self.esp = EspProcess(
                self.specs, {c: m.tty_path for c, m in self.motors.items()},
                edge=(edge_host, int(edge_port)), timing=timing, seed=args.seed,
                realtime=args.realtime,
            )  # fmt: skip
            started.callback(self.esp.stop)
            self.camera = CameraProcess(self.world, camera_config)
            started.callback(self.camera.stop)
            control, _ = await loop.create_datagram_endpoint(
                lambda: _Control(self), local_addr=("127.0.0.1", args.control_port)
            )
            started.pop_all()  # running: stopped below, counters kept
        stop = asyncio.Event()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        ready = {
            "ready": True,
            "control_port": control.get_extra_info("sockname")[1],
            "camera": f"virtual://{args.camera_name}",
            "cars": [{"id": c, "address": list(a)} for c, a in self.esp.addresses.items()],
        }
        print(json.dumps(ready), flush=True)
        try:
            await stop.wait()
        finally:
            camera = self.camera.stop()
            radios = self.esp.stop()  # LEAVE and STOP first, as the cars' power goes
            counters = {
                str(c): car_counters(radios["cars"][c], m.counters()) if radios else m.counters()
                for c, m in self.motors.items()
            }
            self._close_motors()
            control.close()
            if args.truth is not None:
                self.world.write_history(args.truth)
        return {
            "world": self.world.state()["counts"],
            **camera,
            "cars": counters,
            "scheduler": scheduler(),
            "esp_scheduler": radios.get("scheduler"),
        }

    def _close_motors(self) -> None:
        for motor in self.motors.values():
            motor.close()


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="python -m udan.hil.world", description=__doc__.split("\n\n")[0])
    p.add_argument("--fleet", type=Path, required=True, help="fleet.toml of the mock cars")
    p.add_argument("--edge", required=True, help="the edge's HOST:PORT (cars JOIN there)")
    p.add_argument("--camera-name", required=True, help="shared-memory name of the camera")
    p.add_argument("--task", default="find_water", choices=["find_water"])
    p.add_argument("--agents", default="1-5", help="cars per episode, a range")
    p.add_argument("--obstacles", default="0-9", help="obstacles per episode, a range")
    p.add_argument("--episodes-per-cell", type=int, help="plan every cell in turn (else random)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cell-time-ms", type=float, default=200.0)
    p.add_argument(
        "--motion-error", default="0", metavar="LEVEL",
        help=f"how far moves stray: {', '.join(LEVELS)} (docs/motion.md)",
    )  # fmt: skip
    p.add_argument("--fps", type=float, default=40.0)
    p.add_argument("--control-port", type=int, default=0)
    p.add_argument("--tilt", type=float, default=0.0, help="camera tilt (degrees)")
    p.add_argument("--k1", type=float, default=0.0, help="lens distortion k1")
    p.add_argument("--noise", type=float, default=2.0, help="sensor noise sigma (grey levels)")
    p.add_argument("--blur", type=float, default=0.6, help="blur sigma (pixels)")
    p.add_argument("--truth", type=Path, help="write where every car was, when, here at exit")
    p.add_argument(
        "--realtime", action="store_true",
        help="the cars' processes at real-time priority (SCHED_RR; needs CAP_SYS_NICE)",
    )  # fmt: skip
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: serve until SIGTERM, then print the final counters as one JSON line."""
    exit_with_parent()  # if whoever started us asked: its end is our SIGTERM
    args = _parser().parse_args(argv)
    if args.realtime:
        try:
            run_realtime()  # the camera process it starts runs ordinary, 10 nicer
        except PermissionError:
            print(f"{PROG}: error: --realtime: not permitted (needs CAP_SYS_NICE)", file=sys.stderr)
            return 2
    try:
        server = WorldServer(args)
        summary = asyncio.run(server.run())
    except (FleetFileError, EnvConfigError, ValueError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"{PROG}: error: {err.strerror or err}", file=sys.stderr)
        return 2
    with contextlib.suppress(BrokenPipeError):  # whoever started us is gone: nobody to tell
        print(json.dumps(summary), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
