"""The edge runtime's main loop: frames -> cells -> decision -> dispatch, for hours.

One asyncio loop. Capture runs in its own thread (:class:`edge.camera.FrameGrabber`, newest
frame wins) and vision in a worker thread (OpenCV releases the GIL), so the dispatcher's
retransmission timers keep running while a frame is analysed.

A decision step happens on the first frame captured after every car of the fleet reported its
move finished (so the camera shows where the moves ended), or when the step period runs out
(cars still in a move then get ``wait`` and their destinations are held). All commands of a step
leave at once, each valid until the decision + 10 ms.

Episodes (HIL and ``--sim``): with a world control address the runtime asks the world for each
episode's layout, waits until the episode's cars are in the fleet and the vision has swept the
whole new layout once, runs ``episode_steps`` decisions, lets the last moves finish, credits the
last step's rewards from one more frame, and records the returns. Without one it drives the cars for
as long as it runs.

Whatever ends the run — its duration, Ctrl-C, SIGTERM, the end of a video, or an exception — the
``finally`` sends an emergency stop to every joined car before anything is closed.
"""

from __future__ import annotations

import asyncio
import gc
import json
import signal
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

from edge.camera import Frame, FrameGrabber, yield_to_dispatch
from edge.decide import DecisionStep
from edge.fleet import Fleet
from edge.link import CarLink, CommandReport
from edge.pauses import collect_between_steps
from edge.telemetry import Telemetry
from edge.vision import Scene, Vision

ESTOP_GRACE_S = 0.05
#: With no step for this long, collect anyway.
COLLECT_IDLE_NS = 1_000_000_000
#: Rehearse only when the last decision took less than this. A rehearsal runs while the frame
#: is analysed but can hold up its scene by its own length; a decision this long is arithmetic
#: on a large fleet (1,000 agents: ~5 ms warm), not cold caches, and gains little from it.
REHEARSE_UNDER_NS = 3_000_000


def _outcome(command: CommandReport) -> str:
    """on_time (the car accepted it in time), missed, or not_ready (nothing was sent)."""
    if command.acked:
        return "on_time"
    return "not_ready" if command.result == "not_ready" else "missed"


class WorldError(RuntimeError):
    """The HIL world did not answer or refused a request."""


@dataclass(frozen=True)
class LoopConfig:
    """Timing of the main loop."""

    step_timeout_s: float = 1.0
    """Longest a step waits for moves to finish before deciding anyway."""
    stall_s: float = 0.5
    """No frame for this long is a camera stall (counted; cars stop by their watchdog)."""
    duration_s: float | None = None
    """Stop after this long (None: until a signal, or the episodes are done)."""
    episodes: int | None = None
    """With a world: how many episodes to run (None: until the world's plan ends)."""
    episode_steps: int = 50
    """Decisions per episode (the arena's episode length)."""
    join_timeout_s: float = 10.0
    """Longest an episode waits for its cars to be in the fleet before it starts."""
    unseen_grace_s: float = 0.1
    """Longest a step waits for a car the camera missed (then it is stopped for the step)."""

    @property
    def unseen_grace_ns(self) -> int:
        return int(self.unseen_grace_s * 1e9)


async def world_request(
    address: tuple[str, int], payload: Mapping[str, Any], timeout: float = 5.0
) -> dict[str, Any]:
    """One JSON request/answer with the HIL world's loopback control port."""
    loop = asyncio.get_running_loop()
    answer: asyncio.Future[bytes] = loop.create_future()

    class _Client(asyncio.DatagramProtocol):
        def datagram_received(self, data: bytes, addr: Any) -> None:
            if not answer.done():
                answer.set_result(data)

    transport, _ = await loop.create_datagram_endpoint(_Client, remote_addr=address)
    try:
        transport.sendto(json.dumps(payload).encode())
        data = await asyncio.wait_for(answer, timeout)
    except TimeoutError:
        raise WorldError(f"world at {address[0]}:{address[1]} did not answer {payload}") from None
    finally:
        transport.close()
    reply = json.loads(data)
    if not reply.get("ok", False):
        raise WorldError(f"world refused {payload}: {reply.get('error')}")
    return reply


class Runtime:
    """Wires camera, vision, fleet, decision, link and telemetry; ``run`` is the whole job."""

    def __init__(
        self,
        grabber: FrameGrabber,
        vision: Vision,
        link: CarLink,
        decide: DecisionStep,
        fleet: Fleet,
        telemetry: Telemetry,
        config: LoopConfig = LoopConfig(),
        world: tuple[str, int] | None = None,
    ) -> None:
        self.grabber = grabber
        self.vision = vision
        self.link = link
        self.decide = decide
        self.fleet = fleet
        self.telemetry = telemetry
        self.config = config
        self.world = world
        self.stop = asyncio.Event()
        self.last_cell: dict[int, tuple[int, int]] = {}
        self._static: dict[str, frozenset[tuple[int, int]]] | None = None  # the last scene's
        self.last_command: dict[int, int] = {}
        self._car_of_marker = {m: c for c, m in fleet.markers.items()}
        self._vision_pool = ThreadPoolExecutor(
            1, thread_name_prefix="vision", initializer=yield_to_dispatch
        )
        self._not_before_ns = 0
        self._rehearsed = False  # the last step was rehearsed since the last decision
        self._last_decision_ns = 0  # how long the last decision took (state to commands)
        self._collections = 0
        self._longest_collection_ns = 0
        self._collected_ns = time.monotonic_ns()

    # ------------------------------------------------------------------ the job
    async def run(self) -> dict[str, Any]:
        """Drive until the duration, a signal, the end of the camera or of the episodes;
        emergency-stop every car on the way out, whatever happened; return the report. The
        link is started (and closed) by the caller, so a car can be told the edge's address
        before the run."""
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, self.stop.set)
        if self.config.duration_s is not None:
            loop.call_later(self.config.duration_s, self.stop.set)
        gc.disable()  # collections run between steps (_collect), never inside one
        try:
            self.grabber.start()
            if self.world is None:
                await self._drive(max_steps=None)
            else:
                await self._episodes()
        finally:
            gc.enable()
            sent = self.link.estop_all()
            self.telemetry.event("estop", cars=sent)
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.remove_signal_handler(sig)
            await asyncio.sleep(ESTOP_GRACE_S)  # the link repeats the estop in this time
            self.grabber.close()
            self._vision_pool.shutdown(wait=True)
        report = self.telemetry.report()
        report["final"] = self.telemetry.final_line()
        report["link"] = self.link.counters()
        report["camera"] = {"captured": self.grabber.captured, "dropped": self.grabber.dropped}
        report["gc"] = {
            "collections": self._collections,
            "longest_ms": round(self._longest_collection_ns / 1e6, 3),
        }
        return report

    # ------------------------------------------------------------------ frames
    async def _next_scene(self) -> Scene | None:
        """The next frame's scene (captured after ``_not_before_ns``), with the fleet updated;
        None on a stall, the end of the stream, or a stop."""
        while not self.stop.is_set():
            frame = await self._wait_frame()
            if frame is None:
                return None
            if frame.t_capture_ns < self._not_before_ns:
                continue
            loop = asyncio.get_running_loop()
            analysed = loop.run_in_executor(self._vision_pool, self.vision.process, frame)
            if self._worth_rehearsing() and self._rehearse():
                self._rehearsed = True  # this frame may be the deciding one: caches warmed
            scene = await analysed
            now = time.monotonic_ns()
            self._fold(scene, frame, now)
            return scene
        return None

    async def _wait_frame(self) -> Frame | None:
        stopping = asyncio.ensure_future(self.stop.wait())
        grabbing = asyncio.ensure_future(self.grabber.next_frame(self.config.stall_s))
        done, _ = await asyncio.wait({stopping, grabbing}, return_when=asyncio.FIRST_COMPLETED)
        stopping.cancel()
        if grabbing not in done:
            grabbing.cancel()
            return None
        frame = grabbing.result()
        if frame is None and not self.grabber.ended:
            self.telemetry.event("camera_stall", stall_s=self.config.stall_s)
        elif frame is None:
            self.stop.set()
        return frame

    def _fold(self, scene: Scene, frame: Frame, now: int) -> None:
        """A scene into the fleet and the last known cells; telemetry of the frame."""
        self._static = scene.cells
        for marker, sighting in scene.cars.items():
            car = self._car_of_marker.get(marker)
            if car is not None and sighting.inside:
                self.last_cell[car] = sighting.cell
        seen = [m for m, s in scene.cars.items() if s.inside]
        change = self.fleet.update(seen, self.link.ready_cars(), now)
        for car in change.joined:
            self.telemetry.event("fleet_join", car=car)
        for car in change.left:
            self.telemetry.event("fleet_leave", car=car)
            self.last_command.pop(car, None)
        self.telemetry.frame(frame.index, frame.t_capture_ns, now, len(seen), self.grabber.dropped)

    def _worth_rehearsing(self) -> bool:
        """Every car of the fleet finished its move (the next frame taken decides), and the
        last decision was short enough to rehearse."""
        return (
            self._last_decision_ns < REHEARSE_UNDER_NS
            and bool(self.fleet.slot)
            and all(map(self.link.move_finished, self.fleet.slot))
        )

    def _rehearse(self) -> bool:
        """The last step once more; before an episode's first step, the step its fleet would
        make from the cells and markers seen last (that first step is otherwise the coldest:
        1.2 ms median in the full loop, against 0.6 ms for a rehearsed one)."""
        if self.decide.rehearse():
            return True
        slots = dict(self.fleet.slot)
        if self._static is None or not all(car in self.last_cell for car in slots):
            return False
        cells = {car: self.last_cell[car] for car in slots}
        return self.decide.rehearse(slots, cells, self._static)

    def _all_seen(self, scene: Scene) -> bool:
        """Every car of the fleet is on the grid in this frame."""
        return all(
            (s := scene.cars.get(self.fleet.markers[c])) is not None and s.inside
            for c in self.fleet.slot
        )

    def _others(self, scene: Scene) -> list[tuple[int, int]]:
        """Cells of markers on the grid that are not cars of the fleet: they block moves."""
        driven = {self.fleet.markers[c] for c in self.fleet.slot}
        return [s.cell for m, s in scene.cars.items() if s.inside and m not in driven]

    # ------------------------------------------------------------------ steps
    def _collect(self) -> None:
        """Python's cyclic garbage collection, right after a dispatch: the cars now take a move
        (~200 ms) before the next decision. Left to itself, a full collection of this process
        stops every thread for ~14 ms (measured), more than a command's 10 ms, whenever it
        happens to fall; frozen at start and run here, it is small and harmless."""
        start = time.monotonic_ns()
        collect_between_steps(self._collections)
        self._collected_ns = time.monotonic_ns()
        self._collections += 1
        self._longest_collection_ns = max(self._longest_collection_ns, self._collected_ns - start)

    async def _drive(self, max_steps: int | None) -> int:
        """Decide and dispatch step after step; returns the number of steps made."""
        steps = 0
        finished_at: int | None = None
        last_decision = time.monotonic_ns()
        while not self.stop.is_set() and (max_steps is None or steps < max_steps):
            scene = await self._next_scene()
            if time.monotonic_ns() - self._collected_ns > COLLECT_IDLE_NS:
                self._collect()  # no step for a while (a stall, an empty arena)
            if scene is None or not self.fleet.slot:
                continue
            now = time.monotonic_ns()
            moving = {
                c: self.last_command[c]
                for c in self.fleet.slot
                if c in self.last_command and not self.link.move_finished(c)
            }
            if not moving and finished_at is None:
                finished_at = now
            fresh_view = finished_at is not None and scene.t_capture_ns >= finished_at
            # a car the camera missed in this frame would be judged on a stale cell (and stopped
            # for the step): wait a few frames for it, not longer (it may have left the arena)
            waited = finished_at is not None and now - finished_at > self.config.unseen_grace_ns
            fresh_view = fresh_view and (self._all_seen(scene) or waited)
            timed_out = now - last_decision > self.config.step_timeout_s * 1e9
            if not (fresh_view or timed_out):
                continue
            await self._step(scene, moving, now)
            self._collect()
            steps += 1
            finished_at = None
            last_decision = time.monotonic_ns()
        return steps

    async def _step(self, scene: Scene, moving: Mapping[int, int], state_ns: int) -> None:
        """One decision and its dispatch, with the step's telemetry."""
        slots = dict(self.fleet.slot)
        cells = {c: self.last_cell[c] for c in slots}
        fresh = set(self.fleet.fresh)
        decision = self.decide.decide(slots, fresh, cells, scene.cells, self._others(scene), moving)
        self.fleet.stepped()
        decided_ns = time.monotonic_ns()
        rehearsed, self._rehearsed = self._rehearsed, False
        self._last_decision_ns = decided_ns - state_ns
        commands = {c: int(a) for c, a in zip(decision.cars, decision.commands, strict=True)}
        report = await self.link.dispatch(commands, decided_ns)
        self.last_command.update(commands)
        received = [r.car_received_ns for r in report.cars.values() if r.acked]
        # an audit of the car: a command it executed (ACCEPTED, not a duplicate's ack, which
        # carries the copy's later receive time) must have reached it by its deadline, judged
        # in the car's own clock (the edge-clock estimate is only good to half a round trip)
        late = sum(
            r.car_rx_us > r.car_deadline_us
            for r in report.cars.values()
            if r.acked and r.result == "accepted"
        )
        acked = [r.acked_ns for r in report.cars.values() if r.acked]
        self.telemetry.step(
            {
                "t_ns": decided_ns,
                "step": self.decide.t,
                "cars": len(slots),
                "fresh": sorted(fresh),  # new to the policy: their memory starts empty
                "frame": scene.frame_index,
                "state_to_commands_ns": decided_ns - state_ns,
                "commands_to_received_ns": max(received) - decided_ns
                if len(received) == len(commands)
                else None,
                "frame_to_received_ns": max(received) - scene.t_capture_ns
                if len(received) == len(commands)
                else None,
                "decision_to_acked_ns": max(acked) - decided_ns
                if len(acked) == len(commands)
                else None,
                "on_time": report.on_time,
                "retried": report.retried,
                "missed": report.missed,
                "not_ready": report.not_ready,
                "slow_sends": report.slow_sends,
                "late_sends": report.late_sends,
                "late_executions": late,
                "blocked": decision.blocked,
                "stopped": decision.stopped,
                "spans_ns": decision.spans_ns,
                "formed": decision.formed,
                "rehearsed": rehearsed,
                "outcomes": {str(c): _outcome(r) for c, r in report.cars.items()},
                "commands": {str(c): a for c, a in commands.items()},
            }
        )

    # ------------------------------------------------------------------ episodes
    async def _episodes(self) -> None:
        """Ask the world for each episode, play it, credit the last step, record the returns."""
        assert self.world is not None
        index = 0
        while not self.stop.is_set() and (
            self.config.episodes is None or index < self.config.episodes
        ):
            info = await world_request(self.world, {"op": "episode", "index": index})
            if info.get("done"):
                break
            self.decide.reset()
            self._rehearsed = False
            self.fleet.reset()
            self.last_command.clear()
            self._not_before_ns = time.monotonic_ns()
            cars = set(info["cars"])
            if not await self._await_fleet(cars):
                self.telemetry.event("episode_skipped", index=index, cars=sorted(cars))
                index += 1
                continue
            steps = await self._drive(self.config.episode_steps)
            if steps < self.config.episode_steps:  # stopped mid-episode: not a result
                self.telemetry.event("episode_cut", index=index, steps=steps)
                break
            await self._settle_last_step()
            returns = {str(c): r for c, r in sorted(self.decide.returns.items())}
            self.telemetry.episode(
                {
                    "index": index,
                    **{k: info[k] for k in ("agents", "obstacles", "seed") if k in info},
                    "steps": steps,
                    "returns": returns,
                    "score": sum(returns.values()) / len(returns) if returns else None,
                }
            )
            index += 1

    async def _await_fleet(self, cars: set[int]) -> bool:
        """Frames until exactly the episode's cars are in the fleet (joined, seen) and the
        vision has swept the whole image since the layout changed (its obstacle and water
        markers are read by the sweep, a tile per frame)."""
        deadline = time.monotonic() + self.config.join_timeout_s
        frames = 0
        while not self.stop.is_set() and time.monotonic() < deadline:
            frames += await self._next_scene() is not None
            if set(self.fleet.slot) == cars and frames > self.vision.sweep_frames:
                return True
        return False

    async def _settle_last_step(self) -> None:
        """Wait for the last moves to end, then credit their rewards from a fresh frame that
        shows every car."""
        deadline = time.monotonic_ns() + int(self.config.step_timeout_s * 1e9)
        while not self.stop.is_set() and time.monotonic_ns() < deadline:
            if all(self.link.move_finished(c) for c in self.fleet.slot):
                break
            await asyncio.sleep(0.002)
        self._not_before_ns = time.monotonic_ns()
        deadline += int(self.config.step_timeout_s * 1e9)
        while not self.stop.is_set() and time.monotonic_ns() < deadline:
            scene = await self._next_scene()
            if scene is not None and self._all_seen(scene):
                slots = dict(self.fleet.slot)
                cells = {c: self.last_cell[c] for c in slots}
                self.decide.settle(slots, cells, scene.cells)
                return
