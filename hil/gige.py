"""The virtual camera as a real GigE Vision camera on loopback: ``python -m udan.hil.gige``.

Aravis's fake camera (``ArvGvFakeCamera``) speaks GigE Vision on 127.0.0.1 — GVCP control,
GVSP stream packets over UDP — so the edge's ``aravis://127.0.0.1`` source meets the same
protocol stack a lab's camera puts on the wire. Its fill-pattern hook is given the HIL's
rendered frames here: each buffer gets the newest frame of the virtual camera ``--camera-name``
when the fake camera's frame clock fires, and keeps the timestamp the fake camera gave it then
(its exposure; the rendered picture may be up to one render period older). A picture older than
``--max-lag-ms`` at that instant (a renderer starved on a loaded host) keeps its own capture time
instead, so the frame says how old it is (the edge finds it stale) rather than showing an old
scene as new: a real camera exposes at its timestamp. The hook is set through
ctypes on the wheel's own libaravis (through PyGObject, a Python callback given to
``set_fill_pattern`` hangs the camera), and it serves Mono8, the renderer's format.

Faults a camera has on a real network, on request: ``--lost-ratio`` drops stream packets at
random (the fake camera does not resend them: at 1920x1200 and 1400-byte packets a ratio of
1.35e-4 leaves about a fifth of the frames incomplete); ``--delay-ms`` holds frames that long
between their timestamp and their first packet, as a slow camera or network would: all of them,
or with ``--delay-block-s B`` those of every other block of B seconds on the monotonic clock
(``int(t / B)`` even), so frames held and not held alternate in one run and a frame's capture
time says which it was. Killing this process is a camera unplugged.

The GigE Vision control port is fixed (3956), so one fake camera can serve loopback at a time:
a second one waits for the first to end (a lock file), so test runs never take each other's
camera.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import fcntl
import importlib.util
import json
import math
import os
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from udan.edge.camera import CameraError, attach_frames
from udan.edge.sidecar import exit_with_parent
from udan.envs.errors import OneLineParser
from udan.hil.world import CAMERA_NICENESS

PROG = "python -m udan.hil.gige"
LOCK = Path(tempfile.gettempdir()) / "udan-gige-loopback.lock"
"""Held by the fake camera serving loopback (its control port is the standard's, 3956)."""
LOCK_WAIT_S = 600.0
"""Longest a second fake camera waits for the first to end."""
HOLD_AWAKE_S = 0.003
"""The end of a frame's hold (``--delay-ms``) the stream thread waits awake, not asleep."""
MONO8 = 0x01080001
"""ArvPixelFormat of Mono8 (GenICam's PFNC value), the one format this camera fills."""
_FILL = ctypes.CFUNCTYPE(
    None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint32
)


class GigeError(RuntimeError):
    """The fake camera could not be started; one line."""


def libaravis() -> ctypes.CDLL:
    """The libaravis the ``aravis-python`` wheel ships (the ``gige`` extra)."""
    spec = importlib.util.find_spec("aravis")
    if spec is None or not spec.submodule_search_locations:
        raise GigeError("the fake GigE camera needs the gige extra: pip install 'udan-edge[gige]'")
    path = Path(next(iter(spec.submodule_search_locations))) / "lib" / "libaravis-0.8.so"
    lib = ctypes.CDLL(str(path))
    lib.arv_gv_fake_camera_new.restype = ctypes.c_void_p
    lib.arv_gv_fake_camera_new.argtypes = [ctypes.c_char_p, ctypes.c_char_p]
    lib.arv_gv_fake_camera_is_running.argtypes = [ctypes.c_void_p]
    lib.arv_gv_fake_camera_get_fake_camera.restype = ctypes.c_void_p
    lib.arv_gv_fake_camera_get_fake_camera.argtypes = [ctypes.c_void_p]
    lib.arv_fake_camera_set_fill_pattern.argtypes = [
        ctypes.c_void_p, _FILL, ctypes.c_void_p, ctypes.c_void_p
    ]  # fmt: skip
    lib.arv_buffer_set_timestamp.argtypes = [ctypes.c_void_p, ctypes.c_uint64]
    lib.arv_buffer_get_data.restype = ctypes.c_void_p
    lib.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
    for name in ("arv_buffer_get_image_width", "arv_buffer_get_image_height"):
        getattr(lib, name).argtypes = [ctypes.c_void_p]
    return lib


def hold(seconds: float) -> None:
    """Wait ``seconds``, the last ``HOLD_AWAKE_S`` of them awake: a camera's hold is its own
    hardware's, and a sleeping thread on a busy host wakes late (in a loaded test run, with
    the hold asleep, the edge measured a 5 ms hold as 7.3 ms)."""
    until = time.monotonic() + seconds
    time.sleep(max(0.0, seconds - HOLD_AWAKE_S))
    while time.monotonic() < until:
        pass


def held(t_ns: int, block_ns: int) -> bool:
    """Whether a frame captured at ``t_ns`` is held: always without blocks, else in every other
    block of ``block_ns``."""
    return block_ns == 0 or (t_ns // block_ns) % 2 == 0


class GigeCamera:
    """A fake GigE Vision camera on loopback serving the virtual camera ``camera_name``."""

    def __init__(
        self,
        camera_name: str,
        serial: str = "UDAN-HIL",
        *,
        lost_ratio: float = 0.0,
        delay_s: float = 0.0,
        delay_block_s: float = 0.0,
        max_lag_s: float = math.inf,
    ) -> None:
        self.delay_s = delay_s
        self.max_lag_ns = max_lag_s * 1e9
        self.delay_block_ns = round(delay_block_s * 1e9)
        self.served = 0
        """Buffers filled with a rendered frame."""
        self.delayed = 0
        self.old = 0
        """Buffers whose picture was older than ``max_lag_s``: stamped with its capture time."""
        self.failed = 0
        """Buffers the hook could not fill (no frame yet, an error)."""
        self._buf, self._layout = attach_frames(camera_name)
        self._lib = libaravis()
        self._gobject = ctypes.CDLL("libgobject-2.0.so.0")
        self._gobject.g_object_set.restype = None
        self._gobject.g_object_unref.argtypes = [ctypes.c_void_p]
        self._hook = _FILL(self._fill)  # kept: libaravis holds only its address
        self._camera = self._lib.arv_gv_fake_camera_new(b"lo", serial.encode())
        if not self._camera or not self._lib.arv_gv_fake_camera_is_running(self._camera):
            raise GigeError("the fake GigE camera did not start on lo (port 3956 taken?)")
        if lost_ratio:
            self._gobject.g_object_set(
                ctypes.c_void_p(self._camera), b"gvsp-lost-ratio", ctypes.c_double(lost_ratio),
                None,
            )  # fmt: skip
        fake = self._lib.arv_gv_fake_camera_get_fake_camera(self._camera)
        self._lib.arv_fake_camera_set_fill_pattern(fake, self._hook, None, None)

    @property
    def ended(self) -> bool:
        """The virtual camera has stopped publishing."""
        return self._layout.closed(self._buf)

    def _newest(self) -> tuple[np.ndarray, int] | None:
        for _ in range(3):  # the renderer may reuse the slot while it is copied
            got = self._layout.read(self._buf, self._layout.latest(self._buf))
            if got is not None:
                return got
        return None

    def _fill(self, buffer: int, _data: int, _exposure: int, _gain: int, pixel_format: int) -> None:
        """The fake camera's fill hook, in its stream thread, after it stamped the buffer with
        its frame clock (this host's realtime clock): the newest rendered frame (restamped with
        its capture time when older than ``max_lag_ns``), then the delay asked for."""
        stamped_ns = time.monotonic_ns()  # the fake camera stamped the buffer just before
        try:
            lib = self._lib
            width = lib.arv_buffer_get_image_width(buffer)
            height = lib.arv_buffer_get_image_height(buffer)
            got = self._newest()
            if got is None or pixel_format != MONO8:
                self.failed += 1
                return
            image, captured_ns = got
            if stamped_ns - captured_ns > self.max_lag_ns:
                self.old += 1
                realtime_ns = captured_ns + time.time_ns() - time.monotonic_ns()
                lib.arv_buffer_set_timestamp(buffer, realtime_ns)
            if image.shape != (height, width):
                image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
            # the buffer holds the payload of the mode the stream started in; its own size
            # says how much was received, nothing yet
            data = lib.arv_buffer_get_data(buffer, None)
            ctypes.memmove(data, np.ascontiguousarray(image).ctypes.data, width * height)
            self.served += 1
            if self.delay_s and held(stamped_ns, self.delay_block_ns):
                self.delayed += 1
                hold(self.delay_s)
        except Exception:  # nothing may raise into C: the frame goes out unfilled, counted
            self.failed += 1

    def close(self) -> None:
        if self._camera:
            self._gobject.g_object_unref(ctypes.c_void_p(self._camera))
            self._camera = None
        self._buf.close()


def hold_loopback(wait_s: float = LOCK_WAIT_S) -> int:
    """Take the loopback camera lock (waiting for another fake camera to end); its fd."""
    fd = os.open(LOCK, os.O_CREAT | os.O_RDWR, 0o666)
    deadline = time.monotonic() + wait_s
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return fd
        except BlockingIOError:
            if time.monotonic() > deadline:
                raise GigeError(
                    f"another fake GigE camera held loopback for {wait_s:g} s"
                ) from None
            time.sleep(0.1)


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--camera-name", required=True, help="the virtual camera to serve")
    p.add_argument("--serial", default="UDAN-HIL", help="the camera's serial number")
    p.add_argument("--lost-ratio", type=float, default=0.0, help="stream packets dropped")
    p.add_argument("--delay-ms", type=float, default=0.0, help="hold frames this long")
    p.add_argument("--delay-block-s", type=float, default=0.0,
                   help="hold frames in every other block of this many seconds")  # fmt: skip
    p.add_argument("--max-lag-ms", type=float, default=math.inf,
                   help="a picture older than this keeps its own capture time")  # fmt: skip
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Serve until SIGTERM or the virtual camera's end; print a ready line, then counts."""
    exit_with_parent()  # udan-hil run asks: its end is our SIGTERM, however it ended
    args = _parser().parse_args(argv)
    if (
        not 0.0 <= args.lost_ratio <= 1.0
        or min(args.delay_ms, args.delay_block_s) < 0
        or not args.max_lag_ms > 0
    ):
        print(f"{PROG}: error: --lost-ratio in [0, 1], --delay-ms and --delay-block-s >= 0, "
              "--max-lag-ms > 0", file=sys.stderr)  # fmt: skip
        return 2
    os.nice(CAMERA_NICENESS)  # a camera: below the cars and the edge, as the renderer
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        hold_loopback()
        camera = GigeCamera(
            args.camera_name, args.serial, lost_ratio=args.lost_ratio,
            delay_s=args.delay_ms / 1000, delay_block_s=args.delay_block_s,
            max_lag_s=args.max_lag_ms / 1000,
        )  # fmt: skip
    except (GigeError, CameraError, OSError) as err:
        print(f"{PROG}: error: {err}", file=sys.stderr)
        return 2
    print(json.dumps({"ready": True, "address": "127.0.0.1", "serial": args.serial}), flush=True)
    try:
        while not stop.wait(0.1) and not camera.ended:
            pass
    finally:
        counts = {"served": camera.served, "delayed": camera.delayed, "old": camera.old,
                  "failed": camera.failed}  # fmt: skip
        camera.close()
    with contextlib.suppress(BrokenPipeError):
        print(json.dumps(counts), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
