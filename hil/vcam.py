"""The virtual camera's writer: rendered frames into shared memory, read as `virtual://NAME`.

Frames go through shared memory rather than a socket because a 1920x1200 frame is 2.3 MB and 40
of them a second must not cost the renderer's process a copy per reader or a syscall per
kilobyte; the layout and its seqlock are defined once, in `udan.edge.camera.VcamLayout`.

Camera faults are injected here, where a real camera would have them: a frame dropped at random
(its number is used up, so readers see the gap in `Frame.index`), and a stall during which no frame
is published at all. Recording goes through a thread with a short queue so that encoding (15 ms a
frame) never delays publication; frames it cannot keep up with are counted, not waited for.
"""

from __future__ import annotations

import os
import queue
import random
import threading
import time
from collections.abc import Callable
from functools import partial

import cv2
import numpy as np

from udan.edge.camera import FrameWriter


class _Recorder:
    """MP4 ('mp4v') of the published frames at half resolution, encoded in its own thread
    (a full-size encode costs about as much CPU as the renderer and the edge together)."""

    def __init__(self, path: str | os.PathLike, fps: float, width: int, height: int) -> None:
        fourcc = cv2.VideoWriter_fourcc(*"mp4v")
        self._size = (width // 2, height // 2)
        self._writer = cv2.VideoWriter(os.fspath(path), fourcc, fps, self._size, False)
        if not self._writer.isOpened():
            raise OSError(f"cannot record the virtual camera to {path}")
        self.skipped = 0
        self._queue: queue.Queue[np.ndarray | None] = queue.Queue(maxsize=8)
        self._thread = threading.Thread(target=self._run, name="vcam recorder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while (image := self._queue.get()) is not None:
            self._writer.write(image)
        self._writer.release()

    def add(self, image: np.ndarray) -> None:
        try:
            self._queue.put_nowait(cv2.resize(image, self._size, interpolation=cv2.INTER_AREA))
        except queue.Full:
            self.skipped += 1

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join()


class VirtualCamera:
    """Publishes frames in the shared memory `name`; `close()` removes it. `video` records what
    is published to an MP4; `fps` is the rate `run` publishes at and the video's."""

    def __init__(
        self,
        name: str,
        width: int = 1920,
        height: int = 1200,
        *,
        slots: int = 3,
        video: str | os.PathLike | None = None,
        fps: float = 40.0,
        drop_probability: float = 0.0,
        seed: int = 0,
    ) -> None:
        self.name = name
        self._writer = FrameWriter(name, width, height, slots)
        self.layout = self._writer.layout
        self.drop_probability = drop_probability
        self.frames = 0
        """Frames offered (rendered), including the ones faults swallowed."""
        self.published = 0
        self.faulted = 0
        """Frames a fault (random drop or stall) kept from the readers."""
        self._rng = random.Random(seed)
        self._stall_until_ns = 0
        self.fps = fps
        self._recorder = None if video is None else _Recorder(video, fps, width, height)
        self._closed = False

    @property
    def recording_skipped(self) -> int:
        return 0 if self._recorder is None else self._recorder.skipped

    def stall(self, seconds: float) -> None:
        """Camera fault: publish nothing for `seconds` from now."""
        self._stall_until_ns = time.monotonic_ns() + round(seconds * 1e9)

    def publish(self, image: np.ndarray, t_ns: int | None = None) -> bool:
        """Offer the next frame (uint8, height x width) captured at `t_ns` (default now, on
        `time.monotonic_ns()`); False if a fault swallowed it."""
        if image.shape != (self.layout.height, self.layout.width) or image.dtype != np.uint8:
            raise ValueError(
                f"expected a uint8 {self.layout.height}x{self.layout.width} frame, got "
                f"{image.dtype} {image.shape}"
            )
        return self.offer(lambda out: np.copyto(out, image), t_ns)

    def offer(self, draw: Callable[[np.ndarray], object], t_ns: int | None = None) -> bool:
        """Offer the next frame captured at `t_ns` (default now), drawn by `draw(out)` straight
        into its slot of the shared memory (uint8, height x width), so it is never copied
        there; a frame a fault swallows is not drawn. False if a fault swallowed it."""
        t_ns = time.monotonic_ns() if t_ns is None else t_ns
        self.frames += 1
        if t_ns < self._stall_until_ns or self._rng.random() < self.drop_probability:
            self.faulted += 1
            return False
        image = self._writer.begin(self.frames)
        draw(image)
        self._writer.commit(self.frames, t_ns)
        self.published += 1
        if self._recorder is not None:
            self._recorder.add(image)
        return True

    def run(
        self,
        render: Callable[[int, np.ndarray], object],
        *,
        frames: int | None = None,
        stop: threading.Event | None = None,
    ) -> None:
        """Render and publish at `self.fps` until `frames` have been offered or `stop` is set;
        `render(t_ns, out)` draws the world as it is at capture time `t_ns` into `out`, the
        frame's slot (see `offer`). A late frame is not followed by a burst: the schedule
        restarts from it."""
        stop = stop or threading.Event()
        period_ns = round(1e9 / self.fps)
        due = time.monotonic_ns()
        while not stop.is_set() and (frames is None or self.frames < frames):
            t_ns = time.monotonic_ns()
            self.offer(partial(render, t_ns), t_ns)
            due = max(due + period_ns, time.monotonic_ns())
            stop.wait(max(0, due - time.monotonic_ns()) / 1e9)

    def close(self) -> None:
        """Tell readers the stream has ended, finish the recording, remove the memory."""
        if self._closed:
            return
        self._closed = True
        self._writer.close()
        if self._recorder is not None:
            self._recorder.close()

    def __enter__(self) -> VirtualCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
