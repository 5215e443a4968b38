"""GenICam cameras through Aravis: a real GigE Vision stream on loopback (Aravis's fake camera,
fed the virtual camera's frames by ``python -m udan.hil.gige``), and the pieces the source
shares with any camera (frame ids, the clock mapping, pixel formats) on synthetic buffers."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest

from udan.edge.camera import CameraError, CameraLost, FrameGrabber, open_camera
from udan.edge.genicam import DeviceClock, FrameIds, LatchSample, to_gray
from udan.hil.gige import held
from udan.hil.vcam import VirtualCamera

PATTERN = np.random.default_rng(7).integers(0, 256, (480, 640), np.uint8)
CAMERA = "aravis://127.0.0.1?width=640&height=480&fps=40"


# -- on synthetic buffers ------------------------------------------------------------------
def test_gige_frame_ids_unwrap_into_one_increasing_count():
    ids = FrameIds()
    raw = [65533, 65534, 65535, 1, 2, 4, 65535, 1]  # 3 lost; then a long gap past one wrap
    assert [ids.unwrap(i) for i in raw] == [
        65533, 65534, 65535, 65536, 65537, 65539, 2 * 65535, 2 * 65535 + 1,
    ]  # fmt: skip


def test_a_latch_maps_the_camera_clock_with_the_tightest_bracket():
    clock = DeviceClock("latch")
    with pytest.raises(RuntimeError):
        clock.to_host(0, 0)
    # the camera's clock runs 7 s behind the host's monotonic one; round trips of 3, 0.4, 1 ms
    offset = 7_000_000_000
    for before, spread in ((100_000_000, 3_000_000), (200_000_000, 400_000), (300_000_000, 10**6)):
        device = before + spread // 2 - offset + 150_000  # the latch 0.15 ms after the middle
        clock.add_latch(LatchSample(before, device, before + spread))
    assert LatchSample(0, 0, 400_000).spread_ns == 400_000
    assert clock.offset_ns == offset - 150_000  # from the 0.4 ms bracket
    assert clock.to_host(5_000_000_000, 0) == 5_000_000_000 + offset - 150_000


def test_a_camera_on_the_realtime_clock_and_arrival_times_map_onto_monotonic():
    realtime, monotonic = time.time_ns(), time.monotonic_ns()
    exposed = realtime - 20_000_000  # 20 ms ago, by the realtime clock
    host = DeviceClock("realtime").to_host(exposed, realtime)
    assert abs(host - (monotonic - 20_000_000)) < 2_000_000
    host = DeviceClock("arrival").to_host(123, realtime - 5_000_000)
    assert abs(host - (monotonic - 5_000_000)) < 2_000_000
    with pytest.raises(ValueError):
        DeviceClock("ptp")


def test_pixel_formats_become_the_same_grayscale_image():
    gray = PATTERN[:8, :12]
    assert np.array_equal(to_gray(gray.tobytes(), 12, 8, "Mono8"), gray)
    wide = gray.astype("<u2") << 8
    assert np.array_equal(to_gray(wide.tobytes(), 12, 8, "Mono16"), gray)
    assert np.array_equal(to_gray((wide >> 4).tobytes(), 12, 8, "Mono12"), gray)
    bgr = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    rgb = bgr[..., ::-1].copy()
    assert np.array_equal(to_gray(rgb.tobytes(), 12, 8, "RGB8"), gray)
    # a flat colour seen through a Bayer filter: GenICam names the first 2x2 block, OpenCV the
    # one at (1, 1); each name must come out as the same gray
    r, g, b = 200, 100, 40
    expected = cv2.cvtColor(np.full((1, 1, 3), (b, g, r), np.uint8), cv2.COLOR_BGR2GRAY)[0, 0]
    for name, (top_left, top_right, bottom_left, bottom_right) in {
        "BayerRG8": (r, g, g, b), "BayerGB8": (g, b, r, g),
        "BayerGR8": (g, r, b, g), "BayerBG8": (b, g, g, r),
    }.items():  # fmt: skip
        mosaic = np.tile(np.array([[top_left, top_right], [bottom_left, bottom_right]], np.uint8),
                         (8, 8))  # fmt: skip
        out = to_gray(mosaic.tobytes(), 16, 16, name)
        assert abs(int(out[6, 6]) - int(expected)) <= 2, name
    with pytest.raises(CameraError, match="the edge reads Mono8"):
        to_gray(b"", 1, 1, "YUV422_8")


def test_held_frames_alternate_in_blocks():
    assert held(123, 0)  # no blocks: every frame
    assert [held(t * 500_000_000, 1_000_000_000) for t in range(5)] == [
        True, True, False, False, True,
    ]  # fmt: skip


# -- a real GigE Vision stream on loopback ---------------------------------------------------
@contextmanager
def gige(
    *args: str,
    pattern: np.ndarray = PATTERN,
    draw: Callable[[int, np.ndarray], object] | None = None,
) -> Iterator[subprocess.Popen]:
    """A virtual camera publishing ``pattern`` (or what ``draw(t_ns, out)`` draws) at 40 FPS,
    served by the fake GigE camera."""
    height, width = pattern.shape
    draw = draw or (lambda t, out: np.copyto(out, pattern))
    with VirtualCamera(f"udan-test-{uuid.uuid4().hex[:10]}", width, height) as vcam:
        stop = threading.Event()
        render = threading.Thread(target=vcam.run, args=(draw,), kwargs={"stop": stop})
        render.start()
        proc = start_bridge(vcam.name, *args)
        try:
            yield proc
        finally:
            proc.terminate()
            proc.wait(30)
            stop.set()
            render.join()


def start_bridge(camera_name: str, *args: str) -> subprocess.Popen:
    proc = subprocess.Popen(
        [sys.executable, "-m", "udan.hil.gige", "--camera-name", camera_name, *args],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert proc.stdout.readline().startswith('{"ready": true'), "the fake camera did not start"
    return proc


def test_the_mode_asked_in_the_url_is_set_read_back_and_frames_arrive_intact():
    with gige(), open_camera(f"{CAMERA}&exposure_us=3000&gain=2") as source:
        assert source.mode is not None and source.warnings == []
        mode = source.mode
        assert (mode.width, mode.height, mode.fps, mode.format) == (640, 480, 40.0, "Mono8")
        assert (mode.exposure_us, mode.gain, mode.clock) == (3000.0, 2.0, "realtime")
        frames = [source.read() for _ in range(10)]
        described = source.describe()
    assert all(np.array_equal(f.image, PATTERN) for f in frames)
    indices = [f.index for f in frames]
    assert indices == sorted(indices) and len(set(indices)) == 10
    # stamped by the camera (its frame clock), mapped onto this host's monotonic clock: a frame
    # arrives after it was exposed, and not long after on an idle loopback
    ages_ms = [(f.t_arrival_ns - f.t_capture_ns) / 1e6 for f in frames]
    assert all(0 < a < 500 for a in ages_ms), ages_ms
    assert described["vendor"] == "Aravis" and described["model"] == "Fake"
    assert "Mono8" in described["formats"] and described["width"][:2] == [1, 2048]
    assert described["fps"] == [0.1, 1000.0] and described["clocks"] == ["realtime", "arrival"]


def test_the_probe_lists_the_cameras_modes_and_controls():
    calibrate = str(Path(sys.executable).with_name("udan-calibrate"))
    with gige():
        done = subprocess.run(
            [calibrate, "probe", "--camera", "aravis://127.0.0.1?width=800&height=600&fps=30"],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0] == "camera aravis://127.0.0.1"
    assert lines[1].startswith("  mode: 800x600 at 30") and "Mono8" in lines[1]
    assert lines[2] == "  asked: width=800&height=600&fps=30"
    assert "  formats: ['BayerBG8', 'BayerGB8', 'BayerGR8', 'BayerRG8', 'Mono8'" in done.stdout
    assert "  fps: [0.1, 1000.0]" in lines and "  clocks: ['realtime', 'arrival']" in lines


@pytest.mark.parametrize(
    ("options", "says"),
    [
        ("width=5000", "GenICam camera 127.0.0.1 refuses width=5000 (it takes 1-2048)"),
        ("fps=5000", "refuses fps=5000 (it takes 0.1-1000)"),
        ("format=YUV422_8", "refuses format=YUV422_8 (it offers BayerBG8"),
        ("clock=latch", "has no timestamp latch (clock=latch); use clock=arrival"),
        ("format=Mono8&exposure_us=1", "refuses exposure_us=1 (it takes 10-1e+07)"),
    ],
)
def test_a_mode_the_camera_refuses_is_a_one_line_error(options, says):
    with gige(), pytest.raises(CameraError) as err:
        open_camera(f"aravis://127.0.0.1?{options}")
    assert says in str(err.value) and "\n" not in str(err.value)


def test_a_camera_that_does_not_answer_is_a_one_line_error():
    with pytest.raises(CameraError) as err:
        open_camera("aravis://10.255.255.1")  # nobody there (a reserved, unrouted address)
    assert str(err.value).startswith("GenICam camera 10.255.255.1 does not answer: ")


def test_incomplete_frames_are_counted_and_never_returned():
    """At 1 % of stream packets lost (a 640x480 frame is 220 packets) almost no frame arrives
    whole (one in nine); those that do are returned whole, the others only counted. Read until
    three whole frames and ten incomplete ones have come (three whole ones alone came after
    only eight incomplete in one run in ten)."""
    with gige("--lost-ratio", "0.01"), open_camera(CAMERA) as source:
        frames = []
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and (
            len(frames) < 3 or source.counters()["incomplete"] < 10
        ):
            try:
                frames.append(source.read())
            except CameraLost:
                break  # no whole frame for a second: the stream counts as lost
        incomplete = source.counters()["incomplete"]
    assert incomplete >= 10 and frames
    assert all(np.array_equal(f.image, PATTERN) for f in frames)


async def test_an_unplugged_camera_is_lost_then_reopened_when_it_returns():
    with VirtualCamera(f"udan-test-{uuid.uuid4().hex[:10]}", 640, 480) as vcam:
        stop = threading.Event()
        render = threading.Thread(
            target=vcam.run, args=(lambda t, out: np.copyto(out, PATTERN),), kwargs={"stop": stop}
        )
        render.start()
        bridge = start_bridge(vcam.name)
        grabber = FrameGrabber(open_camera(CAMERA))
        try:
            assert await grabber.next_frame(timeout=5.0) is not None
            bridge.kill()  # unplugged: no word to anyone
            bridge.wait()
            unplugged = time.monotonic()
            news: list = []
            while not news:
                await grabber.next_frame(timeout=0.1)  # the newest frame from before, or none
                news += grabber.take_news()
                assert time.monotonic() - unplugged < 10, "the loss was never noticed"
            assert news == [
                ("camera_lost", {"reason": "GenICam camera 127.0.0.1 lost: no complete frame "
                                           "for 1 s"})
            ]  # fmt: skip
            bridge = start_bridge(vcam.name)
            frame = None
            while frame is None:
                frame = await grabber.next_frame(timeout=1.0)
                assert time.monotonic() - unplugged < 30, "the camera was never reopened"
            assert [kind for kind, _ in grabber.take_news()] == ["camera_back"]
            assert np.array_equal(frame.image, PATTERN)
        finally:
            grabber.close()
            bridge.terminate()
            bridge.wait(30)
            stop.set()
            render.join()


def test_a_picture_older_than_the_lag_allowed_keeps_its_capture_time():
    """A starved renderer (here: one render takes 400 ms) leaves the fake camera serving an old
    picture at every tick of its frame clock; past ``--max-lag-ms`` the frame carries the
    picture's own capture time, so the source finds it stale instead of reading an old scene as
    new. Each picture carries its capture time in its first 8 pixels: no frame returned shows a
    picture more than the lag older than its timestamp."""
    stalls = iter([False] * 20 + [True])

    def draw(t_ns: int, out: np.ndarray) -> None:
        np.copyto(out, PATTERN)
        out[0, :8] = np.frombuffer(np.int64(t_ns).tobytes(), np.uint8)
        if next(stalls, False):
            time.sleep(0.4)

    with gige("--max-lag-ms", "50", draw=draw), open_camera(CAMERA) as source:
        frames = [source.read() for _ in range(60)]
        stale = source.counters()["stale"]
    lags_ms = [
        (f.t_capture_ns - int(np.frombuffer(f.image[0, :8].tobytes(), np.int64)[0])) / 1e6
        for f in frames
    ]
    assert max(lags_ms) <= 50 + 2, lags_ms  # (the clock mapping's error: well under 2 ms)
    assert stale >= 5  # the 400 ms stall's ticks: their frames came old, skipped and counted
