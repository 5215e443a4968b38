"""Perception beside the loop: the camera and the vision in a process of their own (the default)
or in threads of the edge, on frames the HIL renderer draws and real OpenCV analyses."""

from __future__ import annotations

import asyncio
import os
import pickle
import signal
import socket
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

from udan.edge.calibration import VisionError
from udan.edge.camera import (
    FRAME_THREAD_NICENESS,
    CameraError,
    FrameGrabber,
    attach_frames,
    open_camera,
)
from udan.edge.geometry import ArenaGeometry
from udan.edge.perception import (
    FrameRing,
    FrameTaken,
    Perception,
    PerceptionError,
    ProcessPerception,
    RingSpec,
    ThreadPerception,
    VisionSettings,
    _Server,
)
from udan.edge.vision import Scene
from udan.hil.render import Renderer
from udan.hil.vcam import VirtualCamera

GEOMETRY = ArenaGeometry()
CARS = {5: (2, 3), 6: (6, 5)}  # marker: (row, col)
LAYOUT = {"obstacle": [(4, 4)], "wall": [], "water": [(0, 4)], "target": []}
PERIOD_S = 0.025  # 40 FPS
SWEEP = 12
FRAMES = 60


@pytest.fixture(scope="module")
def arena_image() -> np.ndarray:
    cars = []
    for marker, (row, col) in CARS.items():
        x, y = GEOMETRY.cell_centre(row, col)
        cars.append((marker, x, y, 0.3))
    return Renderer(GEOMETRY).render(cars, LAYOUT)


def unique_name() -> str:
    return f"udan-test-{uuid.uuid4().hex[:10]}"


def perception_of(kind: str, camera: str) -> Perception:
    settings = VisionSettings(GEOMETRY, tuple(CARS))
    if kind == "process":
        return ProcessPerception(camera, settings)
    return ThreadPerception(FrameGrabber(open_camera(camera)), settings.build())


async def publish(cam: VirtualCamera, image: np.ndarray, count: int, stamps: list[int]) -> None:
    """``count`` frames at 40 FPS, each stamped with its capture time, then the end of the
    stream."""
    for _ in range(count):
        stamps.append(time.monotonic_ns())
        cam.publish(image, stamps[-1])
        await asyncio.sleep(PERIOD_S)
    await asyncio.sleep(0.2)  # the last frame's scene
    cam.close()


async def events_until_the_end(perception: Perception) -> list[FrameTaken | Scene]:
    events = []
    while (event := await perception.next_event(timeout=5.0)) is not None or not perception.ended:
        if event is not None:
            events.append(event)
    return events


@pytest.mark.parametrize("kind", ["process", "thread"])
async def test_scenes_of_rendered_frames_each_announced_before_it_comes(
    kind: str, arena_image: np.ndarray
) -> None:
    """A frame is told as taken before its scene, never after; scenes carry the writer's
    capture times; once the vision has swept the image, both cars are in their cells; every
    frame captured is a scene or counted as dropped."""
    with VirtualCamera(unique_name()) as cam:
        perception = perception_of(kind, f"virtual://{cam.name}")
        try:
            perception.wait_ready()
            assert perception.sweep_frames == SWEEP
            perception.start()
            stamps: list[int] = []
            writer = asyncio.ensure_future(publish(cam, arena_image, FRAMES, stamps))
            events = await events_until_the_end(perception)
            await writer
        finally:
            perception.close()
    scenes = [e for e in events if isinstance(e, Scene)]
    announced = [
        e
        for k, e in enumerate(events)
        if isinstance(e, Scene) and FrameTaken(e.frame_index, e.t_capture_ns) in events[:k]
    ]
    # a notice that arrives with its scene (the loop woke late) is not returned: never after it
    assert announced
    for k, taken in enumerate(events):
        if isinstance(taken, FrameTaken):
            assert all(s.frame_index < taken.index for s in events[:k] if isinstance(s, Scene))
    # most frames on a quiet machine; a saturated one drops many, and analyses what it takes
    assert len(scenes) >= 10
    assert [s.frame_index for s in scenes] == sorted({s.frame_index for s in scenes})
    assert all(s.t_capture_ns == stamps[s.frame_index - 1] for s in scenes)
    assert len(scenes) + perception.dropped == perception.captured <= FRAMES
    # the sweep reads a tile per frame analysed: by the last frames it has covered the image
    for scene in scenes[-3:]:
        assert scene.calibrated
        assert {m: c.cell for m, c in scene.cars.items()} == CARS
    assert scenes[-1].cells["obstacle"] == frozenset({(4, 4)})
    assert scenes[-1].cells["water"] == frozenset({(0, 4)})


@pytest.mark.parametrize("kind", ["process", "thread"])
async def test_frames_captured_before_the_cut_off_are_not_analysed(
    kind: str, arena_image: np.ndarray
) -> None:
    with VirtualCamera(unique_name()) as cam:
        perception = perception_of(kind, f"virtual://{cam.name}")
        try:
            perception.start()
            cut_off = 10_000
            perception.skip_before(cut_off)
            await asyncio.sleep(0.3)  # the cut-off reaches the perception process
            events = asyncio.ensure_future(events_until_the_end(perception))
            for k in range(12):  # stamps alternate stale and fresh
                cam.publish(arena_image, cut_off + (k if k % 2 else -k - 1))
                await asyncio.sleep(PERIOD_S * 2)
            cam.close()
            events = await events
        finally:
            perception.close()
    assert [e.t_capture_ns for e in events if isinstance(e, Scene)] == [
        cut_off + k for k in range(1, 12, 2)
    ]
    assert all(e.t_capture_ns >= cut_off for e in events)


def test_a_frame_the_camera_reuses_during_its_analysis_gives_no_scene(
    arena_image: np.ndarray,
) -> None:
    """The perception process is lent the camera's shared slot, not a copy: a frame whose slot
    the camera rewrote before the analysis ended is dropped and counted, never sent as a scene
    (its image may have been half one frame, half another)."""
    with VirtualCamera(unique_name(), slots=3) as cam:
        source = open_camera(f"virtual://{cam.name}")
        source.lend = True
        grabber = FrameGrabber(source)
        vision = VisionSettings(GEOMETRY, tuple(CARS)).build()
        analyse = vision.process

        def analyse_while_the_camera_laps(frame):
            scene = analyse(frame)
            if frame.index == 2:  # meanwhile the camera wrote three frames: 5 took 2's slot
                for _ in range(3):
                    cam.publish(arena_image)
            return scene

        vision.process = analyse_while_the_camera_laps
        edge, there = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        server = _Server(there, grabber, vision)
        serving = threading.Thread(target=server.serve)
        serving.start()
        messages = []
        try:
            for _ in range(2):
                cam.publish(arena_image)
                while (message := pickle.loads(edge.recv(1 << 16)))[0] != "scene":
                    messages.append(message)
                messages.append(message)
        finally:
            edge.send(pickle.dumps(("stop",)))
            serving.join(5.0)
            grabber.close()
            edge.close()
            there.close()
    scenes = [m[1].frame_index for m in messages if m[0] == "scene"]
    taken = [m[1] for m in messages if m[0] == "taken"]
    assert taken[:2] == [1, 2] and scenes[0] == 1 and 2 not in scenes
    assert scenes[1] in (3, 4, 5)
    assert server.overwritten == 1
    counts = messages[-1][-1]
    assert len(scenes) + counts["dropped"] <= counts["captured"] <= 5


def test_a_frame_is_remembered_for_the_recorder_before_its_scene_leaves(
    arena_image: np.ndarray,
) -> None:
    """The edge asks the perception process to keep a decision's frame as soon as it has the
    scene, and a thread of the perception process reads the ask at once, whatever its main
    thread is doing: the frame is remembered before the scene leaves, so even a main thread
    held up right after sending (here 50 ms) has every asked frame kept, none "not
    remembered"."""
    with VirtualCamera(unique_name(), slots=3) as cam:
        source = open_camera(f"virtual://{cam.name}")
        source.lend = True
        grabber = FrameGrabber(source)
        vision = VisionSettings(GEOMETRY, tuple(CARS)).build()
        edge, there = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        ring = FrameRing(RingSpec(unique_name()))
        server = _Server(there, grabber, vision, ring)
        send_scene = server.send_scene

        def send_then_stall(scene: Scene) -> None:
            send_scene(scene)
            time.sleep(0.05)

        server.send_scene = send_then_stall
        serving = threading.Thread(target=server.serve)
        serving.start()
        counts = {}
        try:
            for _ in range(4):
                cam.publish(arena_image)
                while (message := pickle.loads(edge.recv(1 << 16)))[0] != "scene":
                    pass
                edge.send(pickle.dumps(("keep", message[1].t_capture_ns)))
                time.sleep(0.1)
            edge.send(pickle.dumps(("skip_before", 0)))  # a message back with the counts
            cam.publish(arena_image)
            while (message := pickle.loads(edge.recv(1 << 16)))[0] != "scene":
                pass
            counts = message[-1]
        finally:
            edge.send(pickle.dumps(("stop",)))
            serving.join(5.0)
            grabber.close()
            ring.close()
            edge.close()
            there.close()
    assert counts["not_remembered"] == 0 and ring.missed == 0


def test_the_recorder_ring_copies_a_lent_frame_the_camera_cannot_overwrite() -> None:
    """The flight recorder's ring remembers lent frames by reference (no copy a frame) and
    copies the one a decision used out of its slot when asked: the copy keeps the frame after
    the camera reused the slot, and a frame whose slot was already reused is not kept (counted
    as not remembered), never recorded half one frame, half another."""
    with VirtualCamera(unique_name(), 32, 24, slots=3) as cam:
        source = open_camera(f"virtual://{cam.name}")
        source.lend = True
        ring = FrameRing(RingSpec(unique_name()))
        try:
            frames = []
            for k in (1, 2, 3):
                cam.publish(np.full((24, 32), k, np.uint8), 1000 + k)
                frames.append(source.read())
                ring.analysed(frames[-1])
            assert all(f.lease is not None for f in frames)
            assert ring.keep(1002)
            cam.publish(np.full((24, 32), 4, np.uint8), 1004)  # frame 4 takes frame 1's slot
            cam.publish(np.full((24, 32), 5, np.uint8), 1005)  # and 5 frame 2's
            assert not ring.keep(1001) and ring.missed == 1
            buf, layout = attach_frames(ring.spec.decided)
            number, _ = layout.find(buf, 1002)
            image, t_ns = layout.read(buf, number)
            assert t_ns == 1002 and (image == 2).all()
            assert layout.latest(buf) == 1  # the reused frame was not kept
            buf.close()
        finally:
            ring.close()
            source.close()


@pytest.mark.parametrize(
    ("camera", "error", "says"),
    [
        ("/dev/video97", CameraError, "camera device /dev/video97 does not exist"),
        ("/no/such/place.mp4", CameraError, "video file not found"),
        ("virtual://nobody-renders-this", CameraError, "'nobody-renders-this' not found"),
    ],
)
def test_a_camera_the_perception_process_cannot_open_is_its_one_line_error(
    camera: str, error: type[Exception], says: str
) -> None:
    perception = ProcessPerception(camera)
    with pytest.raises(error) as raised:
        perception.wait_ready()
    perception.close()
    assert says in str(raised.value) and "\n" not in str(raised.value)


def test_a_bad_calibration_file_is_a_vision_error_from_the_perception_process(
    tmp_path: Path,
) -> None:
    bad = tmp_path / "camera.yaml"
    bad.write_text("%YAML:1.0\nnot_a_camera: 1\n")
    with pytest.raises(VisionError) as raised:
        VisionSettings(calibration_file=str(bad)).build()
    perception = ProcessPerception(str(tmp_path), VisionSettings(calibration_file=str(bad)))
    with pytest.raises(VisionError) as remote:
        perception.wait_ready()
    perception.close()
    assert str(remote.value) == str(raised.value)


@pytest.mark.parametrize("kind", ["process", "thread"])
async def test_folders_and_videos_play_to_their_end(tmp_path: Path, kind: str) -> None:
    folder = tmp_path / "shots"
    folder.mkdir()
    video = tmp_path / "clip.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 25, (64, 48))
    for k in range(6):
        cv2.imwrite(str(folder / f"{k:02d}.png"), np.full((48, 64), 30 * k, np.uint8))
        writer.write(np.full((48, 64, 3), 30 * k, np.uint8))
    writer.release()
    for camera in (str(folder), str(video)):
        perception = perception_of(kind, camera)
        try:
            perception.start()
            events = await events_until_the_end(perception)
        finally:
            perception.close()
        scenes = [e for e in events if isinstance(e, Scene)]
        assert perception.captured == 6, camera
        assert len(scenes) + perception.dropped == 6
        assert scenes[-1].frame_index == 5 and not scenes[-1].calibrated


@pytest.mark.parametrize("kind", ["process", "thread"])
async def test_a_read_error_mid_stream_is_raised_in_the_edge(tmp_path: Path, kind: str) -> None:
    folder = tmp_path / "broken"
    folder.mkdir()
    cv2.imwrite(str(folder / "0.png"), np.zeros((48, 64), np.uint8))
    (folder / "1.png").write_bytes(b"garbage")
    perception = perception_of(kind, str(folder))
    try:
        perception.start()
        with pytest.raises(CameraError, match="cannot read image"):
            await events_until_the_end(perception)
    finally:
        perception.close()


async def test_a_killed_perception_process_is_an_error_at_the_next_wait(
    arena_image: np.ndarray,
) -> None:
    with VirtualCamera(unique_name()) as cam:
        perception = ProcessPerception(f"virtual://{cam.name}", VisionSettings(GEOMETRY))
        try:
            perception.start()
            cam.publish(arena_image)
            assert await perception.next_event(timeout=5.0) is not None  # it runs
            os.kill(perception.pid, signal.SIGKILL)
            with pytest.raises(PerceptionError, match=r"ended mid-run \(killed by SIGKILL\)"):
                while True:
                    await perception.next_event(timeout=5.0)
        finally:
            perception.close()


def _nice(pid: int, tid: int) -> int:
    """A thread's niceness (/proc/PID/task/TID/stat, field 19)."""
    stat = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
    return int(stat.rsplit(")", 1)[1].split()[16])


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="Linux /proc")
async def test_the_perception_process_yields_to_the_edge_loop(arena_image: np.ndarray) -> None:
    """Capture and vision have a frame period, a command its 10 ms deadline: both threads of the
    perception process run nicer than the edge's loop, as the frame threads did in it."""
    with VirtualCamera(unique_name()) as cam:
        perception = ProcessPerception(f"virtual://{cam.name}")
        try:
            perception.start()
            cam.publish(arena_image)
            assert await perception.next_event(timeout=5.0) is not None
            pid = perception.pid
            nice = [_nice(pid, int(t.name)) for t in Path(f"/proc/{pid}/task").iterdir()]
        finally:
            perception.close()
    loop = os.getpriority(os.PRIO_PROCESS, 0)
    assert len(nice) >= 2 and set(nice) == {min(loop + FRAME_THREAD_NICENESS, 19)}


EDGE = textwrap.dedent(
    """
    import sys, time
    from udan.edge.perception import ProcessPerception

    perception = ProcessPerception(sys.argv[1])
    perception.wait_ready()
    print(perception.pid, flush=True)
    time.sleep(60)
    """
)


def _running(pid: int) -> bool:
    """Whether a process runs (a zombie, exited but not yet reaped, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_the_perception_process_ends_when_its_edge_is_killed(tmp_path: Path) -> None:
    """No orphan: whatever ends the edge, even SIGKILL, closes its end of the socket."""
    cv2.imwrite(str(tmp_path / "0.png"), np.zeros((48, 64), np.uint8))
    edge = subprocess.Popen(
        [sys.executable, "-c", EDGE, str(tmp_path)], stdout=subprocess.PIPE, text=True
    )
    try:
        child = int(edge.stdout.readline())
        assert _running(child)
        edge.kill()
        edge.wait(10)
        deadline = time.monotonic() + 10
        while _running(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _running(child)
    finally:
        edge.kill()
