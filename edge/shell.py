"""The asyncio shell around the control core (:mod:`edge.core`): frames in, commands out.

The shell does the I/O and the timing tricks (rehearsal while a frame is analysed, garbage
collection between steps); the core decides what happens. One asyncio loop. Capture runs in its
own thread (:class:`edge.camera.FrameGrabber`, newest frame wins) and vision in a worker thread
(OpenCV releases the GIL), so the dispatcher's retransmission timers keep running while a frame
is analysed.

When a decision step happens is the core's rule (:class:`edge.core.ControlCore`). All commands
of a step leave at once, each valid until the decision + 10 ms.

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
from edge.core import ControlCore, StepTiming
from edge.fleet import FleetState
from edge.link import CarLink
from edge.pauses import collect_between_steps
from edge.telemetry import Telemetry
from edge.vision import Scene, Vision

ESTOP_GRACE_S = 0.05
#: With no step for this long, collect anyway.
COLLECT_IDLE_NS = 1_000_000_000


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
    def step_timing(self) -> StepTiming:
        """The core's part of it."""
        return StepTiming(int(self.step_timeout_s * 1e9), int(self.unseen_grace_s * 1e9))


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


class EdgeShell:
    """Wires camera, vision, link and telemetry around a :class:`ControlCore`; ``run`` is the
    whole job."""

    def __init__(
        self,
        grabber: FrameGrabber,
        vision: Vision,
        link: CarLink,
        core: ControlCore,
        telemetry: Telemetry,
        config: LoopConfig = LoopConfig(),
        world: tuple[str, int] | None = None,
    ) -> None:
        self.grabber = grabber
        self.vision = vision
        self.link = link
        self.core = core
        self.telemetry = telemetry
        self.config = config
        self.world = world
        self.stop = asyncio.Event()
        self._vision_pool = ThreadPoolExecutor(
            1, thread_name_prefix="vision", initializer=yield_to_dispatch
        )
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
            self.core.emergency_stop()
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
        """The next frame's scene (one the core does not find stale), with the fleet updated;
        None on a stall, the end of the stream, or a stop."""
        while not self.stop.is_set():
            frame = await self._wait_frame()
            if frame is None:
                return None
            if not self.core.wants(frame.t_capture_ns):
                continue
            loop = asyncio.get_running_loop()
            analysed = loop.run_in_executor(self._vision_pool, self.vision.process, frame)
            self.core.warm_up(self.link.move_finished)  # this frame may be the deciding one
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
        """A scene into the core; telemetry of the frame and of the fleet's changes."""
        change = self.core.see(scene, self.link.ready_cars(), now)
        for car in change.joined:
            self.telemetry.event("fleet_join", car=car)
        for car in change.left:
            self.telemetry.event("fleet_leave", car=car)
        seen = sum(s.inside for s in scene.cars.values())
        self.telemetry.frame(frame.index, frame.t_capture_ns, now, seen, self.grabber.dropped)

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
        core, steps = self.core, 0
        core.wait_for_moves(time.monotonic_ns())
        while not self.stop.is_set() and (max_steps is None or steps < max_steps):
            scene = await self._next_scene()
            if time.monotonic_ns() - self._collected_ns > COLLECT_IDLE_NS:
                self._collect()  # no step for a while (a stall, an empty arena)
            if scene is None:
                continue
            now = time.monotonic_ns()
            state = core.due(scene, self.link.move_finished, now)
            if state is None:
                continue
            await self._step(state, now)
            self._collect()
            steps += 1
            core.wait_for_moves(time.monotonic_ns())
        return steps

    async def _step(self, state: FleetState, state_ns: int) -> None:
        """One decision and its dispatch, with the step's telemetry."""
        decision, commands, decided_ns = self.core.decide(state, state_ns)
        report = await self.link.dispatch(commands, decided_ns)
        self.telemetry.step(self.core.dispatched(state, decision, commands, report, state_ns))

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
            self.core.new_episode(time.monotonic_ns())
            cars = set(info["cars"])
            if not await self._await_fleet(cars):
                self.telemetry.event("episode_skipped", index=index, cars=sorted(cars))
                index += 1
                continue
            steps = await self._drive(self.config.episode_steps)
            if steps < self.config.episode_steps:  # stopped mid-episode: not a result
                self.telemetry.event("episode_cut", index=index, steps=steps)
                break
            await self._credit_last_step()
            returns = {str(c): r for c, r in sorted(self.core.policy_step.returns.items())}
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
            if set(self.core.fleet.slot) == cars and frames > self.vision.sweep_frames:
                return True
        return False

    async def _credit_last_step(self) -> None:
        """Wait for the last moves to end, then credit their rewards from a fresh frame that
        shows every car."""
        deadline = time.monotonic_ns() + int(self.config.step_timeout_s * 1e9)
        while not self.stop.is_set() and time.monotonic_ns() < deadline:
            if all(self.link.move_finished(c) for c in self.core.fleet.slot):
                break
            await asyncio.sleep(0.002)
        self.core.not_before_ns = time.monotonic_ns()
        deadline += int(self.config.step_timeout_s * 1e9)
        while not self.stop.is_set() and time.monotonic_ns() < deadline:
            scene = await self._next_scene()
            if scene is not None and self.core.credit_last_step(scene) is not None:
                return
