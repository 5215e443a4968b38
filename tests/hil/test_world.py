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
from udan.envs.rules import OBSTACLE
from udan.firmware_mock.motor import Pose, Trajectory
from udan.hil.world import CameraProcess, HilWorld

pytestmark = pytest.mark.hil

MARKERS = {1: 10, 2: 11}


def _grid_move(cell: tuple[int, int], to: tuple[int, int], t0: int) -> Trajectory:
    """A controller's plan of a grid move in one cell time (200 ms), at constant speed."""
    g = ArenaGeometry()
    start, end = Pose(*g.cell_centre(*cell), 0.0), Pose(*g.cell_centre(*to), 0.0)
    return Trajectory(start, end, t0, 200_000_000)


def test_a_mirror_fed_by_the_listener_draws_the_same_world() -> None:
    world = HilWorld(ArenaGeometry(), MARKERS)
    mirror = HilWorld(ArenaGeometry(), MARKERS)
    world.listener = mirror.restore
    layout = np.zeros((9, 9), np.uint8)
    layout[4, 4] = OBSTACLE
    world.place(layout, {1: (0, 0)})
    world.add(2, (8, 8))
    now = time.monotonic_ns()
    world.begin(1, _grid_move((0, 0), (0, 1), now))
    assert mirror.snapshot(now) == world.snapshot(now)
    assert world.end(1) and world.state()["pose"]["1"] == [0, 1]
    world.remove(2)
    assert mirror.snapshot(now) == world.snapshot(now)
    cars, cells = mirror.snapshot(now)
    assert [c[0] for c in cars] == [10] and cells["obstacle"] == [(4, 4)]


def test_the_camera_process_shows_the_world_and_stops_cleanly() -> None:
    world = HilWorld(ArenaGeometry(), MARKERS)
    world.place(np.zeros((9, 9), np.uint8), {1: (2, 3)})
    name = f"udan-test-{uuid.uuid4().hex[:8]}"
    config = {
        "model": {"noise_sigma": 2.0},
        "geometry": ArenaGeometry(),
        "name": name,
        "fps": 40.0,
        "markers": MARKERS,
        "realtime": False,
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


def test_the_simulation_plays_the_edges_slot_order() -> None:
    """The reference simulation seats its agents in the slots the edge gave the cars (the order
    they joined): identity order is the plain simulation, and an episode's record names it."""
    from udan.hil.harness import simulate, slot_order
    from udan.hil.world import Episode

    record = {"slots": {"1": 2, "2": 3, "3": 1, "4": 4, "5": 0}}
    assert slot_order(record) == [5, 3, 1, 2, 4]
    assert slot_order({"returns": {}}) is None
    model = Path(__file__).resolve().parents[2] / "models" / "find_water" / "policy.onnx"
    episodes = [Episode(5, 8, 0), Episode(3, 2, 1)]
    plain = simulate("find_water", model, episodes, 30)
    assert simulate("find_water", model, episodes, 30, [[1, 2, 3, 4, 5], None]) == plain
    with pytest.raises(ValueError):
        simulate("find_water", model, episodes, 30, [None])
