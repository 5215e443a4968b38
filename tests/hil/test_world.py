"""The HIL world's camera: a process of its own drawing a mirror of the world the cars move in."""

from __future__ import annotations

import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from udan.edge.camera import open_camera
from udan.edge.geometry import ArenaGeometry
from udan.edge.vision import Vision
from udan.envs.rules import OBSTACLE, RIGHT
from udan.hil.world import CameraProcess, HilWorld

pytestmark = pytest.mark.hil

MARKERS = {1: 10, 2: 11}


def test_a_mirror_fed_by_the_listener_draws_the_same_world() -> None:
    world = HilWorld(ArenaGeometry(), MARKERS, cell_time_s=0.2)
    mirror = HilWorld(ArenaGeometry(), MARKERS, cell_time_s=0.2)
    world.listener = mirror.restore
    layout = np.zeros((9, 9), np.uint8)
    layout[4, 4] = OBSTACLE
    world.place(layout, {1: (0, 0)})
    world.add(2, (8, 8))
    world.begin(1, (0, 0), RIGHT)
    now = time.monotonic_ns()
    assert mirror.snapshot(now) == world.snapshot(now)
    assert world.move(1, (0, 0), RIGHT) == (0, 1)
    world.remove(2)
    assert mirror.snapshot(now) == world.snapshot(now)
    cars, cells = mirror.snapshot(now)
    assert [c[0] for c in cars] == [10] and cells["obstacle"] == [(4, 4)]


def test_the_camera_process_shows_the_world_and_stops_cleanly() -> None:
    world = HilWorld(ArenaGeometry(), MARKERS, cell_time_s=0.2)
    world.place(np.zeros((9, 9), np.uint8), {1: (2, 3)})
    name = f"udan-test-{uuid.uuid4().hex[:8]}"
    config = {
        "model": {"noise_sigma": 2.0},
        "geometry": ArenaGeometry(),
        "name": name,
        "fps": 40.0,
        "markers": MARKERS,
        "cell_time_s": 0.2,
    }
    camera = CameraProcess(world, config)
    try:
        with pytest.raises(OSError, match="already exists"):
            CameraProcess(world, config)  # a second writer of the same camera
        world.add(2, (6, 7))  # a change after start reaches the camera
        vision = Vision(car_markers=MARKERS.values())
        seen: dict[int, tuple[int, int]] = {}
        with open_camera(f"virtual://{name}") as source:
            deadline = time.monotonic() + 20
            while len(seen) < 2 and time.monotonic() < deadline:
                frame = source.read()
                if frame is not None:
                    scene = vision.process(frame)
                    seen = {m: s.cell for m, s in scene.cars.items()}
        assert seen == {10: (2, 3), 11: (6, 7)}
    finally:
        summary = camera.stop()
    assert summary["frames"] > 0
    assert not Path(f"/dev/shm/{name}").exists()
