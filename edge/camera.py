"""Camera sources behind one small interface, chosen by URL, and a grabber that feeds asyncio.

As in python-can, a source implements one narrow hook (`_read`, blocking, an image or None at the
end of the stream) and is registered by scheme as "module:Class", imported only when opened, so a
source needing an extra library (GenICam cameras through Aravis: `aravis://`) costs nothing until
someone asks for it. Everything downstream sees grayscale `Frame`s stamped on
`time.monotonic_ns()`, the clock the runtime measures its spans with: stamped when the camera
exposed them where the camera or its driver says so (the V4L2 buffer timestamp, a GenICam
camera's timestamp mapped onto this clock), so a frame's age on arrival is part of every latency
figure.

A live camera's mode is set in one place, its URL: `/dev/video0?width=1920&height=1200&fps=40`
(`CameraOptions`). The source sets what was asked, reads back what the driver granted
(`CameraMode`), and warns of every difference (an error with `strict=1`); a setting the driver
refuses outright is a `CameraError`. A source with a driver queue never serves a frame that
waited in it for more than a frame period (`StaleGuard`: counted and skipped), and a live camera
that goes away raises `CameraLost`: the grabber reopens it when it returns.

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
import shutil
import struct
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields, replace
from multiprocessing import shared_memory
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np

from udan.edge.pauses import threads_of_this_process

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
    t_arrival_ns: int | None = None
    """When the source handed it over (None: at capture); minus the capture, its age."""
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


CLOCKS = ("auto", "latch", "realtime", "arrival")
"""Where a live camera's capture times come from (`CameraOptions.clock`)."""


def _positive(kind: type) -> Callable[[str], float]:
    def parse(text: str) -> float:
        value = kind(text)
        if not value > 0:
            raise ValueError
        return value

    parse.__name__ = f"a positive {'integer' if kind is int else 'number'}"
    return parse


def _non_negative(text: str) -> float:
    value = float(text)
    if not value >= 0:
        raise ValueError
    return value


_non_negative.__name__ = "a number >= 0"


def _pixel_format(text: str) -> str:
    if not re.fullmatch(r"[A-Za-z0-9_]{1,32}", text):
        raise ValueError
    return text


_pixel_format.__name__ = "a pixel format name (MJPG, YUYV, Mono8, ...)"


def _clock(text: str) -> str:
    if text not in CLOCKS:
        raise ValueError
    return text


_clock.__name__ = f"one of {', '.join(CLOCKS)}"


def _flag(text: str) -> bool:
    if text not in ("0", "1", "true", "false"):
        raise ValueError
    return text in ("1", "true")


_flag.__name__ = "0 or 1"


@dataclass(frozen=True)
class CameraOptions:
    """A live camera's mode as its URL asks for it (`/dev/video0?width=1920&height=1200&fps=40`):
    the one place a mode is set; udan-edge, udan-calibrate and the probe all read it there.
    Unset fields leave the driver's current setting alone."""

    width: int | None = None
    """Image width in pixels."""
    height: int | None = None
    """Image height in pixels."""
    fps: float | None = None
    """Frames per second."""
    format: str | None = None
    """Pixel format: a V4L2 FourCC (MJPG, YUYV, GREY) or a GenICam PixelFormat (Mono8, BayerRG8)."""
    exposure_us: float | None = None
    """Exposure time in microseconds; setting it turns automatic exposure off."""
    gain: float | None = None
    """Sensor gain in the driver's unit (V4L2: its raw value; GenICam: dB); turns automatic gain
    off."""
    clock: str = "auto"
    """Where capture times come from: auto (the driver's or camera's own timestamp), latch (a
    GenICam camera's timestamp latch), realtime (a camera stamping with this host's realtime
    clock, as Aravis's fake camera does), arrival (when the frame arrived here)."""
    strict: bool = False
    """A granted mode that differs from the asked one is an error, not a warning."""

    _PARSERS: ClassVar[dict[str, Callable[[str], Any]]] = {
        "width": _positive(int),
        "height": _positive(int),
        "fps": _positive(float),
        "format": _pixel_format,
        "exposure_us": _positive(float),
        "gain": _non_negative,
        "clock": _clock,
        "strict": _flag,
    }

    @classmethod
    def parse(cls, query: str) -> CameraOptions:
        """Options from a URL's query string (``width=1920&fps=40``); a one-line
        `CameraError` for an unknown option or a bad value."""
        values: dict[str, Any] = {}
        for item in filter(None, query.split("&")):
            name, sep, text = item.partition("=")
            parser = cls._PARSERS.get(name)
            if parser is None:
                known = ", ".join(cls._PARSERS)
                raise CameraError(f"unknown camera option {name!r} (known: {known})")
            if not sep or name in values:
                raise CameraError(f"camera option {name!r} must be given once, as {name}=VALUE")
            try:
                values[name] = parser(text)
            except ValueError:
                raise CameraError(f"camera option {name}={text}: not {parser.__name__}") from None
        return cls(**values)

    @property
    def given(self) -> dict[str, Any]:
        """The options set in the URL (not left at their default)."""
        return {f.name: v for f in fields(self) if (v := getattr(self, f.name)) != f.default}


@dataclass(frozen=True)
class CameraMode:
    """The mode a camera runs in, read back from its driver after the asked one was set."""

    width: int
    height: int
    fps: float | None = None
    format: str | None = None
    exposure_us: float | None = None
    gain: float | None = None
    clock: str = "arrival"
    """Where this source's capture times come from (what ``auto`` came to)."""

    def summary(self) -> str:
        """One line: ``1920x1200 at 40 fps, Mono8, exposure 2000 us, gain 0; capture times:
        device``."""
        parts = [f"{self.width}x{self.height}" + (f" at {self.fps:g} fps" if self.fps else "")]
        parts += [self.format] if self.format else []
        parts += [f"exposure {self.exposure_us:g} us"] if self.exposure_us is not None else []
        parts += [f"gain {self.gain:g}"] if self.gain is not None else []
        return ", ".join(parts) + f"; capture times: {self.clock}"


MODE_TOLERANCE = 0.01
"""Relative difference between an asked and a granted value (frame rate, exposure, gain) that
counts as granted: drivers round to their own steps."""


def mode_mismatches(asked: CameraOptions, granted: CameraMode) -> list[str]:
    """Each asked setting the granted mode differs from, in words."""
    out = []
    for name in ("width", "height", "fps", "format", "exposure_us", "gain"):
        want, got = getattr(asked, name), getattr(granted, name)
        if want is None:
            continue
        if isinstance(want, str):
            same = got is not None and want.lower() == str(got).lower()
        else:
            same = got is not None and abs(got - want) <= MODE_TOLERANCE * max(abs(want), 1e-9)
        if not same:
            out.append(f"{name} {_show(want)} asked, {_show(got)} granted")
    return out


def _show(value: object) -> str:
    return "none" if value is None else f"{value:g}" if isinstance(value, float) else str(value)


class StaleGuard:
    """Frames that waited in a driver's queue: a frame older on arrival than the youngest of the
    last ``window`` (the camera's own exposure and transfer time) by more than a frame period was
    not the newest one when it arrived. A source that finds one counts it and reads again, which
    drains the queue."""

    def __init__(self, period_ns: int, window: int = 64) -> None:
        self.period_ns = period_ns
        self._ages: deque[int] = deque(maxlen=window)

    def stale(self, age_ns: int) -> bool:
        """Whether a frame that arrived ``age_ns`` after its capture is stale."""
        self._ages.append(age_ns)
        return age_ns > min(self._ages) + self.period_ns


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
    for tid in threads_of_this_process():
        yield_to_dispatch(tid)


class CameraError(Exception):
    """A camera that cannot be opened or read; the message is one line for the CLI."""


class CameraLost(CameraError):
    """A live camera that went away mid-run (unplugged, powered off, its network down): the
    grabber reopens it when it returns (`CameraSource.reopen`)."""


class CameraSource:
    """Base of all sources: subclasses implement `_read` (and `_close`, `_stamp`, `_lease` if
    needed); live cameras also take `CameraOptions` (`OPTIONS` names the ones a source
    understands), report the granted `mode` and can `reopen`."""

    OPTIONS: ClassVar[frozenset[str]] = frozenset()
    """The `CameraOptions` this kind of source takes; any other given is an error."""
    KIND: ClassVar[str] = "this source"
    lend = False
    """Set by a consumer that checks `Frame.intact` after using each image: a source that can
    then hands out its own buffer instead of a copy (the virtual camera's shared slot)."""

    def __init__(self, url: str, options: CameraOptions = CameraOptions()) -> None:
        unknown = sorted(options.given.keys() - self.OPTIONS)
        if unknown:
            takes = (
                f"takes only {', '.join(sorted(self.OPTIONS))}"
                if self.OPTIONS
                else ("takes none (a mode is set on live cameras: /dev/videoN, aravis://)")
            )
            raise CameraError(f"camera option {', '.join(unknown)}: {self.KIND} {takes}")
        self.url = url
        self.options = options
        self.mode: CameraMode | None = None
        """What the camera runs in (None where a source has no mode: a folder)."""
        self.warnings: list[str] = []
        """How the granted mode differs from the asked one."""
        self.stale = 0
        """Frames skipped for having waited in the driver's queue (`StaleGuard`)."""
        self._stale_guard: StaleGuard | None = None
        self._count = 0
        self._stopping = threading.Event()

    def _granted(self, mode: CameraMode) -> None:
        """Take the mode read back from the driver: warn of what differs from the asked one
        (raise with ``strict``); a known frame rate also bounds how old a frame may arrive."""
        self.mode = mode
        self.warnings = mode_mismatches(self.options, mode)
        if self.warnings and self.options.strict:
            raise CameraError(
                f"{self.url}: the camera did not grant the mode asked: " + "; ".join(self.warnings)
            )
        if mode.fps:
            self._stale_guard = StaleGuard(round(1e9 / mode.fps))

    def counters(self) -> dict[str, int]:
        """What the source skipped: stale frames (and, for GenICam cameras, incomplete ones)."""
        return {"stale": self.stale}

    def reopen(self) -> None:
        """Open a lost camera again (raises `CameraError` while it is not back)."""
        raise CameraError(f"{self.url} cannot be reopened")

    def describe(self) -> dict[str, Any]:
        """The modes and controls the camera offers (the probe's answer); none here."""
        return {}

    def _read(self) -> np.ndarray | None:
        """Block until the next image (any channel count, uint8); None at the end."""
        raise NotImplementedError

    def _stamp(self, arrival_ns: int) -> tuple[int, int]:
        """(capture time, index) of the image `_read` just returned, which arrived at
        ``arrival_ns``; sources that know better than the arrival say when it was exposed."""
        return arrival_ns, self._count

    def _lease(self) -> Callable[[], bool] | None:
        """For an image `_read` lent from the source's buffer: whether the buffer still holds
        it (`Frame.lease`); None for an image of its own."""
        return None

    def _close(self) -> None:
        """Release the device, file or mapping."""

    def read(self) -> Frame | None:
        """The next frame, or None at the end of the stream; a frame that waited in the
        driver's queue is counted (`stale`) and the next one read instead."""
        while True:
            image = self._read()
            if image is None:
                return None
            arrival_ns = time.monotonic_ns()
            t_ns, index = self._stamp(arrival_ns)
            lease = self._lease()
            self._count += 1
            guard = self._stale_guard
            if guard is not None and guard.stale(arrival_ns - t_ns):
                self.stale += 1
                continue
            if image.ndim == 3 and image.shape[2] > 1:
                code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
                image, lease = cv2.cvtColor(image, code), None
            elif image.ndim == 3:
                image = image[..., 0]
            return Frame(image, t_ns, index, arrival_ns, lease)

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
    """A source read through OpenCV's `VideoCapture` (set up by the subclass in `_cap`)."""

    _cap: cv2.VideoCapture

    def _read(self) -> np.ndarray | None:
        if self._stopping.is_set():
            return None
        ok, image = self._cap.read()
        return image if ok else None

    def _close(self) -> None:
        self._cap.release()


V4L2_EXPOSURE_UNIT_US = 100
"""V4L2's absolute exposure control counts 100 µs steps (OpenCV passes it through)."""
V4L2_MANUAL_EXPOSURE = 1
"""V4L2_EXPOSURE_MANUAL, the auto-exposure value OpenCV's V4L2 backend passes through."""
DEVICE_BUFFERS = 1
"""Buffers the V4L2 driver queues: one, so a read gets the newest frame, not an old one."""
MAX_FRAME_AGE_NS = 2_000_000_000
"""A driver timestamp further in the past than this (or in the future) is not on the monotonic
clock: the source stamps frames on arrival instead."""


def fourcc_text(code: float) -> str | None:
    """OpenCV's numeric FourCC (CAP_PROP_FOURCC) as its four characters; None if unset."""
    raw = int(code).to_bytes(4, "little")
    text = raw.decode("ascii", "replace").strip("\0 ")
    return text or None


def v4l2_capture_ns(pos_msec: float, arrival_ns: int) -> int | None:
    """When a V4L2 buffer was captured, from its timestamp as OpenCV's V4L2 backend reports it
    (``CAP_PROP_POS_MSEC``: milliseconds on CLOCK_MONOTONIC for drivers that flag
    V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC, as uvcvideo does); None if it cannot be one (unset, in the
    future, or older than `MAX_FRAME_AGE_NS`: a driver stamping on another clock)."""
    t_ns = round(pos_msec * 1e6)
    return t_ns if 0 < t_ns <= arrival_ns and arrival_ns - t_ns < MAX_FRAME_AGE_NS else None


class DeviceSource(_CaptureSource):
    """A V4L2 camera (`/dev/videoN` or an index "0") through OpenCV, its mode set from the URL:
    `/dev/video0?width=1920&height=1080&fps=30&format=MJPG&exposure_us=2000`. Frames carry the
    driver's buffer timestamp; the driver queues one buffer, and a frame that still waited in it
    is skipped (`StaleGuard`). An unplugged camera raises `CameraLost` and is reopened by path."""

    OPTIONS = frozenset(
        {"width", "height", "fps", "format", "exposure_us", "gain", "clock", "strict"}
    )
    KIND = "a V4L2 camera"

    def __init__(self, target: str, options: CameraOptions = CameraOptions()) -> None:
        super().__init__(target, options)
        if options.clock not in ("auto", "arrival"):
            raise CameraError(
                f"camera option clock={options.clock}: a V4L2 camera stamps "
                "frames with its driver's clock (auto) or on arrival (arrival)"
            )
        if options.format is not None and len(options.format) != 4:
            raise CameraError(
                f"camera option format={options.format}: a V4L2 pixel format is "
                "a FourCC of four characters (MJPG, YUYV, GREY)"
            )
        self._cap = self._open()
        self._clock = "device" if options.clock == "auto" else "arrival"
        self._configure()

    def _open(self) -> cv2.VideoCapture:
        target = self.url
        if target.isdigit():
            with _quiet_opencv():
                cap = cv2.VideoCapture(int(target), cv2.CAP_V4L2)
        else:
            if not os.path.exists(target):
                raise CameraError(f"camera device {target} does not exist")
            with _quiet_opencv():
                cap = cv2.VideoCapture(target, cv2.CAP_V4L2)
        if not cap.isOpened():
            raise CameraError(f"cannot open camera device {target}")
        return cap

    def _configure(self) -> None:
        """Set the asked mode (the pixel format first: it decides the sizes on offer), then
        read back what the driver granted."""
        cap, o = self._cap, self.options
        settings: list[tuple[int, float, str]] = []
        if o.format is not None:
            settings.append(
                (cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*o.format), f"format={o.format}")
            )
        for prop, value, name in (
            (cv2.CAP_PROP_FRAME_WIDTH, o.width, "width"),
            (cv2.CAP_PROP_FRAME_HEIGHT, o.height, "height"),
            (cv2.CAP_PROP_FPS, o.fps, "fps"),
        ):
            if value is not None:
                settings.append((prop, value, f"{name}={value:g}"))
        if o.exposure_us is not None:
            settings.append((cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_MANUAL_EXPOSURE, "manual exposure"))
            settings.append(
                (
                    cv2.CAP_PROP_EXPOSURE,
                    o.exposure_us / V4L2_EXPOSURE_UNIT_US,
                    f"exposure_us={o.exposure_us:g}",
                )
            )
        if o.gain is not None:
            settings.append((cv2.CAP_PROP_GAIN, o.gain, f"gain={o.gain:g}"))
        settings.append((cv2.CAP_PROP_BUFFERSIZE, DEVICE_BUFFERS, f"{DEVICE_BUFFERS} buffer"))
        for prop, value, what in settings:
            if not cap.set(prop, value):
                raise CameraError(f"camera {self.url} refuses {what}")
        exposure = cap.get(cv2.CAP_PROP_EXPOSURE)
        gain = cap.get(cv2.CAP_PROP_GAIN)
        self._granted(
            CameraMode(
                width=int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                height=int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                fps=cap.get(cv2.CAP_PROP_FPS) or None,
                format=fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)),
                exposure_us=exposure * V4L2_EXPOSURE_UNIT_US if exposure > 0 else None,
                gain=gain if gain >= 0 else None,
                clock=self._clock,
            )
        )

    def _read(self) -> np.ndarray | None:
        if self._stopping.is_set():
            return None
        ok, image = self._cap.read()
        if not ok:
            if self._stopping.is_set():
                return None
            raise CameraLost(f"camera {self.url} gave no frame (unplugged?)")
        return image

    def _stamp(self, arrival_ns: int) -> tuple[int, int]:
        t_ns = None
        if self._clock == "device":
            t_ns = v4l2_capture_ns(self._cap.get(cv2.CAP_PROP_POS_MSEC), arrival_ns)
        return (arrival_ns if t_ns is None else t_ns), self._count

    def reopen(self) -> None:
        self._cap.release()
        self._cap = self._open()
        self._configure()

    def describe(self) -> dict[str, Any]:
        """The formats, sizes, frame rates and controls the driver lists, as ``v4l2-ctl``
        (Debian's v4l-utils) prints them: OpenCV cannot enumerate them."""
        tool = shutil.which("v4l2-ctl")
        if tool is None:
            return {"modes": "install v4l-utils (v4l2-ctl) to list this camera's modes"}
        listed = subprocess.run(
            [tool, "-d", self.url, "--list-formats-ext", "--list-ctrls"],
            capture_output=True, text=True, timeout=10,
        )  # fmt: skip
        return {"v4l2-ctl": (listed.stdout or listed.stderr).strip()}


class VideoFileSource(_CaptureSource):
    """A recorded video, read as fast as asked (see `FrameGrabber` pace)."""

    KIND = "a video file"

    def __init__(self, target: str, options: CameraOptions = CameraOptions()) -> None:
        super().__init__(target, options)
        if not os.path.isfile(target):
            raise CameraError(f"video file not found: {target}")
        with _quiet_opencv():
            self._cap = cv2.VideoCapture(target)
        if not self._cap.isOpened():
            raise CameraError(f"cannot open video file {target} (not a video OpenCV can decode)")
        cap = self._cap
        self.mode = CameraMode(
            int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            cap.get(cv2.CAP_PROP_FPS) or None,
        )


class FolderSource(CameraSource):
    """The images of a folder, in sorted file-name order."""

    KIND = "an image folder"

    def __init__(self, target: str, options: CameraOptions = CameraOptions()) -> None:
        super().__init__(target, options)
        folder = Path(target)
        if not folder.is_dir():
            raise CameraError(f"image folder not found: {target}")
        self._files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self._files:
            raise CameraError(f"no images ({', '.join(sorted(IMAGE_SUFFIXES))}) in folder {target}")

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

    def find(self, buf, t_ns: int) -> tuple[int | None, int]:
        """The number of the frame captured at ``t_ns`` if a slot still holds it, and the
        newest capture time any slot holds."""
        newest = 0
        for slot in range(self.slots):
            number, t = _VCAM_SLOT.unpack_from(buf, self._slot_at(slot))
            if number and t == t_ns:
                return number, t
            newest = max(newest, t)
        return None, newest

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


class FrameWriter:
    """Publishes frames into the shared memory ``name``, laid out as a `VcamLayout`: the HIL's
    virtual camera, and the perception process's ring of analysed frames for the flight
    recorder. A frame is drawn straight into its slot (`begin`, `commit`) or copied there
    (`publish`); each one rings the `FrameBell`. `close` tells readers the stream has ended and
    removes the memory (a reader that mapped it keeps its mapping)."""

    def __init__(self, name: str, width: int, height: int, slots: int = 3) -> None:
        self.name = name
        self.layout = VcamLayout(width, height, slots)
        try:
            self._shm = shared_memory.SharedMemory(name, create=True, size=self.layout.size)
        except FileExistsError:
            raise FileExistsError(
                f"shared memory {name!r} already exists (another writer is running, or remove "
                f"the stale /dev/shm/{name})"
            ) from None
        self.layout.write_header(self._shm.buf)
        self._bell = FrameBell(self._shm.buf)
        self._closed = False

    def begin(self, number: int) -> np.ndarray:
        """The slot of frame ``number`` (from 1, increasing), to draw the frame into before
        `commit`; readers see it as being written until then."""
        return self.layout.begin(self._shm.buf, number)

    def commit(self, number: int, t_ns: int) -> None:
        """Frame ``number``, captured at ``t_ns``, is complete: readers are woken."""
        self.layout.commit(self._shm.buf, number, t_ns)
        self._bell.ring()

    def publish(self, number: int, t_ns: int, image: np.ndarray) -> None:
        """Frame ``number`` (from 1, increasing) captured at ``t_ns``: a copy of ``image``."""
        np.copyto(self.begin(number), image)
        self.commit(number, t_ns)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.layout.mark_closed(self._shm.buf)
        self._bell.ring()
        self._shm.close()
        self._shm.unlink()


def shm_path(name: str) -> Path:
    """Where Linux exposes the POSIX shared memory `name` (what `SharedMemory(name)` creates)."""
    return Path("/dev/shm") / name


ATTACH_S = 1.0
"""How long a reader waits for a writer that has created its segment but not its header yet."""


def attach_frames(name: str) -> tuple[mmap.mmap, VcamLayout]:
    """Map the frame segment ``name`` (a `VcamLayout` in /dev/shm) read-only; `CameraError` if
    there is none.

    The segment is mapped through /dev/shm rather than with `SharedMemory(name)`, which on
    Python < 3.13 registers it with this process's resource tracker, and the tracker would
    unlink the writer's segment when this reader exits."""
    deadline = time.monotonic() + ATTACH_S
    while True:
        try:
            with open(shm_path(name), "rb") as f:
                buf = mmap.mmap(f.fileno(), 0, prot=mmap.PROT_READ)
            return buf, VcamLayout.from_buffer(buf)
        except FileNotFoundError:
            raise CameraError(
                f"virtual camera {name!r} not found (is the HIL virtual camera running?)"
            ) from None
        except ValueError as exc:
            if time.monotonic() > deadline:
                raise CameraError(f"virtual camera {name!r}: {exc}") from None
            time.sleep(0.01)


class VirtualSource(CameraSource):
    """`virtual://NAME`: frames the HIL renderer publishes in shared memory NAME, stamped when
    the renderer began to draw them (the simulated exposure)."""

    KIND = "the virtual camera"

    def __init__(self, target: str, options: CameraOptions = CameraOptions()) -> None:
        name = target.strip("/")
        if not name or "/" in name:
            raise CameraError(f"bad virtual camera name {target!r} (expected virtual://NAME)")
        super().__init__(f"virtual://{name}", options)
        self._buf, self._layout = attach_frames(name)
        self.mode = CameraMode(
            self._layout.width, self._layout.height, format="Mono8", clock="render"
        )
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

    def _stamp(self, arrival_ns: int) -> tuple[int, int]:
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
    "aravis": "udan.edge.genicam:AravisSource",
}
_URL = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*)://(.*)$")


def register_source(scheme: str, target: str) -> None:
    """Make `scheme://...` open the class `target` ("package.module:Class"), imported when first
    used; the class takes the part of the URL after "scheme://" and the `CameraOptions` of its
    query."""
    _SOURCES[scheme.lower()] = target


def _source_class(scheme: str) -> type[CameraSource]:
    module, _, name = _SOURCES[scheme].partition(":")
    return getattr(importlib.import_module(module), name)


def split_camera_url(url: str) -> tuple[str, str, CameraOptions]:
    """(scheme, target, options) of a camera URL: `scheme://TARGET?OPTIONS`, `/dev/videoN` or
    an index, an image folder, or a video file (a path that exists is taken whole, even with a
    "?" in its name)."""
    base, query = url, ""
    if "?" in url and not os.path.exists(url):
        base, _, query = url.partition("?")
    options = CameraOptions.parse(query)
    m = _URL.match(base)
    if m:
        scheme, target = m.group(1).lower(), m.group(2)
        if scheme not in _SOURCES:
            known = ", ".join(f"{s}://" for s in sorted(_SOURCES))
            raise CameraError(f"unknown camera scheme {scheme}:// in {url!r} (known: {known})")
    elif base.isdigit() or base.startswith("/dev/"):
        scheme, target = "device", base
    elif os.path.isdir(base):
        scheme, target = "folder", base
    elif os.path.isfile(base) or Path(base).suffix.lower() in VIDEO_SUFFIXES:
        scheme, target = "video", base
    else:
        raise CameraError(f"no camera, video file or image folder at {url!r}")
    return scheme, target, options


def open_camera(url: str) -> CameraSource:
    """The source `url` names (`split_camera_url`), in the mode its options ask for."""
    scheme, target, options = split_camera_url(url)
    try:
        return _source_class(scheme)(target, options)
    except (OSError, cv2.error) as exc:
        detail = (getattr(exc, "strerror", None) or str(exc)).strip().splitlines()[0]
        raise CameraError(f"cannot open camera {url}: {detail}") from None


# -- grabber ----------------------------------------------------------------------------------
class FrameGrabber:
    """Reads `source` in a thread and hands the newest frame to asyncio; owns the source.

    The thread starts with `start()` (or the first `next_frame`). `pace` (frames per second)
    plays a file or folder at a camera's rate instead of as fast as it decodes. A live camera
    that is lost (`CameraLost`) is reopened every `REOPEN_S` until it is back; both are news
    (`take_news`) for whoever reports the run."""

    JOIN_S = 2.0
    REOPEN_S = 0.5
    """How often a lost camera is tried again."""

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
        self._news: list[tuple[str, dict[str, Any]]] = []
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
                frame = self._read()
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

    def _read(self) -> Frame | None:
        """The source's next frame; a lost camera is reopened until it is back (or the grabber
        is closed: None)."""
        while not self._stop.is_set():
            try:
                return self.source.read()
            except CameraLost as lost:
                self._tell("camera_lost", reason=str(lost))
                since = time.monotonic()
                while not self._stop.wait(self.REOPEN_S):
                    try:
                        self.source.reopen()
                    except CameraError:
                        continue
                    self._tell("camera_back", after_s=round(time.monotonic() - since, 3))
                    break
        return None

    def _tell(self, kind: str, **fields: Any) -> None:
        with self._lock:
            self._news.append((kind, fields))

    def take_news(self) -> list[tuple[str, dict[str, Any]]]:
        """What happened to the camera since the last call: ("camera_lost", {"reason"}),
        ("camera_back", {"after_s"})."""
        with self._lock:
            news, self._news = self._news, []
        return news

    def counters(self) -> dict[str, int]:
        """Frames read and overwritten here, and what the source skipped."""
        return {"captured": self.captured, "dropped": self.dropped, **self.source.counters()}

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
