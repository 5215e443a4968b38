"""Camera sources, the frame grabber, and the virtual camera across two real processes."""

import asyncio
import os
import subprocess
import sys
import textwrap
import threading
import time
import uuid
from pathlib import Path

import cv2
import numpy as np
import pytest

from udan.edge.camera import (
    FRAME_THREAD_NICENESS,
    CameraError,
    CameraLost,
    CameraMode,
    CameraOptions,
    CameraSource,
    FrameGrabber,
    StaleGuard,
    fourcc_text,
    mode_mismatches,
    open_camera,
    shm_path,
    split_camera_url,
    v4l2_capture_ns,
)
from udan.hil.vcam import VirtualCamera


def write_images(folder, count, shape=(48, 64)):
    """Colour PNGs whose pixels all equal their number, named so sorting matters."""
    folder.mkdir(exist_ok=True)
    for k in range(count):
        img = np.full((*shape, 3), 10 * k % 256, np.uint8)
        cv2.imwrite(str(folder / f"img_{k:03d}.png"), img)
    (folder / "notes.txt").write_text("not an image")
    return folder


def unique_name():
    return f"udan-test-{uuid.uuid4().hex[:10]}"


def one_line_error(url):
    with pytest.raises(CameraError) as err:
        open_camera(url)
    message = str(err.value)
    assert "\n" not in message and message
    return message


# -- file sources --------------------------------------------------------------------------
def test_folder_plays_images_in_order_as_grayscale(tmp_path):
    folder = write_images(tmp_path / "shots", 4)
    with open_camera(str(folder)) as cam:
        frames = list(cam)
    assert [f.index for f in frames] == [0, 1, 2, 3]
    assert [int(f.image[0, 0]) for f in frames] == [0, 10, 20, 30]
    assert all(f.image.shape == (48, 64) and f.image.dtype == np.uint8 for f in frames)
    times = [f.t_capture_ns for f in frames]
    assert times == sorted(times) and times[-1] <= time.monotonic_ns()


def test_video_file(tmp_path):
    path = tmp_path / "clip.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25, (64, 48))
    for k in range(6):
        writer.write(np.full((48, 64, 3), 40 * k, np.uint8))
    writer.release()
    with open_camera(str(path)) as cam:
        frames = list(cam)
    assert len(frames) == 6
    assert frames[0].image.ndim == 2
    assert abs(int(frames[5].image.mean()) - 200) < 8


@pytest.mark.parametrize(
    ("url", "says"),
    [
        ("/dev/video97", "camera device /dev/video97 does not exist"),
        ("97", "cannot open camera device 97"),
        ("/dev/null", "cannot open camera device /dev/null"),
        ("ftp://camera", "unknown camera scheme ftp://"),
        ("/no/such/place.mp4", "video file not found"),
        ("/no/such/place", "no camera, video file or image folder"),
        ("virtual://nobody-renders-this", "virtual camera 'nobody-renders-this' not found"),
    ],
)
def test_bad_cameras_are_one_line_errors(url, says):
    assert says in one_line_error(url)


def test_empty_folder_and_undecodable_video(tmp_path):
    (tmp_path / "empty").mkdir()
    assert "no images" in one_line_error(str(tmp_path / "empty"))
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"this is not a video" * 100)
    assert "cannot open video file" in one_line_error(str(junk))


def test_unknown_scheme_lists_the_known_ones():
    message = one_line_error("rtsp://10.0.0.1/stream")
    for scheme in ("device://", "folder://", "video://", "virtual://"):
        assert scheme in message


# -- camera options, granted modes, timestamps ---------------------------------------------
def test_the_url_is_the_one_place_a_mode_is_set():
    scheme, target, options = split_camera_url(
        "/dev/video0?width=1920&height=1080&fps=30&format=MJPG&exposure_us=2000&gain=4&strict=1"
    )
    assert (scheme, target) == ("device", "/dev/video0")
    assert options == CameraOptions(1920, 1080, 30.0, "MJPG", 2000.0, 4.0, "auto", True)
    assert options.given == {
        "width": 1920, "height": 1080, "fps": 30.0, "format": "MJPG", "exposure_us": 2000.0,
        "gain": 4.0, "strict": True,
    }  # fmt: skip
    scheme, target, options = split_camera_url("aravis://192.168.1.20?fps=40&clock=latch")
    assert (scheme, target, options.fps, options.clock) == ("aravis", "192.168.1.20", 40.0, "latch")
    assert split_camera_url("/dev/video2")[2] == CameraOptions()


def test_a_path_with_a_question_mark_is_taken_whole(tmp_path):
    folder = write_images(tmp_path / "what?width=3", 1)
    assert split_camera_url(str(folder))[:2] == ("folder", str(folder))


@pytest.mark.parametrize(
    ("url", "says"),
    [
        ("/dev/video0?whidth=640", "unknown camera option 'whidth' (known: width, height, fps"),
        ("/dev/video0?width=wide", "camera option width=wide: not a positive integer"),
        ("/dev/video0?width=-640", "camera option width=-640: not a positive integer"),
        ("/dev/video0?fps=0", "camera option fps=0: not a positive number"),
        ("/dev/video0?gain=-1", "camera option gain=-1: not a number >= 0"),
        ("/dev/video0?clock=ntp", "camera option clock=ntp: not one of auto, latch, realtime"),
        ("/dev/video0?strict=yes", "camera option strict=yes: not 0 or 1"),
        ("/dev/video0?format=M%20JPG", "not a pixel format name"),
        ("/dev/video0?width=640&width=800", "camera option 'width' must be given once"),
        ("/dev/video0?width", "camera option 'width' must be given once, as width=VALUE"),
        ("/dev/video0?format=MJPEG", "a V4L2 pixel format is a FourCC of four characters"),
        ("/dev/video0?clock=latch", "a V4L2 camera stamps frames with its driver's clock"),
        ("/dev/video97?width=640", "camera device /dev/video97 does not exist"),
    ],
)
def test_bad_camera_options_are_one_line_errors(url, says):
    assert says in one_line_error(url)


def test_sources_without_a_mode_refuse_options(tmp_path):
    folder = write_images(tmp_path / "shots", 2)
    message = one_line_error(f"folder://{folder}?width=640")
    assert message == (
        "camera option width: an image folder takes none (a mode is set on live cameras: "
        "/dev/videoN, aravis://)"
    )
    with VirtualCamera(unique_name(), 32, 24) as cam:
        assert "the virtual camera takes none" in one_line_error(f"virtual://{cam.name}?fps=40")
        with open_camera(f"virtual://{cam.name}") as source:
            assert source.mode == CameraMode(32, 24, format="Mono8", clock="render")


def test_a_granted_mode_is_compared_with_the_asked_one():
    asked = CameraOptions(width=1920, height=1200, fps=40.0, format="Mono8", exposure_us=2000.0)
    granted = CameraMode(1920, 1200, 40.2, "mono8", 2010.0, 0.0)  # drivers round their steps
    assert mode_mismatches(asked, granted) == []
    granted = CameraMode(1280, 720, 30.0, "YUYV", None, 0.0)
    assert mode_mismatches(asked, granted) == [
        "width 1920 asked, 1280 granted",
        "height 1200 asked, 720 granted",
        "fps 40 asked, 30 granted",
        "format Mono8 asked, YUYV granted",
        "exposure_us 2000 asked, none granted",
    ]
    assert mode_mismatches(CameraOptions(), granted) == []  # nothing asked, nothing to miss


class _Granting(CameraSource):
    """A camera driver's answer, as a source that grants what it is given."""

    OPTIONS = frozenset({"width", "fps", "strict"})
    KIND = "a test camera"

    def __init__(self, options: CameraOptions, granted: CameraMode) -> None:
        super().__init__("test://", options)
        self._granted(granted)


def test_a_mode_granted_otherwise_warns_or_with_strict_fails():
    granted = CameraMode(640, 480, 30.0)
    source = _Granting(CameraOptions(width=1920, fps=40.0), granted)
    assert source.mode == granted
    assert source.warnings == ["width 1920 asked, 640 granted", "fps 40 asked, 30 granted"]
    with pytest.raises(CameraError) as err:
        _Granting(CameraOptions(width=1920, strict=True), granted)
    assert str(err.value) == (
        "test://: the camera did not grant the mode asked: width 1920 asked, 640 granted"
    )


def test_a_v4l2_buffer_timestamp_is_the_capture_time_when_it_is_on_the_monotonic_clock():
    arrival = 5_000_000_000_000  # 5000 s after boot
    assert v4l2_capture_ns(4_999_962.5, arrival) == 4_999_962_500_000  # 37.5 ms old
    assert v4l2_capture_ns(0.0, arrival) is None  # not set (OpenCV's first frame)
    assert v4l2_capture_ns(5_000_001.0, arrival) is None  # in the future: another clock
    assert v4l2_capture_ns(1_700_000_000_000.0, arrival) is None  # realtime: the future here
    assert v4l2_capture_ns(4_990_000.0, arrival) is None  # 10 s old: not a live frame's time


def test_fourcc_text():
    assert fourcc_text(cv2.VideoWriter_fourcc(*"MJPG")) == "MJPG"
    assert fourcc_text(cv2.VideoWriter_fourcc(*"GREY")) == "GREY"
    assert fourcc_text(0) is None


def test_a_frame_that_waited_in_the_queue_is_stale():
    guard = StaleGuard(period_ns=25_000_000)
    ages_ms = [12, 13, 12.5, 30, 36.9, 37.1, 12, 60, 14]  # the youngest: 12 ms
    assert [guard.stale(round(a * 1e6)) for a in ages_ms] == [
        False, False, False, False, False, True, False, True, False,
    ]  # fmt: skip


class _Unplugged(CameraSource):
    """A live camera that is unplugged after three frames and answers again at the third try
    to reopen it."""

    def __init__(self) -> None:
        super().__init__("test://unplugged")
        self.opened = 1
        self.tries = 0

    def _read(self):
        if self._stopping.is_set():
            return None
        if self._count == 3 * self.opened:
            raise CameraLost("test camera: unplugged")
        time.sleep(0.005)
        return np.full((4, 4), self.opened, np.uint8)

    def reopen(self) -> None:
        self.tries += 1
        if self.tries < 3:
            raise CameraError("test camera: not there")
        self.opened += 1


async def test_a_lost_camera_is_reopened_when_it_returns_and_both_are_news(monkeypatch):
    monkeypatch.setattr(FrameGrabber, "REOPEN_S", 0.01)
    source = _Unplugged()
    grabber = FrameGrabber(source)
    seen = []
    while len(seen) < 5:
        frame = await grabber.next_frame(timeout=5.0)
        assert frame is not None
        seen.append(int(frame.image[0, 0]))
    grabber.close()
    assert seen[0] == 1 and seen[-1] == 2
    news = grabber.take_news()
    assert [kind for kind, _ in news] == ["camera_lost", "camera_back"]
    assert news[0][1] == {"reason": "test camera: unplugged"}
    assert source.tries == 3 and news[1][1]["after_s"] >= 0.02
    assert grabber.take_news() == []


# -- grabber -------------------------------------------------------------------------------
async def test_grabber_newest_frame_wins_and_counts_drops(tmp_path):
    """A consumer slower than the source gets ever newer frames; everything it skipped is
    counted as dropped, nothing is lost from the accounting."""
    folder = write_images(tmp_path / "many", 40)
    grabber = FrameGrabber(open_camera(str(folder)), pace=400)
    got = []
    while (frame := await grabber.next_frame(timeout=2.0)) is not None:
        got.append(frame.index)
        await asyncio.sleep(0.02)
    grabber.close()
    assert got == sorted(set(got)) and got[-1] == 39
    assert grabber.captured == 40
    assert grabber.dropped > 0
    assert len(got) + grabber.dropped == grabber.captured
    assert grabber.ended


@pytest.mark.skipif(not hasattr(os, "setpriority"), reason="Unix niceness")
async def test_the_capture_thread_yields_to_the_event_loop(tmp_path):
    """Capture has a frame period to finish, a command its 10 ms deadline: the capture thread
    runs nicer than the loop that dispatches."""
    folder = write_images(tmp_path / "nice", 3)
    grabber = FrameGrabber(open_camera(str(folder)), pace=20)
    assert await grabber.next_frame(timeout=2.0) is not None
    capture = os.getpriority(os.PRIO_PROCESS, grabber._thread.native_id)
    loop = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    grabber.close()
    assert capture == min(loop + FRAME_THREAD_NICENESS, 19)


async def test_grabber_pace_and_timeout(tmp_path):
    folder = write_images(tmp_path / "paced", 5)
    grabber = FrameGrabber(open_camera(str(folder)), pace=50)
    t0 = time.monotonic()
    got = [await grabber.next_frame(timeout=1.0) for _ in range(5)]
    assert [f.index for f in got] == [0, 1, 2, 3, 4]
    assert time.monotonic() - t0 >= 4 / 50 * 0.9
    assert await grabber.next_frame(timeout=0.2) is None
    grabber.close()


async def test_grabber_raises_a_read_error(tmp_path):
    folder = write_images(tmp_path / "broken", 2)
    (folder / "img_001.png").write_bytes(b"garbage")
    grabber = FrameGrabber(open_camera(str(folder)))
    assert (await grabber.next_frame(timeout=2.0)).index == 0
    with pytest.raises(CameraError, match="cannot read image"):
        await grabber.next_frame(timeout=2.0)
    grabber.close()


async def test_grabber_waits_on_a_silent_camera_and_closes():
    """No frame yet is a timeout, not the end; closing stops the blocked reader promptly."""
    with VirtualCamera(unique_name(), 32, 24) as cam:
        grabber = FrameGrabber(open_camera(f"virtual://{cam.name}"))
        assert await grabber.next_frame(timeout=0.05) is None
        assert not grabber.ended
        cam.publish(np.full((24, 32), 7, np.uint8), 123)
        frame = await grabber.next_frame(timeout=1.0)
        assert (frame.index, frame.t_capture_ns, int(frame.image[0, 0])) == (1, 123, 7)
        t0 = time.monotonic()
        grabber.close()
        assert time.monotonic() - t0 < 1.0


def test_wait_frame_blocks_a_thread_until_a_frame_a_timeout_or_a_stop():
    """The perception process's main thread runs no event loop: it waits on the grabber."""
    with VirtualCamera(unique_name(), 32, 24) as cam:
        grabber = FrameGrabber(open_camera(f"virtual://{cam.name}"))
        assert grabber.wait_frame(0.05) is None and not grabber.ended
        cam.publish(np.full((24, 32), 9, np.uint8), 456)
        frame = grabber.wait_frame(1.0)
        assert (frame.index, frame.t_capture_ns, int(frame.image[0, 0])) == (1, 456, 9)
        threading.Timer(0.1, grabber.stop).start()
        t0 = time.monotonic()
        assert grabber.wait_frame(5.0) is None
        assert time.monotonic() - t0 < 1.0
        grabber.close()


# -- the virtual camera ----------------------------------------------------------------------
WRITER = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from udan.hil.vcam import VirtualCamera

    name, count, period = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
    with VirtualCamera(name, 64, 48) as cam:
        print("ready", flush=True)
        sys.stdin.readline()
        for k in range(1, count + 1):
            t_ns = time.monotonic_ns()
            image = np.full((48, 64), k % 256, np.uint8)
            image[0, :8] = np.frombuffer(t_ns.to_bytes(8, "little"), np.uint8)
            cam.publish(image, t_ns)
            time.sleep(period)
    """
)


def start_writer(name, count, period):
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, name, str(count), str(period)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
    )
    assert proc.stdout.readline().strip() == "ready"
    return proc


def stamp(frame):
    return int.from_bytes(frame.image[0, :8].tobytes(), "little")


def test_virtual_camera_across_processes():
    """Another process renders; this one reads every frame with the writer's capture time,
    and the stream ends when the writer closes, which also removes the shared memory."""
    name = unique_name()
    proc = start_writer(name, 30, 0.01)
    try:
        cam = open_camera(f"virtual://{name}")
        proc.stdin.write("go\n")
        proc.stdin.flush()
        frames = list(cam)
        cam.close()
    finally:
        proc.communicate(timeout=10)
    assert proc.returncode == 0
    indices = [f.index for f in frames]  # a busy reader may skip one: newest wins
    assert indices == sorted(set(indices)) and indices[-1] == 30 and len(indices) >= 20
    assert all(int(f.image[5, 5]) == f.index for f in frames)
    assert all(f.t_capture_ns == stamp(f) for f in frames)
    assert not shm_path(name).exists()


async def test_virtual_camera_newest_frame_wins_across_processes():
    name = unique_name()
    proc = start_writer(name, 200, 0.002)
    try:
        grabber = FrameGrabber(open_camera(f"virtual://{name}"))
        grabber.start()
        proc.stdin.write("go\n")
        proc.stdin.flush()
        got = []
        while (frame := await grabber.next_frame(timeout=5.0)) is not None:
            assert frame.t_capture_ns == stamp(frame)
            got.append(frame.index)
            await asyncio.sleep(0.015)
        grabber.close()
    finally:
        proc.communicate(timeout=10)
    assert got == sorted(set(got)) and got[-1] == 200
    assert grabber.dropped > 0
    assert len(got) + grabber.dropped == grabber.captured


def test_camera_faults_drop_and_stall():
    image = np.zeros((24, 32), np.uint8)
    with VirtualCamera(unique_name(), 32, 24, drop_probability=0.5, seed=1) as cam:
        reader = open_camera(f"virtual://{cam.name}")
        seen = []
        for _ in range(40):
            if cam.publish(image):
                seen.append(reader.read().index)
        assert cam.published + cam.faulted == cam.frames == 40
        assert 5 < cam.faulted < 35
        assert len(seen) == cam.published
        assert seen == sorted(seen) and seen[-1] - seen[0] + 1 > len(seen)  # gaps show
        cam.drop_probability = 0.0
        cam.stall(0.2)
        assert not cam.publish(image)
        time.sleep(0.25)
        assert cam.publish(image)
        reader.close()


def test_virtual_camera_name_is_exclusive_and_recording(tmp_path):
    video = tmp_path / "run.mp4"
    with VirtualCamera(unique_name(), 64, 48, video=video, fps=20) as cam:
        with pytest.raises(FileExistsError, match="already exists"):
            VirtualCamera(cam.name, 64, 48)
        for k in range(5):
            cam.publish(np.full((48, 64), 50 * k, np.uint8))
        with pytest.raises(ValueError, match="expected a uint8 48x64"):
            cam.publish(np.zeros((10, 10), np.uint8))
    with open_camera(str(video)) as replay:
        frames = list(replay)
    assert len(frames) == 5
    assert abs(int(frames[4].image.mean()) - 200) < 8


def test_a_lent_frame_is_the_slot_itself_until_the_camera_reuses_it():
    """A consumer that checks ``Frame.intact`` is lent the shared slot, no copy; the frame says
    when the writer has begun to reuse it, and a copy taken before that is the frame's own."""
    with VirtualCamera(unique_name(), 32, 24, slots=3) as cam:
        reader = open_camera(f"virtual://{cam.name}")
        reader.lend = True
        cam.publish(np.full((24, 32), 1, np.uint8))
        frame = reader.read()
        assert not frame.image.flags.owndata and frame.lease is not None
        own = frame.owned()
        assert own.lease is None and own.intact() and own.image.flags.owndata
        for k in (2, 3):
            cam.publish(np.full((24, 32), k, np.uint8))
            assert frame.intact() and int(frame.image[0, 0]) == 1
        cam.publish(np.full((24, 32), 4, np.uint8))  # frame 4 takes frame 1's slot
        assert not frame.intact() and frame.owned() is None
        assert int(own.image[0, 0]) == 1
        copying = open_camera(f"virtual://{cam.name}")
        assert copying.read().lease is None  # a consumer that did not ask gets a copy
        copying.close()
        reader.close()


def _voluntary_switches(thread: threading.Thread) -> int:
    status = Path(f"/proc/self/task/{thread.native_id}/status").read_text()
    return int(status.split("voluntary_ctxt_switches:")[1].split()[0])


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="Linux /proc")
def test_a_reader_sleeps_until_the_writer_rings_instead_of_polling():
    """A waiting reader sleeps on the frame counter (a futex the writer wakes after each frame):
    a second without frames costs it a handful of wake-ups, not the 2,000 of a 0.5 ms poll,
    and a frame wakes it at once."""
    with VirtualCamera(unique_name(), 32, 24) as cam:
        reader = open_camera(f"virtual://{cam.name}")
        got = []
        thread = threading.Thread(target=lambda: got.append(reader.read()))
        thread.start()
        time.sleep(0.1)
        before = _voluntary_switches(thread)
        time.sleep(1.0)
        woken = _voluntary_switches(thread) - before
        t_ns = time.monotonic_ns()
        cam.publish(np.full((24, 32), 5, np.uint8), t_ns)
        thread.join(5.0)
        reader.close()
    assert woken <= 30
    assert got[0].t_capture_ns == t_ns and int(got[0].image[0, 0]) == 5
