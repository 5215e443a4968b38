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
hil/ while hil/ may import edge/. A reader sleeps on the header's frame counter as a Linux futex
and the writer wakes every sleeper after each frame: the writer needs to know nothing about its
readers, never blocks on them, and a reader that dies costs nothing (where there is no futex the
reader polls the counter every half millisecond, at the price of up to that much latency). A
consumer that checks `Frame.intact` after using an image may have it lent: the image is then the
shared slot itself, not a copy (`CameraSource.lend`).
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import importlib
import mmap
import os
import platform
import re
import struct
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm"})
VIDEO_SUFFIXES = frozenset({".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg"})
POLL_S = 0.0005
"""How often a virtual-camera reader looks for a new frame where it cannot sleep on a futex."""
WAIT_S = 0.1
"""Longest a virtual-camera reader sleeps on the futex before it looks again anyway."""


@dataclass(frozen=True)
class Frame:
    """One grayscale image and when it was captured (`time.monotonic_ns()` clock)."""

    image: np.ndarray
    t_capture_ns: int
    index: int
    """Frame number from the source: consecutive unless the source skipped frames."""
    lease: Callable[[], bool] | None = None
    """For an image lent from the source's own buffer (`CameraSource.lend`): whether that
    buffer still holds this frame. None: the image is the frame's own."""

    def intact(self) -> bool:
        """Whether the image is still this frame's: always for an image of its own; for a lent
        one, whether the source has not reused its buffer yet. A result computed from a lent
        image counts only if this holds after the computation."""
        return self.lease is None or self.lease()

    def owned(self) -> Frame | None:
        """This frame with an image of its own (a lent one is copied); None if the source has
        already reused the buffer."""
        if self.lease is None:
            return self
        copy = replace(self, image=self.image.copy(), lease=None)
        return copy if self.lease() else None


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
    """Base of all sources: subclasses implement `_read` (and `_close`, `_stamp`, `_lease` if
    needed)."""

    lend = False
    """Set by a consumer that checks `Frame.intact` after using each image: a source that can
    then hands out its own buffer instead of a copy (the virtual camera's shared slot)."""

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

    def _lease(self) -> Callable[[], bool] | None:
        """For an image `_read` lent from the source's buffer: whether the buffer still holds
        it (`Frame.lease`); None for an image of its own."""
        return None

    def _close(self) -> None:
        """Release the device, file or mapping."""

    def read(self) -> Frame | None:
        """The next frame, or None at the end of the stream."""
        image = self._read()
        if image is None:
            return None
        t_ns, index = self._stamp()
        lease = self._lease()
        self._count += 1
        if image.ndim == 3 and image.shape[2] > 1:
            code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
            image, lease = cv2.cvtColor(image, code), None
        elif image.ndim == 3:
            image = image[..., 0]
        return Frame(image, t_ns, index, lease)

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

    Frame n goes to slot n % slots. Writer: slot number := 0, image, slot (n, t), latest := n,
    wake the readers (`FrameBell`). Reader: take latest n, copy slot n % slots, and keep the
    copy only if the slot still says n before and after (a seqlock); a reader that is lent the
    slot instead of a copy checks it after using the image. Several slots give a slow reader
    room before it is lapped.
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

    def begin(self, buf, number: int) -> np.ndarray:
        """Writer side, first half: the slot of frame `number` (from 1, increasing), marked as
        being written; draw the frame into the image returned, then `commit` it."""
        _VCAM_SLOT.pack_into(buf, self._slot_at(number % self.slots), 0, 0)
        return self._image(buf, number % self.slots)

    def commit(self, buf, number: int, t_ns: int) -> None:
        """Writer side, second half: frame `number`, captured at `t_ns`, is complete (then
        ring the `FrameBell`)."""
        _VCAM_SLOT.pack_into(buf, self._slot_at(number % self.slots), number, t_ns)
        struct.pack_into("<Q", buf, _VCAM_LATEST_AT, number)

    def mark_closed(self, buf) -> None:
        struct.pack_into("<I", buf, _VCAM_CLOSED_AT, 1)

    def latest(self, buf) -> int:
        return struct.unpack_from("<Q", buf, _VCAM_LATEST_AT)[0]

    def closed(self, buf) -> bool:
        return struct.unpack_from("<I", buf, _VCAM_CLOSED_AT)[0] != 0

    def holds(self, buf, number: int) -> bool:
        """Reader side: whether frame `number`'s slot still holds it, complete."""
        return _VCAM_SLOT.unpack_from(buf, self._slot_at(number % self.slots))[0] == number

    def lend(self, buf, number: int) -> tuple[np.ndarray, int] | None:
        """Reader side: frame `number`'s image in place, no copy, and its capture time, or None
        if the writer is already reusing its slot; the image is this frame's only while
        `holds` says so."""
        before, t_ns = _VCAM_SLOT.unpack_from(buf, self._slot_at(number % self.slots))
        return (self._image(buf, number % self.slots), t_ns) if before == number else None

    def read(self, buf, number: int) -> tuple[np.ndarray, int] | None:
        """Reader side: a copy of frame `number` and its capture time, or None if the writer
        has already reused its slot."""
        lent = self.lend(buf, number)
        if lent is None:
            return None
        image = lent[0].copy()
        return (image, lent[1]) if self.holds(buf, number) else None


_SYS_FUTEX = {"x86_64": 202, "aarch64": 98, "arm64": 98, "riscv64": 98}.get(platform.machine())
_FUTEX_WAIT, _FUTEX_WAKE = 0, 1  # without FUTEX_PRIVATE_FLAG: shared between processes


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


def _futex_call() -> Callable[..., int] | None:
    """libc's `syscall(2)` where Linux futexes are known (glibc wraps no futex call)."""
    if not sys.platform.startswith("linux") or _SYS_FUTEX is None:
        return None
    try:
        call = ctypes.CDLL(None, use_errno=True).syscall
    except (OSError, AttributeError):
        return None
    call.restype = ctypes.c_long
    return call


_FUTEX = _futex_call()


class FrameBell:
    """The header's frame counter as a futex (its low 32 bits): a reader sleeps on it until
    the writer rings after a frame, waking every sleeper; where there is no futex, a reader
    naps `POLL_S` instead. The mapping `buf` must stay open while the bell is used."""

    def __init__(self, buf) -> None:
        self._word = ctypes.c_void_p(np.frombuffer(buf, np.uint8, 4, _VCAM_LATEST_AT).ctypes.data)

    def wait(self, latest: int, timeout_s: float) -> None:
        """Sleep while the counter still says `latest`, at most `timeout_s` (or `POLL_S`
        without a futex); may return early."""
        if _FUTEX is None:
            time.sleep(POLL_S)
            return
        timeout = _Timespec(int(timeout_s), int(timeout_s % 1 * 1e9))
        expected = ctypes.c_uint(latest & 0xFFFFFFFF)
        _FUTEX(_SYS_FUTEX, self._word, _FUTEX_WAIT, expected, ctypes.byref(timeout), None, 0)

    def ring(self) -> None:
        """Wake every reader sleeping on the counter."""
        if _FUTEX is not None:
            _FUTEX(_SYS_FUTEX, self._word, _FUTEX_WAKE, ctypes.c_int(2**31 - 1), None, None, 0)


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
        self._bell: FrameBell | None = FrameBell(self._buf)

    def _read(self) -> np.ndarray | None:
        buf, layout, bell = self._buf, self._layout, self._bell
        take = layout.lend if self.lend else layout.read
        while not self._stopping.is_set() and bell is not None:
            latest = layout.latest(buf)
            if latest > self._last:
                got = take(buf, latest)
                if got is not None:
                    self._last = latest
                    image, self._last_t = got
                    return image
                continue
            if layout.closed(buf):
                return None
            bell.wait(latest, WAIT_S)
        return None

    def _stamp(self) -> tuple[int, int]:
        return self._last_t, self._last

    def _lease(self) -> Callable[[], bool] | None:
        if not self.lend:
            return None
        number, layout, buf = self._last, self._layout, self._buf
        return lambda: layout.holds(buf, number)

    def stop(self) -> None:
        super().stop()
        if self._bell is not None:
            self._bell.ring()  # a reader asleep on the bell wakes and sees the stop

    def _close(self) -> None:
        self._bell = None
        with contextlib.suppress(BufferError):  # a lent image still maps it: unmapped with it
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
        self._arrived = threading.Condition(self._lock)
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
        """Wake the coroutine waiting in `next_frame` or the threads in `wait_frame`, if any
        (lock held)."""
        self._arrived.notify_all()
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

    def wait_frame(self, timeout: float | None = None) -> Frame | None:
        """`next_frame` for a thread that runs no event loop (the perception process's): the
        newest frame not yet returned, waiting up to `timeout` seconds; None on timeout, at the
        end of the stream, or once stopped (a read error is raised)."""
        self.start()
        with self._lock:
            self._arrived.wait_for(
                lambda: self._latest is not None or self._ended or self._stop.is_set(), timeout
            )
            return self._take()

    @property
    def ended(self) -> bool:
        """The stream has ended (or failed) and every frame of it has been taken."""
        with self._lock:
            return self._ended and self._latest is None

    def stop(self) -> None:
        """Stop capturing soon (a blocked read returns) and wake `wait_frame`; safe from any
        thread."""
        self._stop.set()
        self.source.stop()
        with self._lock:
            self._arrived.notify_all()

    def close(self) -> None:
        """Stop the capture thread and close the source."""
        self.stop()
        if self._thread.ident is not None:
            self._thread.join(self.JOIN_S)
        if not self._thread.is_alive():
            self.source.close()

    def __enter__(self) -> FrameGrabber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
