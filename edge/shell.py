"""The asyncio shell around the control core (:mod:`udan.edge.core`): frames in, commands out.

The shell does the I/O and the timing tricks (rehearsal while a frame is analysed, garbage
collection between steps); the core decides what happens. One asyncio loop. Capture runs in its
own process by default (:class:`udan.edge.perception.ProcessPerception`: the camera and the vision
there, compact scenes over a socket read by the loop), so the dispatcher's retransmission timers
and the scene never wait for each other's turn at the interpreter lock.

When a decision step happens is the core's rule (:class:`udan.edge.core.ControlCore`), and so
is when cars off their cells' centres are re-centred first (a :class:`udan.edge.core.Recentring`
round, dispatched like a step). All commands of a step leave at once, each valid until the
decision + 10 ms.

Whatever ends the run — its duration, Ctrl-C, SIGTERM, the end of a video, or an exception — the
``finally`` sends an emergency stop to every joined car before anything is closed.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import signal
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, Protocol

from udan.edge.core import ControlCore, Recentring, StepTiming
from udan.edge.fleet import FleetState
from udan.edge.link import CarLink
from udan.edge.live import LiveView
from udan.edge.overlay import overlay_of
from udan.edge.pauses import collect_between_steps
from udan.edge.perception import FrameTaken, Perception
from udan.edge.telemetry import Telemetry
from udan.edge.vision import Scene

log = logging.getLogger(__name__)

ESTOP_GRACE_S = 0.05
#: With no step for this long, collect anyway.
COLLECT_IDLE_NS = 1_000_000_000


@dataclass(frozen=True)
class LoopConfig:
    """Timing of the main loop."""

    step_timeout_s: float = 1.0
    """Longest a step waits for moves to finish before deciding anyway."""
    stall_s: float = 0.5
    """No frame for this long is a camera stall (counted; cars stop by their watchdog)."""
    duration_s: float | None = None
    """Stop after this long (None: until a signal, or the episodes are done)."""
    unseen_grace_s: float = 0.1
    """Longest a step waits for a car the camera missed (then it is stopped for the step)."""

    @property
    def step_timing(self) -> StepTiming:
        """The core's part of it."""
        return StepTiming(int(self.step_timeout_s * 1e9), int(self.unseen_grace_s * 1e9))


#: With no step for this many kept records (a stalled camera, an empty arena: ~3 s of frames),
#: the flight recorder sends them anyway.
FLUSH_PENDING = 400


class Flushable(Protocol):
    """What keeps records inside a step and sends them between steps (the flight recorder)."""

    def flush(self, more_than: int = 0) -> None: ...


class EdgeShell:
    """Wires perception, link and telemetry around a :class:`ControlCore`; ``run`` is the whole
    job."""

    def __init__(
        self,
        perception: Perception,
        link: CarLink,
        core: ControlCore,
        telemetry: Telemetry,
        config: LoopConfig = LoopConfig(),
        live: LiveView | None = None,
        recorder: Flushable | None = None,
    ) -> None:
        self.perception = perception
        self.link = link
        self.core = core
        self.telemetry = telemetry
        self.config = config
        self.live = live
        self.recorder = recorder
        self.stop = asyncio.Event()
        self._captured_ns: int | None = None  # capture time of the newest scene folded in
        self._collections = 0
        self._longest_collection_ns = 0
        self._collected_ns = time.monotonic_ns()

    # ------------------------------------------------------------------ the job
    async def run(
        self, play: Callable[[EdgeShell], Awaitable[object]] | None = None
    ) -> dict[str, Any]:
        """Drive until the duration, a signal, the end of the camera or of ``play`` (which
        drives the shell its own way: :class:`udan.edge.episodes.EpisodePlayer`); emergency-stop
        every car on the way out, whatever happened; return the report. The link is started
        (and closed) by the caller, so a car can be told the edge's address before the run."""
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, self.stop.set)
        if self.config.duration_s is not None:
            loop.call_later(self.config.duration_s, self.stop.set)
        gc.disable()  # collections run between steps (_collect), never inside one
        try:
            self.perception.start()
            if self.live is not None:
                self.live.start(self._stop_from_page)
            if play is None:
                await self.drive(max_steps=None)
            else:
                await play(self)
        finally:
            gc.enable()
            self.core.emergency_stop()
            sent = self.link.estop_all()
            self.telemetry.event("estop", cars=sent)
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.remove_signal_handler(sig)
            await asyncio.sleep(ESTOP_GRACE_S)  # the link repeats the estop in this time
            self.perception.close()
            self._camera_news()
            if self.recorder is not None:
                self.recorder.flush()
            self._publish(final=True)  # the page shows how the run ended
        report = self.telemetry.report()
        report["final"] = self.telemetry.final_line()
        report["link"] = self.link.counters()
        perception = self.perception
        report["camera"] = {**perception.counters, **perception.camera_info}
        report["perception_scheduler"] = perception.scheduler
        if perception.video is not None:
            report["camera"]["video"] = perception.video
        report["gc"] = {
            "collections": self._collections,
            "longest_ms": round(self._longest_collection_ns / 1e6, 3),
        }
        return report

    # ------------------------------------------------------------------ frames
    async def next_scene(self) -> Scene | None:
        """The next frame's scene (one the core does not find stale), with the fleet updated;
        None on a stall, the end of the stream, or a stop. While a frame that may decide the
        step is analysed, the core rehearses the step."""
        while not self.stop.is_set():
            self.perception.skip_before(self.core.not_before_ns)
            self._publish()
            event = await self._wait_event()
            if event is None:
                return None
            if not self.core.wants(event.t_capture_ns):
                continue
            if isinstance(event, FrameTaken):
                self.core.warm_up(self.link.move_finished)  # this frame may be the deciding one
                continue
            self._fold(event, time.monotonic_ns())
            return event
        return None

    def _camera_news(self) -> None:
        """The camera's news into telemetry: lost (with the reason; no scene comes, so no step
        is decided and the cars stop after their move) and back."""
        for kind, fields in self.perception.take_news():
            self.telemetry.event(kind, **fields)

    async def _wait_event(self) -> FrameTaken | Scene | None:
        """The next news from the perception. Before waiting (the loop is idle until then),
        the camera's news go to telemetry, and again after: news told before a frame may come
        in one read with that frame's scene, and go to telemetry before its step. The flight
        recorder sends what it kept only if no step has sent it for a long while (it sends
        after each step)."""
        self._camera_news()
        if self.recorder is not None:
            self.recorder.flush(FLUSH_PENDING)  # after each step, or when they pile up
        perception = self.perception
        stopping = asyncio.ensure_future(self.stop.wait())
        waiting = asyncio.ensure_future(perception.next_event(self.config.stall_s))
        done, _ = await asyncio.wait({stopping, waiting}, return_when=asyncio.FIRST_COMPLETED)
        stopping.cancel()
        if waiting not in done:
            waiting.cancel()
            return None
        event = waiting.result()
        self._camera_news()
        if event is None and not perception.ended:
            self.telemetry.event("camera_stall", stall_s=self.config.stall_s)
        elif event is None:
            self.stop.set()
        return event

    def _fold(self, scene: Scene, now: int) -> None:
        """A scene into the core; telemetry of the frame, of the fleet's changes and of the
        vision's warnings (each also one line on stderr)."""
        self._captured_ns = scene.t_capture_ns
        for warning in scene.warnings:
            log.warning("vision: %s", warning)
            self.telemetry.event("vision_warning", message=warning)
        change = self.core.see(scene, self.link.ready_cars(), now)
        for car in change.joined:
            self.telemetry.event("fleet_join", car=car)
        for car in change.left:
            self.telemetry.event("fleet_leave", car=car)
        seen = sum(s.inside for s in scene.cars.values())
        uncertain = sum(s.inside and s.uncertain for s in scene.cars.values())
        dropped = self.perception.dropped
        self.telemetry.frame(
            scene.frame_index,
            scene.t_capture_ns,
            now,
            seen,
            dropped,
            uncertain,
            scene.vision_ns,
            scene.t_arrival_ns,
        )

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

    async def drive(self, max_steps: int | None) -> int:
        """Decide and dispatch step after step; returns the number of steps made."""
        core, steps = self.core, 0
        core.wait_for_moves(time.monotonic_ns())
        while not self.stop.is_set() and (max_steps is None or steps < max_steps):
            scene = await self.next_scene()
            if time.monotonic_ns() - self._collected_ns > COLLECT_IDLE_NS:
                self._collect()  # no step for a while (a stall, an empty arena)
            if scene is None:
                continue
            now = time.monotonic_ns()
            due = core.due(scene, self.link.move_finished, now)
            if due is None:
                stops = core.guard(scene, self.link.move_finished)
                if stops:  # a body about to touch another: stopped where it is
                    report = await self.link.dispatch(stops, time.monotonic_ns())
                    self.telemetry.event("guard_stop", cars=list(stops), on_time=report.on_time)
                    continue
                # the next frame may decide; its "taken" news comes in time to rehearse on only
                # when this loop wakes within the frame's analysis, so rehearse now as well
                core.warm_up(self.link.move_finished)
                continue
            if isinstance(due, Recentring):
                await self._recentre(due)
            else:
                await self._step(due, now)
                self._collect()
                steps += 1
            core.wait_for_moves(time.monotonic_ns())
        return steps

    async def _recentre(self, recentring: Recentring) -> None:
        """A re-centring round: its commands, dispatched like a step's, with their record."""
        decided_ns = time.monotonic_ns()
        commands, guidance = recentring.commands, recentring.guidance
        report = await self.link.dispatch(commands, decided_ns, guidance=guidance)
        self.telemetry.recentre(self.core.recentred(recentring, report))

    async def _step(self, state: FleetState, state_ns: int) -> None:
        """One decision and its dispatch, with the step's telemetry."""
        decision, commands, decided_ns = self.core.commands_for(state, state_ns)
        report = await self.link.dispatch(
            commands, decided_ns, guidance=decision.guidance, after=decision.after
        )
        record = self.core.dispatched(state, decision, commands, report, state_ns)
        self.telemetry.step(record)
        if self.live is not None:
            self.live.step(record)
        if self.perception.overlay.wanted:  # drawn onto the frames, where they are
            counts = self.telemetry.counts
            sent = counts["on_time"] + counts["missed"]
            share = counts["on_time"] / sent if sent else None
            self.perception.annotate(overlay_of(record, counts["steps"], share))
        if self.recorder is not None:
            # the frame the step used, and what the recorder was given since the last step:
            # sent now, when the cars take a move before the next decision, not between a
            # frame's rehearsal and its decision (pickling them would cool the caches the
            # rehearsal warmed)
            self.perception.keep_frame(state.t_capture_ns)
            self.recorder.flush()

    # ------------------------------------------------------------------ the live view
    def _publish(self, *, final: bool = False) -> None:
        """A snapshot for the live view when one is due; called where the loop is about to
        wait for the camera anyway (``final``: at the end of the run, due or not)."""
        live, now = self.live, time.monotonic_ns()
        if live is None or not (live.due(now) or final):
            return
        core, counts, camera = self.core, self.telemetry, self.perception
        live.publish(
            {
                "t_ns": now,
                "step": live.last_step,
                "static": {kind: sorted(cells) for kind, cells in (core.static or {}).items()},
                "fleet": sorted(core.fleet.slot),
                "joined": sorted(self.link.ready_cars()),
                "totals": counts.totals(),
                "link": self.link.counters(),
                "camera": camera.counters,
                "frame_age_ns": None if self._captured_ns is None else now - self._captured_ns,
                "stopped": core.stopped,
            },
            camera.thumbnail,
        )

    def _stop_from_page(self) -> int:
        """The page's stop-all button: no further step, and an emergency stop to every car
        through the link (authenticated per car, like any command), counted."""
        self.core.emergency_stop()
        sent = self.link.estop_all()
        self.telemetry.event("remote_estop", cars=sent)
        return sent
