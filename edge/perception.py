"""Perception — the camera and the vision — beside the control loop: compact Scenes out.

Two ways to run it behind one interface (:class:`Perception`):

- :class:`ProcessPerception` (the default): the camera source is opened, read and analysed in a
  process of its own (``python -m udan.edge.perception``, a fresh interpreter: the edge has an
  ONNX model and a frozen heap that forking would copy for nothing). Frames never leave it; it
  sends each frame's :class:`~udan.edge.vision.Scene` (about a kilobyte pickled) over a Unix
  ``SOCK_SEQPACKET`` socket pair, read by the edge's asyncio loop with ``add_reader``. In one
  process the vision thread and the event loop took turns at one interpreter lock, so the
  scene waited on the loop's Python and the loop on the vision's; in two processes they run on
  two cores at once.
- :class:`ThreadPerception`: the earlier design, a capture thread and a one-thread vision
  executor in the edge process (``udan-edge --perception thread``): for tests and platforms
  without subprocesses, and as the reference the benchmark compares against.

Both tell the loop that a frame is being analysed (:class:`FrameTaken`) before its scene comes,
so the control core can rehearse the step meanwhile; frames captured before a cut-off
(:meth:`Perception.skip_before`, the core's stale-frame rule) are not analysed. Only the newest
scene matters: one the loop has not taken when the next arrives is dropped and counted, like a
frame overwritten before the vision took it.

The perception process runs in a process group of its own (a Ctrl-C on the terminal is not its
to handle) and ignores SIGINT and SIGTERM: the edge stops it after the cars' emergency stop, and it
ends by itself when the edge's end of the socket closes, however the edge ended. If it dies
mid-run, the edge's next wait for a scene raises :class:`PerceptionError` and the run ends with
an emergency stop.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import pickle
import socket
import subprocess
import sys
import threading
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Any

from udan.edge.calibration import VisionError
from udan.edge.camera import (
    CameraError,
    CameraMode,
    CameraSource,
    Frame,
    FrameGrabber,
    FrameWriter,
    open_camera,
    yield_process_to_dispatch,
    yield_to_dispatch,
)
from udan.edge.geometry import ArenaGeometry
from udan.edge.overlay import NO_OVERLAY, Annotator, OverlaySettings
from udan.edge.pauses import freeze_garbage, run_process_realtime, scheduler
from udan.edge.sidecar import (
    MESSAGE_BYTES,
    STOP_TIMEOUT_S,
    exit_of,
    ignore_interrupts,
    reap,
    spawn,
)
from udan.edge.vision import Scene, Vision

START_TIMEOUT_S = 30.0
"""Longest the edge waits for the perception process to open its camera (a cold start imports
OpenCV and numpy from disk)."""
_ERRORS = {"camera": CameraError, "vision": VisionError}


class PerceptionError(RuntimeError):
    """The perception process ended or broke off mid-run; the message is one line."""


class PerceptionDied(PerceptionError):
    """The perception process's socket closed mid-run. How the process ended is looked up when
    the message is read, after the cars' emergency stop: a killed process closes its files a
    moment before its exit status is there, and the loop must not wait for it."""

    def __init__(self, proc: subprocess.Popen) -> None:
        super().__init__()
        self.proc = proc

    def __str__(self) -> str:
        return f"the perception process ended mid-run ({exit_of(self.proc)})"


@dataclass(frozen=True)
class FrameTaken:
    """The vision has started to analyse this frame; its scene follows."""

    index: int
    t_capture_ns: int


@dataclass(frozen=True)
class VisionSettings:
    """What a :class:`~udan.edge.vision.Vision` is built from, sent to the perception process."""

    geometry: ArenaGeometry = field(default_factory=ArenaGeometry)
    car_markers: tuple[int, ...] | None = None
    calibration_file: str | None = None
    marker_heights: dict[int, float] = field(default_factory=dict)
    """Height of each car marker above the floor (metres), from the fleet file."""

    def build(self) -> Vision:
        return Vision(
            self.geometry,
            car_markers=self.car_markers,
            calibration_file=self.calibration_file,
            marker_heights=self.marker_heights,
        )

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> VisionSettings:
        fields = json.loads(text)
        markers = fields["car_markers"]
        return cls(
            ArenaGeometry(**fields["geometry"]),
            None if markers is None else tuple(markers),
            fields["calibration_file"],
            {int(marker): height for marker, height in fields["marker_heights"].items()},
        )


REMEMBERED_BYTES = 40 << 20
"""Analysed frames the perception remembers (by reference, no copy) for the flight recorder,
in bytes: 16 frames of 1920x1200 (0.4 s at 40 FPS), 4 of 4K; a decision's frame is asked for
within a few tens of milliseconds."""
REMEMBERED_MIN, REMEMBERED_MAX = 4, 16
DECIDED_SLOTS = 8
"""Decided frames the shared memory holds for the recorder (1.6 s of 5 decisions a second)."""
PREVIEW_SLOTS = 4


@dataclass(frozen=True)
class RingSpec:
    """Where the perception puts frames for the flight recorder, and how many besides the
    decided ones (a second)."""

    name: str
    rate: float = 0.0

    @property
    def decided(self) -> str:
        """Shared memory of the frames decisions used."""
        return f"{self.name}-decided"

    @property
    def previews(self) -> str:
        """Shared memory of the other frames, ``rate`` a second."""
        return f"{self.name}-preview"


class FrameRing:
    """The analysed frames, for the flight recorder (:mod:`udan.edge.recorder`). The last few
    are remembered by reference, so this costs no copy: a frame of its own nothing writes to
    any more, a lent one (the virtual camera's slot, :attr:`Frame.lease`) until the camera
    reuses the slot. The frame a decision used is copied into the shared memory
    :attr:`RingSpec.decided` when the edge says so (:meth:`keep`, a few times a second), and one
    frame every ``1 / rate`` s into :attr:`RingSpec.previews` as it is analysed: a few copies a
    second, not one a frame; a lent image is first copied out of its slot and kept only if the
    slot still held it after the copy (:meth:`Frame.owned`), so the camera can never overwrite
    a recorded frame. Made at the first frame, at that frame's size (a frame of another size is
    not kept); removed on close. :meth:`keep` comes from the perception process's control
    thread, :meth:`analysed` from its main thread: a lock keeps them apart."""

    def __init__(self, spec: RingSpec) -> None:
        self.spec = spec
        self.missed = 0
        """Frames asked for that were no longer remembered (or whose lent slot was reused)."""
        self._lock = threading.Lock()
        self._frames: deque[Frame] = deque(maxlen=REMEMBERED_MIN)
        self._decided: FrameWriter | None = None
        self._previews: FrameWriter | None = None
        self._kept = 0
        self._previewed = 0
        self._preview_due_ns = 0
        self._period_ns = round(1e9 / spec.rate) if spec.rate > 0 else 0

    def analysed(self, frame: Frame) -> None:
        """A frame the vision is done with: :meth:`remember` it, then :meth:`preview` it."""
        if self.remember(frame):
            self.preview(frame)

    def remember(self, frame: Frame) -> bool:
        """Remember a frame the vision is done with, before its scene leaves: the edge may ask
        to :meth:`keep` it as soon as it has the scene (in the perception process the ask is
        read by another thread). False for a frame of another size than the first."""
        image = frame.image
        with self._lock:
            if self._decided is None:
                height, width = image.shape
                remembered = REMEMBERED_BYTES // max(1, width * height)
                self._frames = deque(maxlen=max(REMEMBERED_MIN, min(REMEMBERED_MAX, remembered)))
                self._decided = FrameWriter(self.spec.decided, width, height, DECIDED_SLOTS)
                self._previews = FrameWriter(self.spec.previews, width, height, PREVIEW_SLOTS)
            layout = self._decided.layout
            if image.shape != (layout.height, layout.width):
                return False
            self._frames.append(frame)
            return True

    def preview(self, frame: Frame) -> None:
        """Copy a remembered frame for the previews when one is due."""
        if not self._period_ns or frame.t_capture_ns < self._preview_due_ns:
            return
        owned = frame.owned()
        if owned is not None and self._previews is not None:
            self._preview_due_ns = max(self._preview_due_ns + self._period_ns, frame.t_capture_ns)
            self._previewed += 1
            self._previews.publish(self._previewed, frame.t_capture_ns, owned.image)

    def keep(self, t_capture_ns: int) -> bool:
        """Copy the frame captured at ``t_capture_ns`` (a decision used it) for the recorder;
        False if it is no longer remembered."""
        with self._lock:
            frame = next((f for f in self._frames if f.t_capture_ns == t_capture_ns), None)
        owned = None if frame is None else frame.owned()
        if owned is None or self._decided is None:
            self.missed += 1
            return False
        self._kept += 1
        self._decided.publish(self._kept, t_capture_ns, owned.image)
        return True

    def close(self) -> None:
        for writer in (self._decided, self._previews):
            if writer is not None:
                writer.close()


def ring_counts(ring: FrameRing | None) -> dict[str, int]:
    """The flight recorder's frames the perception no longer remembered when asked."""
    return {} if ring is None else {"not_remembered": ring.missed}


def camera_facts(source: CameraSource) -> dict[str, Any]:
    """What the edge reports of an opened camera: its URL, the options asked, the granted
    mode and how it differs from the asked one."""
    mode: CameraMode | None = source.mode
    return {
        "url": source.url,
        "asked": source.options.given,
        "mode": None if mode is None else asdict(mode),
        "warnings": list(source.warnings),
    }


class Perception(ABC):
    """Frames to scenes beside the event loop; see the module docstring."""

    sweep_frames: int
    """Frames one sweep of the whole image takes (:attr:`udan.edge.vision.Vision.sweep_frames`)."""
    overlay: OverlaySettings = NO_OVERLAY
    """What is drawn onto the frames (:mod:`udan.edge.overlay`): the annotated video, the
    live page's thumbnails; nothing by default."""
    video: dict[str, int] | None = None
    """Once closed, what the annotated video got: frames written, frames skipped."""

    @property
    @abstractmethod
    def thumbnail(self) -> bytes | None:
        """The newest camera thumbnail with the detections drawn (JPEG), when asked for."""

    @abstractmethod
    def annotate(self, overlay: dict[str, Any]) -> None:
        """The last step (:func:`udan.edge.overlay.overlay_of`), to be drawn on the frames."""

    @property
    @abstractmethod
    def captured(self) -> int:
        """Frames read from the camera."""

    @property
    @abstractmethod
    def dropped(self) -> int:
        """Frames whose scene the loop never got: overwritten before the vision took them, or
        analysed but superseded before the loop took the scene."""

    @property
    @abstractmethod
    def ended(self) -> bool:
        """The stream has ended and every scene of it has been taken."""

    @property
    @abstractmethod
    def counters(self) -> dict[str, int]:
        """Frames captured and dropped, what the camera source skipped (stale frames,
        incomplete GenICam buffers), and decided frames the flight recorder asked for too late
        (``not_remembered``)."""

    @property
    @abstractmethod
    def camera_info(self) -> dict[str, Any]:
        """The camera as opened (:func:`camera_facts`); empty until :meth:`wait_ready`."""

    @property
    @abstractmethod
    def scheduler(self) -> str:
        """The scheduling policy the vision runs under ("SCHED_RR" or "SCHED_OTHER")."""

    @abstractmethod
    def take_news(self) -> list[tuple[str, dict[str, Any]]]:
        """What happened to the camera since the last call ("camera_lost", "camera_back")."""

    @abstractmethod
    def keep_frame(self, t_capture_ns: int) -> None:
        """A decision used the frame captured at ``t_capture_ns``: copy it for the flight
        recorder (:class:`FrameRing`; nothing without one). Never waits."""

    @abstractmethod
    def wait_ready(self) -> None:
        """Until the camera is open and the vision built; raises their errors
        (:class:`~udan.edge.camera.CameraError`, :class:`~udan.edge.calibration.VisionError`,
        one line each)."""

    @abstractmethod
    def start(self) -> None:
        """Start capturing (later calls do nothing)."""

    @abstractmethod
    def skip_before(self, t_ns: int) -> None:
        """Frames captured before ``t_ns`` are stale: do not analyse them."""

    @abstractmethod
    async def next_event(self, timeout: float) -> FrameTaken | Scene | None:
        """The next news, waiting up to ``timeout`` seconds: a frame taken for analysis, or the
        newest scene not yet returned; None on timeout or at the end of the stream. Raises the
        camera's or the vision's error, or :class:`PerceptionError`."""

    @abstractmethod
    def close(self) -> None:
        """Stop capturing and release the camera."""


# -- in the edge process ------------------------------------------------------------------
class ThreadPerception(Perception):
    """Capture in a thread (:class:`~udan.edge.camera.FrameGrabber`) and vision in a one-thread
    executor, both in the edge process and under its interpreter lock."""

    def __init__(
        self,
        grabber: FrameGrabber,
        vision: Vision,
        ring: FrameRing | None = None,
        overlay: OverlaySettings = NO_OVERLAY,
    ) -> None:
        self.grabber = grabber
        self.vision = vision
        self.ring = ring
        self.overlay = overlay
        self._annotator = Annotator(overlay, vision) if overlay.wanted else None
        self.sweep_frames = vision.sweep_frames
        self._pool = ThreadPoolExecutor(
            1, thread_name_prefix="vision", initializer=yield_to_dispatch
        )
        self._analysing: asyncio.Future[Scene] | None = None
        self._not_before_ns = 0

    @property
    def captured(self) -> int:
        return self.grabber.captured

    @property
    def dropped(self) -> int:
        return self.grabber.dropped

    @property
    def counters(self) -> dict[str, int]:
        return {**self.grabber.counters(), **ring_counts(self.ring)}

    @property
    def camera_info(self) -> dict[str, Any]:
        return camera_facts(self.grabber.source)

    @property
    def scheduler(self) -> str:
        return "SCHED_OTHER"  # threads of a real-time loop start ordinary

    def take_news(self) -> list[tuple[str, dict[str, Any]]]:
        return self.grabber.take_news()

    @property
    def ended(self) -> bool:
        return self._analysing is None and self.grabber.ended

    @property
    def thumbnail(self) -> bytes | None:
        return None if self._annotator is None else self._annotator.thumbnail

    def annotate(self, overlay: dict[str, Any]) -> None:
        if self._annotator is not None:
            self._annotator.step(overlay)

    def _analyse(self, frame: Frame) -> Scene:
        """The scene and the frame's survey: after it, the survey would hold the interpreter
        lock the loop needs to take the scene."""
        scene = self.vision.process(frame)
        self.vision.survey()
        if self._annotator is not None:
            self._annotator.frame(frame, scene)
        if self.ring is not None:
            self.ring.analysed(frame)
        return scene

    def keep_frame(self, t_capture_ns: int) -> None:
        if self.ring is not None:  # in the vision's thread: the loop touches no pixel
            self._pool.submit(self.ring.keep, t_capture_ns)

    def wait_ready(self) -> None:
        """Nothing to wait for: the camera was opened and the vision built by the caller."""

    def start(self) -> None:
        self.grabber.start()

    def skip_before(self, t_ns: int) -> None:
        self._not_before_ns = t_ns

    async def next_event(self, timeout: float) -> FrameTaken | Scene | None:
        if self._analysing is not None:
            analysing, self._analysing = self._analysing, None
            return await analysing
        while (frame := await self.grabber.next_frame(timeout)) is not None:
            if frame.t_capture_ns >= self._not_before_ns:
                loop = asyncio.get_running_loop()
                self._analysing = loop.run_in_executor(self._pool, self._analyse, frame)
                return FrameTaken(frame.index, frame.t_capture_ns)
        return None

    def close(self) -> None:
        self.grabber.close()
        self._pool.shutdown(wait=True)
        if self.ring is not None:
            self.ring.close()
        if self._annotator is not None:
            self.video = self._annotator.close()


# -- in a process of its own ----------------------------------------------------------------
class ProcessPerception(Perception):
    """The camera and the vision in a perception process of their own."""

    def __init__(
        self,
        camera: str,
        settings: VisionSettings = VisionSettings(),
        ring: RingSpec | None = None,
        overlay: OverlaySettings = NO_OVERLAY,
        realtime: bool = False,
    ) -> None:
        """Start the perception process (it opens ``camera`` and builds its vision while the
        caller goes on; :meth:`wait_ready` waits for that); with ``ring``, it keeps the frames
        it analysed there for the flight recorder (:class:`FrameRing`); ``realtime``: it runs
        ``SCHED_RR`` below the loop (:data:`~udan.edge.pauses.PERCEPTION_PRIORITY`)."""
        self.camera = camera
        self.overlay = overlay
        self.sweep_frames = 0
        self._scheduler = "SCHED_OTHER"
        self._camera_info: dict[str, Any] = {}
        self._counts: dict[str, int] = {"captured": 0, "dropped": 0}
        self._news: list[tuple[str, dict[str, Any]]] = []
        self._thumbnail: bytes | None = None
        self._superseded = 0  # scenes superseded here before the loop took them
        self._scene: Scene | None = None
        self._taken: FrameTaken | None = None
        self._error: Exception | None = None
        self._stream_ended = False
        self._wake: asyncio.Event | None = None
        self._reading: asyncio.AbstractEventLoop | None = None
        self._not_before_ns = 0
        self._buffer = bytearray(MESSAGE_BYTES)
        self._ring = ring
        args = ["--camera", camera, "--vision", settings.to_json()]
        if ring is not None:
            args += ["--ring", ring.name, "--ring-rate", str(ring.rate)]
        if overlay.wanted:
            args += ["--overlay", overlay.to_json()]
        if realtime:
            args.append("--realtime")
        self._sock, self._proc = spawn("udan.edge.perception", args)

    def wait_ready(self) -> None:
        if self.sweep_frames:
            return
        self._sock.settimeout(START_TIMEOUT_S)
        try:
            first = self._sock.recv(MESSAGE_BYTES)
        except TimeoutError:
            raise PerceptionError(
                f"the perception process did not open {self.camera} within {START_TIMEOUT_S:g} s"
            ) from None
        if not first:
            self._stream_ended = True
            raise PerceptionError(
                f"the perception process ended while starting ({exit_of(self._proc)})"
            )
        kind, *body = pickle.loads(first)
        if kind == "error":
            self._stream_ended = True
            raise _ERRORS.get(body[0], PerceptionError)(body[1])
        self._sock.setblocking(False)
        self.sweep_frames, self._camera_info, self._scheduler = int(body[0]), body[1], body[2]

    @property
    def pid(self) -> int:
        return self._proc.pid

    @property
    def captured(self) -> int:
        return self._counts["captured"]

    @property
    def dropped(self) -> int:
        return self._counts["dropped"] + self._superseded

    @property
    def counters(self) -> dict[str, int]:
        return {**self._counts, "dropped": self.dropped}

    @property
    def camera_info(self) -> dict[str, Any]:
        return self._camera_info

    @property
    def scheduler(self) -> str:
        return self._scheduler

    def take_news(self) -> list[tuple[str, dict[str, Any]]]:
        news, self._news = self._news, []
        return news

    def keep_frame(self, t_capture_ns: int) -> None:
        if self._ring is not None and not self._stream_ended:
            self._send(("keep", t_capture_ns))

    @property
    def ended(self) -> bool:
        return self._stream_ended and self._scene is None

    @property
    def thumbnail(self) -> bytes | None:
        return self._thumbnail

    def annotate(self, overlay: dict[str, Any]) -> None:
        if self.overlay.wanted and not self._stream_ended:
            self._send(("step", overlay))

    def start(self) -> None:
        self.wait_ready()
        if self._reading is None:
            self._reading = asyncio.get_running_loop()
            self._wake = asyncio.Event()
            self._reading.add_reader(self._sock.fileno(), self._receive)
            self._send(("start",))

    def skip_before(self, t_ns: int) -> None:
        if t_ns != self._not_before_ns and not self._stream_ended:
            self._not_before_ns = t_ns
            self._send(("skip_before", t_ns))

    def _send(self, message: tuple) -> None:
        with contextlib.suppress(OSError):  # it has gone: the reader reports that
            self._sock.send(pickle.dumps(message))

    def _receive(self) -> None:
        """Everything the perception process has sent since the last call (a loop callback)."""
        while not self._stream_ended:
            try:
                size = self._sock.recv_into(self._buffer)
            except BlockingIOError:
                break
            except OSError as err:
                self._end(PerceptionError(f"the perception process's socket failed: {err}"))
                break
            if not size:
                self._end(PerceptionDied(self._proc))
                break
            self._take_message(pickle.loads(memoryview(self._buffer)[:size]))
        assert self._wake is not None
        self._wake.set()

    def _take_message(self, message: tuple) -> None:
        kind, *body = message
        if kind == "taken":
            self._taken = FrameTaken(body[0], body[1])
        elif kind == "scene":
            if self._scene is not None:
                self._superseded += 1
            self._scene = body[0].after(self._scene)
        elif kind == "thumbnail":
            self._thumbnail = body[0]
        elif kind == "video":
            self.video = body[0]
        elif kind == "error":
            self._end(_ERRORS.get(body[0], PerceptionError)(body[1]))
            return
        elif kind == "news":
            self._news.append((body[0], body[1]))
        elif kind == "end":
            self._end(None)
        self._counts = body[-1]

    def _end(self, error: Exception | None) -> None:
        self._stream_ended = True
        self._error = error
        if self._reading is not None:
            self._reading.remove_reader(self._sock.fileno())

    def _next(self) -> FrameTaken | Scene | None:
        """The newest scene if one is waiting, else the frame being analysed if not yet told;
        at the end, None or the error that ended it."""
        scene, taken = self._scene, self._taken
        if scene is not None:
            self._scene = None
            if taken is not None and taken.index <= scene.frame_index:
                self._taken = None
            return scene
        if taken is not None:
            self._taken = None
            return taken
        if self._stream_ended and self._error is not None:
            raise self._error
        return None

    async def next_event(self, timeout: float) -> FrameTaken | Scene | None:
        self.start()
        assert self._wake is not None and self._reading is not None
        deadline = self._reading.time() + timeout
        while (event := self._next()) is None and not self._stream_ended:
            self._wake.clear()
            try:
                await asyncio.wait_for(self._wake.wait(), deadline - self._reading.time())
            except TimeoutError:
                return self._next()
        return event

    def close(self) -> None:
        """Tell the perception process to stop, take its last counts, and wait for it; one
        still starting (nothing opened that its exit would not release) is killed."""
        if self._reading is not None and not self._stream_ended:
            self._reading.remove_reader(self._sock.fileno())
        if not self.sweep_frames and not self._stream_ended:
            self._proc.kill()
        elif not self._stream_ended:
            self._send(("stop",))
            self._sock.setblocking(True)
            self._sock.settimeout(STOP_TIMEOUT_S)
            with contextlib.suppress(OSError, EOFError, pickle.UnpicklingError):
                while data := self._sock.recv(MESSAGE_BYTES):
                    kind, *body = pickle.loads(data)
                    if kind in ("taken", "scene", "news", "thumbnail", "end"):
                        self._counts = body[-1]
                    if kind == "video":
                        self.video = body[0]
            self._stream_ended = True
        self._sock.close()
        reap(self._proc)


# -- the perception process itself ---------------------------------------------------------
class _Server:
    """The perception process's loop: newest frame, scene, send; control messages are read by
    a thread of their own.

    The main thread waits for the capture thread's frame on a condition variable and analyses
    it there and then: no event loop between the frame's arrival and its analysis (an asyncio
    hand-over cost ~0.3 ms a frame). The frame's image is lent by a source that can (the
    virtual camera's shared slot, no copy), and a scene counts only if the image was still the
    frame's after the analysis; otherwise it is dropped and counted.

    The frame's survey (:meth:`~udan.edge.vision.Vision.survey`, half the vision's time) runs
    after its scene is sent when the process is real-time below the loop (the loop preempts it
    at once), and before otherwise: an ordinary one would compete with the loop and the cars
    for the cores while the step is decided and sent (docs/timing.md has both measured)."""

    POLL_S = 0.1
    """How often a frame wait wakes to look for a stop (a stop also wakes it at once)."""

    def __init__(
        self,
        sock: socket.socket,
        grabber: FrameGrabber,
        vision: Vision,
        ring: FrameRing | None = None,
        annotator: Annotator | None = None,
    ) -> None:
        self.sock = sock
        self.grabber = grabber
        self.vision = vision
        self.ring = ring
        self.annotator = annotator
        self._thumbnail: bytes | None = None  # the last one sent
        self.not_before_ns = 0
        self.unsent = 0
        """Scenes the edge's full socket had no room for (it is not reading: they are old)."""
        self.unsent_scene: Scene | None = None
        """The last of them, whose warnings go with the next scene sent."""
        self.overwritten = 0
        """Frames whose lent image the camera reused during their analysis (scene dropped)."""
        self.stopping = threading.Event()

    def send(self, *message: Any) -> bool:
        """A message with the counts so far, never waiting: a message the socket has no room
        for is dropped (a scene counted). Returns whether it was sent."""
        counts = {**self.grabber.counters(), **ring_counts(self.ring)}
        counts["dropped"] += self.unsent + self.overwritten
        try:
            self.sock.send(pickle.dumps((*message, counts)), socket.MSG_DONTWAIT)
        except BlockingIOError:
            self.unsent += message[0] == "scene"
            return False
        return True

    def send_scene(self, scene: Scene) -> None:
        """A scene (:meth:`send`); the warnings of one dropped go with the next."""
        scene = scene.after(self.unsent_scene)
        self.unsent_scene = None if self.send("scene", scene) else scene

    def control(self, data: bytes) -> None:
        """One message from the edge; an empty one (the edge has gone) is a stop."""
        kind, *body = pickle.loads(data) if data else ("stop",)
        if kind == "skip_before":
            self.not_before_ns = body[0]
        elif kind == "keep" and self.ring is not None:
            self.ring.keep(body[0])
        elif kind == "step" and self.annotator is not None:
            self.annotator.step(body[0])
        elif kind == "stop":
            self.stopping.set()
            self.grabber.stop()

    def _listen(self) -> None:
        """The control thread: the edge's messages until a stop."""
        while not self.stopping.is_set():
            try:
                data = self.sock.recv(MESSAGE_BYTES)
            except OSError:
                data = b""
            self.control(data)

    def serve(self) -> None:
        threading.Thread(target=self._listen, name="control", daemon=True).start()
        survey_after = scheduler() == "SCHED_RR"  # below the loop, which preempts it
        while not self.stopping.is_set():
            frame = self.grabber.wait_frame(self.POLL_S)
            for kind, fields in self.grabber.take_news():
                self.send("news", kind, fields)
            if frame is None and self.grabber.ended:
                break
            if frame is None or frame.t_capture_ns < self.not_before_ns:
                continue
            self.send("taken", frame.index, frame.t_capture_ns)
            scene = self.vision.process(frame)
            if not survey_after:
                self.vision.survey()
            if not frame.intact():
                self.overwritten += 1
                continue
            remembered = self.ring is not None and self.ring.remember(frame)
            self.send_scene(scene)
            if survey_after:
                self.vision.survey()
            if self.annotator is not None:
                self._annotate(frame, scene)
            if remembered:
                self.ring.preview(frame)

    def _annotate(self, frame: Frame, scene: Scene) -> None:
        """The frame to the annotator; its newest thumbnail to the edge if there is a new one
        (one too large for a message is not sent)."""
        assert self.annotator is not None
        self.annotator.frame(frame, scene)
        thumbnail = self.annotator.thumbnail
        if thumbnail is not self._thumbnail and len(thumbnail or b"") < MESSAGE_BYTES - 64:
            self._thumbnail = thumbnail
            self.send("thumbnail", thumbnail)


def _error_kind(err: Exception) -> str:
    return "camera" if isinstance(err, CameraError) else "vision"


def serve(
    fd: int,
    camera: str,
    settings: VisionSettings,
    ring: RingSpec | None = None,
    overlay: OverlaySettings = NO_OVERLAY,
    realtime: bool = False,
) -> int:
    """The perception process: open ``camera`` and build the vision, say "ready" with the
    camera's granted mode and the scheduling policy (or the error, one line), wait for
    "start", then send scenes until told to stop or the edge goes away; with ``ring``, keep
    frames for the flight recorder (:class:`FrameRing`); draw the steps onto the frames when
    ``overlay`` asks (the video is finished on the way out). ``realtime``: every thread
    ``SCHED_RR`` below the loop; else nicer than it."""
    ignore_interrupts()
    sock = socket.socket(fileno=fd)
    try:
        vision = settings.build()
        source = open_camera(camera)
    except (CameraError, VisionError) as err:
        sock.send(pickle.dumps(("error", _error_kind(err), str(err))))
        return 2
    source.lend = True  # the server checks each frame's image after its analysis
    grabber = FrameGrabber(source)
    frames = None if ring is None else FrameRing(ring)
    annotator = Annotator(overlay, vision) if overlay.wanted else None
    server = _Server(sock, grabber, vision, frames, annotator)
    try:
        freeze_garbage()
        if realtime:
            with contextlib.suppress(PermissionError):  # the report says SCHED_OTHER
                run_process_realtime()
        ready = ("ready", vision.sweep_frames, camera_facts(source), scheduler())
        sock.send(pickle.dumps(ready))
        while (data := sock.recv(MESSAGE_BYTES)) and pickle.loads(data)[0] != "start":
            server.control(data)
            if server.stopping.is_set():  # stopped before the run began
                return 0
        if not data:
            return 0
        if scheduler() != "SCHED_RR":  # ordinary (not asked, or refused): nicer than the loop
            yield_process_to_dispatch()
        grabber.start()
        server.serve()
        if annotator is not None:
            server.send("video", annotator.close())
            annotator = None
        server.send("end")
    except (CameraError, VisionError) as err:
        with contextlib.suppress(OSError):
            server.send("error", _error_kind(err), str(err))
        return 1
    except OSError:  # the edge has gone
        return 0
    finally:
        grabber.close()
        if frames is not None:
            frames.close()
        if annotator is not None:
            annotator.close()
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m udan.edge.perception --fd N --camera URL --vision JSON`` (started by the
    edge, not by hand)."""
    parser = argparse.ArgumentParser(prog="udan.edge.perception", description=__doc__)
    parser.add_argument("--fd", type=int, required=True)
    parser.add_argument("--camera", required=True)
    parser.add_argument("--vision", type=VisionSettings.from_json, default=VisionSettings())
    parser.add_argument("--ring", help="keep frames for the flight recorder under this name")
    parser.add_argument("--ring-rate", type=float, default=0.0)
    parser.add_argument("--overlay", type=OverlaySettings.from_json, default=NO_OVERLAY)
    parser.add_argument("--realtime", action="store_true")
    args = parser.parse_args(argv)
    ring = None if args.ring is None else RingSpec(args.ring, args.ring_rate)
    return serve(args.fd, args.camera, args.vision, ring, args.overlay, args.realtime)


if __name__ == "__main__":
    sys.exit(main())
