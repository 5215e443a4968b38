"""GenICam cameras (GigE Vision, USB3 Vision) through Aravis: ``--camera aravis://DEVICE``.

The lab cameras of the paper's platform (a MindVision GigE camera, 1920x1200 at 40 FPS) speak
GenICam, which OpenCV cannot open; Aravis is the open-source GenICam stack on Linux. It comes
with the ``gige`` extra (``pip install 'udan-edge[gige]'``: the ``aravis-python`` wheel with
libaravis and its GObject typelib, and PyGObject, which needs GObject introspection's system
libraries; docs/lab-setup.md says which). This module is imported only when an ``aravis://``
URL is opened, like every other source of :mod:`udan.edge.camera`.

``DEVICE`` is what ``Aravis.Camera.new`` takes: a device id (``Vendor-Model-Serial``), a serial
or an IP address; empty means the first camera found. The URL's options set the mode through
the GenICam standard features (region, ``PixelFormat``, ``AcquisitionFrameRate``,
``ExposureTime``, ``Gain``); a value outside a feature's range is refused before it is sent.

- **Capture time**: a buffer carries the camera's timestamp on the camera's own clock. It is
  mapped onto this host's monotonic clock (:class:`DeviceClock`) by the camera's timestamp
  latch where it has one (the host's clock read around a latch command gives the offset, renewed
  every `LATCH_PERIOD_S`), or, for a camera that stamps with this host's realtime clock (Aravis's
  own fake camera, ``clock=realtime``), through the realtime clock; failing both, a frame is
  stamped when its first packet arrived (``clock=arrival``: its age then leaves out exposure and
  transfer).
- **Incomplete buffers** (stream packets lost and not resent in time) are counted and never
  returned: no sighting is ever taken from half a frame.
- **The newest frame**: the driver keeps `BUFFERS` buffers; a read takes every buffer that is
  ready and keeps the newest complete one (the older ones are counted as stale).
- **A camera that goes away** (no frame for `LOST_AFTER_S` and no answer on its control
  channel) raises :class:`~udan.edge.camera.CameraLost`; :meth:`AravisSource.reopen` connects
  again when it answers.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from udan.edge.camera import CameraError, CameraLost, CameraMode, CameraOptions, CameraSource

BUFFERS = 4
"""Buffers queued with the driver: enough to hold a frame being filled while others wait."""
POP_TIMEOUT_S = 0.1
"""How long one wait for a buffer lasts (a stop is noticed within it)."""
LOST_AFTER_S = 1.0
"""No complete frame for this long and no answer on the control channel: the camera is lost."""
LATCH_PERIOD_S = 10.0
"""How often the camera's clock is latched again (clocks drift apart by parts per million)."""
LATCH_SAMPLES = 5
"""Latches of which the one read back fastest gives the offset (the tightest bracket)."""
_LATCHES = (
    ("TimestampLatch", "TimestampLatchValue"),  # SFNC 2.x
    ("GevTimestampControlLatch", "GevTimestampValue"),  # GigE Vision 1.x
)
_BAYER = {  # GenICam names the top-left 2x2 block; OpenCV the one at (1, 1)
    "BayerRG8": cv2.COLOR_BayerBG2GRAY,
    "BayerGB8": cv2.COLOR_BayerGR2GRAY,
    "BayerGR8": cv2.COLOR_BayerGB2GRAY,
    "BayerBG8": cv2.COLOR_BayerRG2GRAY,
}
_WIDE_MONO = {"Mono10": 2, "Mono12": 4, "Mono14": 6, "Mono16": 8}  # bits to drop
_COLOUR = {"RGB8": cv2.COLOR_RGB2GRAY, "BGR8": cv2.COLOR_BGR2GRAY}
READABLE_FORMATS = ("Mono8", *_WIDE_MONO, *_BAYER, *_COLOUR)
"""Pixel formats the edge turns into grayscale frames."""


def _aravis() -> tuple[Any, Any]:
    """(Aravis, GLib) from the ``gige`` extra; a one-line `CameraError` without it."""
    try:
        import aravis  # the wheel loads libaravis and points GObject at its typelib
        from gi.repository import GLib
    except (ImportError, ValueError) as err:
        raise CameraError(
            f"aravis:// needs the GenICam extra ({err}): pip install 'udan-edge[gige]' "
            "(docs/lab-setup.md)"
        ) from None
    return aravis.Aravis, GLib


def to_gray(data: bytes, width: int, height: int, pixel_format: str) -> np.ndarray:
    """A grayscale uint8 image from a buffer's image bytes in a `READABLE_FORMATS` format."""
    if pixel_format == "Mono8":
        return np.frombuffer(data, np.uint8, width * height).reshape(height, width)
    if pixel_format in _WIDE_MONO:
        wide = np.frombuffer(data, "<u2", width * height).reshape(height, width)
        return (wide >> _WIDE_MONO[pixel_format]).astype(np.uint8)
    if pixel_format in _BAYER:
        raw = np.frombuffer(data, np.uint8, width * height).reshape(height, width)
        return cv2.cvtColor(raw, _BAYER[pixel_format])
    if pixel_format in _COLOUR:
        rgb = np.frombuffer(data, np.uint8, width * height * 3).reshape(height, width, 3)
        return cv2.cvtColor(rgb, _COLOUR[pixel_format])
    raise CameraError(f"pixel format {pixel_format}: the edge reads {', '.join(READABLE_FORMATS)}")


class FrameIds:
    """GigE Vision 1.x frame ids (16 bits, 0 unused, 65535 followed by 1) as one increasing
    count, so frame numbers keep their order over a run of hours and show lost frames as gaps."""

    def __init__(self) -> None:
        self._last: int | None = None
        self._base = 0

    def unwrap(self, frame_id: int) -> int:
        """The increasing number of the frame with id ``frame_id``."""
        if self._last is not None and frame_id < self._last - 0x8000:
            self._base += 0xFFFF
        self._last = frame_id
        return self._base + frame_id


@dataclass(frozen=True)
class LatchSample:
    """One latch of the camera's clock, bracketed by this host's monotonic clock."""

    host_before_ns: int
    device_ns: int
    host_after_ns: int

    @property
    def spread_ns(self) -> int:
        """How long the latch's round trip took: the offset is known to half of it."""
        return self.host_after_ns - self.host_before_ns

    @property
    def offset_ns(self) -> int:
        """Host monotonic minus device time, at the middle of the round trip."""
        return (self.host_before_ns + self.host_after_ns) // 2 - self.device_ns


class DeviceClock:
    """Maps a camera's buffer timestamps onto this host's monotonic clock.

    ``latch``: from the latch samples given (:meth:`add_latch`), the offset of the one with the
    tightest bracket among the last `LATCH_SAMPLES`. ``realtime``: the camera's clock is this
    host's realtime clock, whose offset from the monotonic one is read at each mapping (it moves
    when NTP steps the realtime clock). ``arrival``: the frame's arrival on the realtime clock
    (Aravis's system timestamp) mapped the same way."""

    KINDS = ("latch", "realtime", "arrival")

    def __init__(self, kind: str) -> None:
        if kind not in self.KINDS:
            raise ValueError(f"unknown clock {kind!r}")
        self.kind = kind
        self._samples: deque[LatchSample] = deque(maxlen=LATCH_SAMPLES)

    def add_latch(self, sample: LatchSample) -> None:
        self._samples.append(sample)

    @property
    def offset_ns(self) -> int | None:
        """The latch offset in use (None before the first latch)."""
        if not self._samples:
            return None
        return min(self._samples, key=lambda s: s.spread_ns).offset_ns

    def to_host(self, device_ns: int, system_ns: int) -> int:
        """Host monotonic time of a buffer stamped ``device_ns`` by the camera that arrived at
        ``system_ns`` (realtime clock)."""
        if self.kind == "latch":
            offset = self.offset_ns
            if offset is None:
                raise RuntimeError("no latch sample yet")
            return device_ns + offset
        realtime_to_host = time.monotonic_ns() - time.time_ns()
        return (device_ns if self.kind == "realtime" else system_ns) + realtime_to_host


class AravisSource(CameraSource):
    """``aravis://DEVICE``: a GenICam camera through Aravis; see the module docstring."""

    OPTIONS = frozenset(
        {"width", "height", "fps", "format", "exposure_us", "gain", "clock", "strict"}
    )
    KIND = "a GenICam camera"

    def __init__(self, target: str, options: CameraOptions | None = None) -> None:
        super().__init__(f"aravis://{target}", options or CameraOptions())
        self.device = target or None
        self.incomplete = 0
        """Buffers that arrived with packets missing: counted, never analysed."""
        self._aravis, self._glib = _aravis()
        self._ids = FrameIds()
        self._cam: Any = None
        self._stream: Any = None
        self._stamp_of: tuple[int, int] = (0, 0)
        self._open()

    # -- opening -----------------------------------------------------------------------------
    def _name(self) -> str:
        return self.device or "(the first one found)"

    def _open(self) -> None:
        try:
            self._cam = self._aravis.Camera.new(self.device)
        except self._glib.Error as err:
            raise CameraError(
                f"GenICam camera {self._name()} does not answer: {err.message}"
            ) from None
        try:
            self._configure()
            self._start()
        except self._glib.Error as err:
            raise CameraError(f"GenICam camera {self._name()}: {err.message}") from None

    def _refuse(self, what: str, value: float, bounds: Any) -> None:
        if not bounds.min <= value <= bounds.max:
            raise CameraError(
                f"GenICam camera {self._name()} refuses {what}={value:g} "
                f"(it takes {bounds.min:g}-{bounds.max:g})"
            )

    def _configure(self) -> None:
        """Set the asked mode through the standard features, read back the granted one, and
        choose how capture times are mapped."""
        cam, o, auto_off = self._cam, self.options, self._aravis.Auto.OFF
        if o.format is not None:
            offered = list(cam.dup_available_pixel_formats_as_strings())
            if o.format not in offered:
                raise CameraError(
                    f"GenICam camera {self._name()} refuses format={o.format} "
                    f"(it offers {', '.join(offered)})"
                )
            cam.set_pixel_format_from_string(o.format)
        if o.width is not None or o.height is not None:
            _, _, width, height = cam.get_region()
            self._refuse("width", o.width or width, cam.get_width_bounds())
            self._refuse("height", o.height or height, cam.get_height_bounds())
            cam.set_region(0, 0, o.width or width, o.height or height)
        if o.fps is not None:
            self._refuse("fps", o.fps, cam.get_frame_rate_bounds())
            cam.set_frame_rate(o.fps)
        if o.exposure_us is not None:
            self._refuse("exposure_us", o.exposure_us, cam.get_exposure_time_bounds())
            if cam.is_exposure_auto_available():
                cam.set_exposure_time_auto(auto_off)
            cam.set_exposure_time(o.exposure_us)
        if o.gain is not None:
            self._refuse("gain", o.gain, cam.get_gain_bounds())
            if cam.is_gain_auto_available():
                cam.set_gain_auto(auto_off)
            cam.set_gain(o.gain)
        _, _, width, height = cam.get_region()
        pixel_format = cam.get_pixel_format_as_string()
        if pixel_format not in READABLE_FORMATS:
            raise CameraError(
                f"GenICam camera {self._name()} sends {pixel_format}; the edge reads "
                f"{', '.join(READABLE_FORMATS)} (set format= in the camera URL)"
            )
        self._format = pixel_format
        self._clock = DeviceClock(self._choose_clock())
        self._granted(
            CameraMode(
                width=width,
                height=height,
                fps=cam.get_frame_rate() if cam.is_frame_rate_available() else None,
                format=pixel_format,
                exposure_us=cam.get_exposure_time() if cam.is_exposure_time_available() else None,
                gain=cam.get_gain() if cam.is_gain_available() else None,
                clock=self._clock.kind,
            )
        )
        if self._clock.kind == "latch":
            for _ in range(LATCH_SAMPLES):
                self._latch()

    def _latch_features(self) -> tuple[str, str] | None:
        device = self._cam.get_device()
        for command, value in _LATCHES:
            if device.get_feature(command) is not None and device.get_feature(value) is not None:
                return command, value
        return None

    def _choose_clock(self) -> str:
        """``clock`` as asked, or for ``auto`` the best this camera offers: its latch, else the
        realtime clock for Aravis's own fake camera (it stamps buffers with it), else arrival."""
        asked = self.options.clock
        latch = self._latch_features()
        if asked == "latch" and latch is None:
            raise CameraError(
                f"GenICam camera {self._name()} has no timestamp latch (clock=latch); use "
                "clock=arrival"
            )
        if asked in ("auto", "latch") and latch is not None:
            return "latch"
        fake = (self._cam.get_vendor_name(), self._cam.get_model_name()) == ("Aravis", "Fake")
        if asked == "realtime" or (asked == "auto" and fake):
            return "realtime"
        return "arrival"

    def _latch(self) -> None:
        """One latch of the camera's clock into the mapping."""
        command, value = self._latch_features()
        device = self._cam.get_device()
        frequency = 1e9
        if device.get_feature("GevTimestampTickFrequency") is not None:
            frequency = float(device.get_integer_feature_value("GevTimestampTickFrequency"))
        before = time.monotonic_ns()
        device.execute_command(command)
        ticks = device.get_integer_feature_value(value)
        after = time.monotonic_ns()
        self._clock.add_latch(LatchSample(before, round(ticks * 1e9 / frequency), after))
        self._latched_at = time.monotonic()

    def _start(self) -> None:
        self._stream = self._cam.create_stream(None, None)
        payload = self._cam.get_payload()
        for _ in range(BUFFERS):
            self._stream.push_buffer(self._aravis.Buffer.new_allocate(payload))
        self._cam.start_acquisition()
        self._heard_at = time.monotonic()

    # -- reading -----------------------------------------------------------------------------
    def _newest(self, buffer: Any) -> Any | None:
        """Of ``buffer`` and every other one ready now, the newest complete one (the others go
        back to the driver, counted as incomplete or stale); None if none is complete."""
        success = self._aravis.BufferStatus.SUCCESS
        newest = None
        while buffer is not None:
            if buffer.get_status() != success:
                self.incomplete += 1
                self._stream.push_buffer(buffer)
            else:
                if newest is not None:
                    self.stale += 1
                    self._stream.push_buffer(newest)
                newest = buffer
            buffer = self._stream.try_pop_buffer()
        return newest

    def _read(self) -> np.ndarray | None:
        while not self._stopping.is_set():
            buffer = self._stream.timeout_pop_buffer(round(POP_TIMEOUT_S * 1e6))
            buffer = None if buffer is None else self._newest(buffer)
            if buffer is None:
                if time.monotonic() - self._heard_at > LOST_AFTER_S:
                    self._lost()
                continue
            self._heard_at = time.monotonic()
            try:
                width, height = buffer.get_image_width(), buffer.get_image_height()
                image = to_gray(buffer.get_image_data(), width, height, self._format)
                self._stamp_of = (
                    self._clock.to_host(buffer.get_timestamp(), buffer.get_system_timestamp()),
                    self._ids.unwrap(buffer.get_frame_id()),
                )
            finally:
                self._stream.push_buffer(buffer)
            if self._clock.kind == "latch" and time.monotonic() - self._latched_at > LATCH_PERIOD_S:
                self._latch()
            return image
        return None

    def _lost(self) -> None:
        """No complete frame for `LOST_AFTER_S`: the stream is lost (a camera that went away
        answers no control request either, but finding that out takes Aravis's retries, about
        5 s; one that still answers is restarted just the same)."""
        raise CameraLost(
            f"GenICam camera {self._name()} lost: no complete frame for {LOST_AFTER_S:g} s"
        )

    def _stamp(self, arrival_ns: int) -> tuple[int, int]:
        return self._stamp_of

    def counters(self) -> dict[str, int]:
        return {"stale": self.stale, "incomplete": self.incomplete}

    def reopen(self) -> None:
        """Connect again. The old connection is let go in a thread of its own: to a camera
        that went away, stopping it and letting go of its stream wait out Aravis's timeouts
        (about 5 s), which must not hold up the new one."""
        if self._cam is not None:
            old, self._cam, self._stream = (self._cam, self._stream), None, None
            threading.Thread(target=self._release, args=old, daemon=True).start()
        self._open()

    def _release(self, cam: Any, stream: Any) -> None:
        """Stop ``cam``; it and ``stream`` are let go when this returns."""
        with contextlib.suppress(self._glib.Error):
            cam.stop_acquisition()

    def _close(self) -> None:
        if self._cam is not None:
            self._release(self._cam, self._stream)
            self._cam = self._stream = None

    # -- probe -------------------------------------------------------------------------------
    def describe(self) -> dict[str, Any]:
        """The camera's identity, the modes it offers and its controls' ranges."""
        cam = self._cam
        sensor = cam.get_sensor_size()

        def bounds(available: bool, getter: str) -> list[float] | None:
            if not available:
                return None
            b = getattr(cam, getter)()
            return [b.min, b.max]

        return {
            "device": cam.get_device_id(),
            "vendor": cam.get_vendor_name(),
            "model": cam.get_model_name(),
            "serial": cam.get_device_serial_number(),
            "sensor": [sensor.width, sensor.height],
            "formats": list(cam.dup_available_pixel_formats_as_strings()),
            "width": [*bounds(True, "get_width_bounds"), cam.get_width_increment()],
            "height": [*bounds(True, "get_height_bounds"), cam.get_height_increment()],
            "fps": bounds(cam.is_frame_rate_available(), "get_frame_rate_bounds"),
            "exposure_us": bounds(cam.is_exposure_time_available(), "get_exposure_time_bounds"),
            "exposure_auto": cam.is_exposure_auto_available(),
            "gain": bounds(cam.is_gain_available(), "get_gain_bounds"),
            "gain_auto": cam.is_gain_auto_available(),
            "clocks": ["latch"] * (self._latch_features() is not None) + ["realtime", "arrival"],
        }
