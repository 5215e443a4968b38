"""Camera sources behind one small interface, chosen by URL, and a grabber that feeds asyncio.

As in python-can, a source implements one narrow hook (`_read`, blocking, an image or None at the
end of the stream) and is registered by scheme as "module:Class", imported only when opened, so a
source needing an extra library costs nothing until someone asks for it. Everything downstream
sees grayscale `Frame`s stamped with `time.monotonic_ns()`, the clock the runtime measures its
spans with.

`FrameGrabber` runs the blocking reads in a thread: a camera read may block for a frame period,
and the event loop must keep dispatching commands meanwhile. Only the newest frame matters to a
controller, so an unconsumed frame is overwritten by the next one (and counted as dropped) rather
than queued: a slow consumer sees fresh frames, never a growing backlog.

The virtual camera (`virtual://NAME`) is a shared-memory segment written by the HIL's renderer in
another process. Its layout is defined here, once (`VcamLayout`), because edge/ may not import
hil/ while hil/ may import edge/. The reader polls the header every half millisecond instead of
being notified: the writer needs to know nothing about its readers, never blocks on them, and a
reader that dies costs nothing; the price is at most the poll interval of latency.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import mmap
import os
import re
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm"})
VIDEO_SUFFIXES = frozenset({".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg"})
POLL_S = 0.0005
"""How often a virtual-camera reader looks for a new frame."""


@dataclass(frozen=True)
class Frame:
    """One grayscale image and when it was captured (`time.monotonic_ns()` clock)."""

    image: np.ndarray
    t_capture_ns: int
    index: int
    """Frame number from the source: consecutive unless the source skipped frames."""


#: How much nicer (Unix niceness) than the event loop the frame threads run: capture and vision
#: have the frame period to finish, a command has its 10 ms deadline, so the loop that sends
#: and retransmits commands preempts them.
FRAME_THREAD_NICENESS = 5


_LOOP_NICENESS = os.getpriority(os.PRIO_PROCESS, 0) if hasattr(os, "getpriority") else 0
"""The niceness of the thread that imported this module: the event loop's (in the perception
process, the niceness it was started with, the loop's)."""


def yield_to_dispatch(thread_id: int | None = None) -> None:
    """Run the calling thread (or native ``thread_id``) ``FRAME_THREAD_NICENESS`` nicer than the
    event loop (Linux niceness is per thread, and raising it needs no privilege); elsewhere
    nothing changes."""
    with contextlib.suppress(AttributeError, OSError):
        tid = thread_id or threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, _LOOP_NICENESS + FRAME_THREAD_NICENESS)


def yield_process_to_dispatch() -> None:
    """Every thread of this process (libraries start some of their own) nicer than the loop,
    as :func:`yield_to_dispatch`; threads started later inherit it from their creator."""
    tasks = Path("/proc/self/task")
    if tasks.is_dir():
        for task in tasks.iterdir():
            yield_to_dispatch(int(task.name))


class CameraError(Exception):
    """A camera that cannot be opened or read; the message is one line for the CLI."""


class CameraSource:
    """Base of all sources: subclasses implement `_read` (and `_close`, `_stamp` if needed)."""

    def __init__(self, url: str) -> None:
        self.url = url
        self._count = 0
        self._stopping = threading.Event()

    def _read(self) -> np.ndarray | None:
        """Block until the next image (any channel count, uint8); None at the end."""
        raise NotImplementedError

    def _stamp(self) -> tuple[int, int]:
        """(capture time, index) of the image `_read` just returned."""
        return time.monotonic_ns(), self._count

    def _close(self) -> None:
        """Release the device, file or mapping."""

    def read(self) -> Frame | None:
        """The next frame, or None at the end of the stream."""
        image = self._read()
        if image is None:
            return None
        t_ns, index = self._stamp()
        self._count += 1
        if image.ndim == 3:
            code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
            image = cv2.cvtColor(image, code) if image.shape[2] > 1 else image[..., 0]
        return Frame(image, t_ns, index)

    def stop(self) -> None:
        """Make a blocked or future `read` return None soon; safe from any thread."""
        self._stopping.set()

    def close(self) -> None:
        self.stop()
        self._close()

    def __iter__(self) -> Iterator[Frame]:
        while (frame := self.read()) is not None:
            yield frame

    def __enter__(self) -> CameraSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextlib.contextmanager
def _quiet_opencv() -> Iterator[None]:
    """OpenCV logs warnings when an open fails; the CameraError says it in one line instead."""
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(level)


class _CaptureSource(CameraSource):
    def __init__(self, url: str, capture: cv2.VideoCapture) -> None:
        super().__init__(url)
        self._cap = capture

    def _read(self) -> np.ndarray | None:
        if self._stopping.is_set():
            return None
        ok, image = self._cap.read()
        return image if ok else None

    def _close(self) -> None:
        self._cap.release()


class DeviceSource(_CaptureSource):
    """A live camera: `/dev/videoN` or an index ("0")."""

    def __init__(self, target: str) -> None:
        if target.isdigit():
            with _quiet_opencv():
                cap = cv2.VideoCapture(int(target))
        else:
            if not os.path.exists(target):
                raise CameraError(f"camera device {target} does not exist")
            with _quiet_opencv():
                cap = cv2.VideoCapture(target, cv2.CAP_V4L2)
        if not cap.isOpened():
            raise CameraError(f"cannot open camera device {target}")
        super().__init__(target, cap)


class VideoFileSource(_CaptureSource):
    """A recorded video, read as fast as asked (see `FrameGrabber` pace)."""

    def __init__(self, target: str) -> None:
        if not os.path.isfile(target):
            raise CameraError(f"video file not found: {target}")
        with _quiet_opencv():
            cap = cv2.VideoCapture(target)
        if not cap.isOpened():
            raise CameraError(f"cannot open video file {target} (not a video OpenCV can decode)")
        super().__init__(target, cap)


class FolderSource(CameraSource):
    """The images of a folder, in sorted file-name order."""

    def __init__(self, target: str) -> None:
        folder = Path(target)
        if not folder.is_dir():
            raise CameraError(f"image folder not found: {target}")
        self._files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self._files:
            raise CameraError(f"no images ({', '.join(sorted(IMAGE_SUFFIXES))}) in folder {target}")
        super().__init__(target)

    def _read(self) -> np.ndarray | None:
        if self._stopping.is_set() or self._count >= len(self._files):
            return None
        path = self._files[self._count]
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise CameraError(f"cannot read image {path}")
        return image


# -- the virtual camera's shared memory -------------------------------------------------------
_VCAM_HEADER = struct.Struct("<4sHHIIIIQ")
_VCAM_SLOT = struct.Struct("<QQ")
_VCAM_CLOSED_AT = 16
_VCAM_LATEST_AT = 24
VCAM_MAGIC = b"UDVC"
VCAM_VERSION = 1


@dataclass(frozen=True)
class VcamLayout:
    """The virtual camera's shared memory, little-endian:

    - header, 32 bytes: magic "UDVC", version u16, slots u16, width u32, height u32, closed u32,
      reserved u32, latest u64 (number of the newest complete frame, 0 = none yet);
    - per slot, 16 bytes: frame number u64 (0 while being written), capture time u64 (the
      writer's `time.monotonic_ns()` at render time);
    - from `data_offset` (64-byte aligned): `slots` grayscale images of width x height bytes.

    Frame n goes to slot n % slots. Writer: slot number := 0, image, slot (n, t), latest := n.
    Reader: take latest n, copy slot n % slots, and keep the copy only if the slot still says n
    before and after (a seqlock): several slots give a slow reader room before it is lapped.
    """

    width: int
    height: int
    slots: int = 3

    @property
    def frame_bytes(self) -> int:
        return self.width * self.height

    @property
    def data_offset(self) -> int:
        return -(-(_VCAM_HEADER.size + self.slots * _VCAM_SLOT.size) // 64) * 64

    @property
    def size(self) -> int:
        return self.data_offset + self.slots * self.frame_bytes

    def _slot_at(self, slot: int) -> int:
        return _VCAM_HEADER.size + slot * _VCAM_SLOT.size

    def _image(self, buf, slot: int) -> np.ndarray:
        offset = self.data_offset + slot * self.frame_bytes
        return np.frombuffer(buf, np.uint8, self.frame_bytes, offset).reshape(
            self.height, self.width
        )

    @classmethod
    def from_buffer(cls, buf) -> VcamLayout:
        """The layout a writer put in `buf`; ValueError if it is not a virtual camera."""
        magic, version, slots, width, height, *_ = _VCAM_HEADER.unpack_from(buf, 0)
        if magic != VCAM_MAGIC or version != VCAM_VERSION or slots < 1:
            raise ValueError("not a virtual camera header")
        layout = cls(width, height, slots)
        if len(buf) < layout.size:
            raise ValueError("virtual camera segment is shorter than its header says")
        return layout

    def write_header(self, buf) -> None:
        _VCAM_HEADER.pack_into(
            buf, 0, VCAM_MAGIC, VCAM_VERSION, self.slots, self.width, self.height, 0, 0, 0
        )

    def publish(self, buf, number: int, t_ns: int, image: np.ndarray) -> None:
        """Writer side: frame `number` (from 1, increasing) captured at `t_ns`."""
        at = self._slot_at(number % self.slots)
        _VCAM_SLOT.pack_into(buf, at, 0, 0)
        self._image(buf, number % self.slots)[:] = image
        _VCAM_SLOT.pack_into(buf, at, number, t_ns)
        struct.pack_into("<Q", buf, _VCAM_LATEST_AT, number)

    def mark_closed(self, buf) -> None:
        struct.pack_into("<I", buf, _VCAM_CLOSED_AT, 1)

    def latest(self, buf) -> int:
        return struct.unpack_from("<Q", buf, _VCAM_LATEST_AT)[0]

    def closed(self, buf) -> bool:
        return struct.unpack_from("<I", buf, _VCAM_CLOSED_AT)[0] != 0

    def read(self, buf, number: int) -> tuple[np.ndarray, int] | None:
        """Reader side: a copy of frame `number` and its capture time, or None if the writer
        has already reused its slot."""
        at = self._slot_at(number % self.slots)
        before, t_ns = _VCAM_SLOT.unpack_from(buf, at)
        if before != number:
            return None
        image = self._image(buf, number % self.slots).copy()
        after, _ = _VCAM_SLOT.unpack_from(buf, at)
        return (image, t_ns) if after == number else None


def shm_path(name: str) -> Path:
    """Where Linux exposes the POSIX shared memory `name` (what `SharedMemory(name)` creates)."""
    return Path("/dev/shm") / name


class VirtualSource(CameraSource):
    """`virtual://NAME`: frames the HIL renderer publishes in shared memory NAME.

    The segment is mapped read-only through /dev/shm rather than with `SharedMemory(name)`,
    which on Python < 3.13 registers it with this process's resource tracker, and the tracker
    would unlink the writer's segment when this reader exits."""

    ATTACH_S = 1.0
    """How long to wait for a writer that has created the segment but not its header yet."""

    def __init__(self, target: str) -> None:
        name = target.strip("/")
        if not name or "/" in name:
            raise CameraError(f"bad virtual camera name {target!r} (expected virtual://NAME)")
        super().__init__(f"virtual://{name}")
        deadline = time.monotonic() + self.ATTACH_S
        while True:
            try:
                with open(shm_path(name), "rb") as f:
                    self._buf = mmap.mmap(f.fileno(), 0, prot=mmap.PROT_READ)
                self._layout = VcamLayout.from_buffer(self._buf)
                break
            except FileNotFoundError:
                raise CameraError(
                    f"virtual camera {name!r} not found (is the HIL virtual camera running?)"
                ) from None
            except ValueError as exc:
                if time.monotonic() > deadline:
                    raise CameraError(f"virtual camera {name!r}: {exc}") from None
                time.sleep(0.01)
        self._last = 0
        self._last_t = 0

    def _read(self) -> np.ndarray | None:
        buf, layout = self._buf, self._layout
        while not self._stopping.is_set():
            latest = layout.latest(buf)
            if latest > self._last:
                got = layout.read(buf, latest)
                if got is not None:
                    self._last = latest
                    image, self._last_t = got
                    return image
                continue
            if layout.closed(buf):
                return None
            time.sleep(POLL_S)
        return None

    def _stamp(self) -> tuple[int, int]:
        return self._last_t, self._last

    def _close(self) -> None:
        self._buf.close()


# -- registry ---------------------------------------------------------------------------------
_SOURCES: dict[str, str] = {
    "device": "udan.edge.camera:DeviceSource",
    "video": "udan.edge.camera:VideoFileSource",
    "folder": "udan.edge.camera:FolderSource",
    "virtual": "udan.edge.camera:VirtualSource",
}
_URL = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*)://(.*)$")


def register_source(scheme: str, target: str) -> None:
    """Make `scheme://...` open the class `target` ("package.module:Class"), imported when first
    used; the class takes the part of the URL after "scheme://"."""
    _SOURCES[scheme.lower()] = target


def _source_class(scheme: str) -> type[CameraSource]:
    module, _, name = _SOURCES[scheme].partition(":")
    return getattr(importlib.import_module(module), name)


def open_camera(url: str) -> CameraSource:
    """The source `url` names: `scheme://...` (device, video, folder, virtual), `/dev/videoN`
    or an index, an image folder, or a video file."""
    m = _URL.match(url)
    if m:
        scheme, target = m.group(1).lower(), m.group(2)
        if scheme not in _SOURCES:
            known = ", ".join(f"{s}://" for s in sorted(_SOURCES))
            raise CameraError(f"unknown camera scheme {scheme}:// in {url!r} (known: {known})")
    elif url.isdigit() or url.startswith("/dev/"):
        scheme, target = "device", url
    elif os.path.isdir(url):
        scheme, target = "folder", url
    elif os.path.isfile(url) or Path(url).suffix.lower() in VIDEO_SUFFIXES:
        scheme, target = "video", url
    else:
        raise CameraError(f"no camera, video file or image folder at {url!r}")
    try:
        return _source_class(scheme)(target)
    except (OSError, cv2.error) as exc:
        detail = (getattr(exc, "strerror", None) or str(exc)).strip().splitlines()[0]
        raise CameraError(f"cannot open camera {url}: {detail}") from None


# -- grabber ----------------------------------------------------------------------------------
class FrameGrabber:
    """Reads `source` in a thread and hands the newest frame to asyncio; owns the source.

    The thread starts with `start()` (or the first `next_frame`). `pace` (frames per second)
    plays a file or folder at a camera's rate instead of as fast as it decodes."""

    JOIN_S = 2.0

    def __init__(self, source: CameraSource, *, pace: float | None = None) -> None:
        self.source = source
        self.pace = pace
        self.captured = 0
        """Frames read from the source."""
        self.dropped = 0
        """Frames overwritten by a newer one before anyone took them."""
        self._lock = threading.Lock()
        self._latest: Frame | None = None
        self._ended = False
        self._error: Exception | None = None
        self._waiter: tuple[asyncio.AbstractEventLoop, asyncio.Event] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"camera {source.url}", daemon=True)

    def start(self) -> None:
        """Start capturing (once; later calls do nothing)."""
        with self._lock:
            if self._thread.ident is None:
                self._thread.start()

    def _run(self) -> None:
        yield_to_dispatch()
        due = time.monotonic()
        try:
            while not self._stop.is_set():
                if self.pace:
                    if self._stop.wait(max(0.0, due - time.monotonic())):
                        break
                    due += 1.0 / self.pace
                frame = self.source.read()
                if frame is None:
                    break
                with self._lock:
                    if self._latest is not None:
                        self.dropped += 1
                    self._latest = frame
                    self.captured += 1
                    self._wake()
        except Exception as exc:
            with self._lock:
                self._error = exc
        finally:
            with self._lock:
                self._ended = True
                self._wake()

    def _wake(self) -> None:
        """Wake the coroutine waiting in `next_frame`, if any (lock held)."""
        if self._waiter is not None:
            loop, event = self._waiter
            self._waiter = None
            with contextlib.suppress(RuntimeError):  # its loop has closed
                loop.call_soon_threadsafe(event.set)

    def _take(self) -> Frame | None:
        """The unconsumed newest frame; at the end, None or the error that ended it (lock held)."""
        if self._latest is not None:
            frame, self._latest = self._latest, None
            return frame
        if self._ended and self._error is not None:
            raise self._error
        return None

    async def next_frame(self, timeout: float | None = None) -> Frame | None:
        """The newest frame newer than the last one returned, waiting for one up to `timeout`
        seconds; None on timeout or at the end of the stream (a read error is raised)."""
        self.start()
        loop = asyncio.get_running_loop()
        deadline = None if timeout is None else loop.time() + timeout
        while True:
            with self._lock:
                frame = self._take()
                if frame is not None or self._ended:
                    return frame
                event = asyncio.Event()
                self._waiter = (loop, event)
            remaining = None if deadline is None else deadline - loop.time()
            try:
                await asyncio.wait_for(event.wait(), remaining)
            except TimeoutError:
                with self._lock:
                    if self._waiter is not None and self._waiter[1] is event:
                        self._waiter = None
                    return self._take()

    @property
    def ended(self) -> bool:
        """The stream has ended (or failed) and every frame of it has been taken."""
        with self._lock:
            return self._ended and self._latest is None

    def close(self) -> None:
        """Stop the capture thread and close the source."""
        self._stop.set()
        self.source.stop()
        if self._thread.ident is not None:
            self._thread.join(self.JOIN_S)
        if not self._thread.is_alive():
            self.source.close()

    def __enter__(self) -> FrameGrabber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
