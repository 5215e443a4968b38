"""Playing the HIL world's episodes (edge/episodes.py): when an episode's first step may be
decided. The vision is the real one, on rendered frames."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

from udan.edge.camera import Frame
from udan.edge.episodes import EpisodePlan, EpisodePlayer
from udan.edge.geometry import ArenaGeometry
from udan.edge.vision import Scene, Vision
from udan.hil.render import CameraModel, Renderer

GEOMETRY = ArenaGeometry()
LAYOUT = {
    "obstacle": [(1, 2), (2, 6), (4, 2), (4, 7), (6, 4), (7, 1)],
    "wall": [(0, 1), (0, 7)],
    "water": [(0, 3), (0, 4), (0, 5)],
    "target": [],
}


class _Shell:
    """What the player reads of a shell while it waits: the next scene (the real vision on a
    rendered frame of ``LAYOUT``), the fleet (its one car joined from the start: the wait is
    the vision's), the vision's sweep length and the stop."""

    def __init__(self) -> None:
        self.renderer = Renderer(GEOMETRY, CameraModel())
        self.vision = Vision(GEOMETRY)
        self.perception = SimpleNamespace(sweep_frames=self.vision.sweep_frames)
        self.core = SimpleNamespace(fleet=SimpleNamespace(slot={1: 0}))
        self.stop = asyncio.Event()
        self.scenes: list[Scene] = []

    async def next_scene(self) -> Scene:
        index = len(self.scenes)
        image = self.renderer.render([], LAYOUT)
        self.scenes.append(self.vision.process(Frame(image, 25_000_000 * index, index)))
        return self.scenes[-1]


def test_the_first_step_waits_for_a_sweep_of_a_calibrated_camera() -> None:
    """The vision finds the calibration markers during its first sweep; the tiles it swept
    before could place their obstacle markers in no cell. The episode starts only once every
    tile has been swept since the camera was calibrated, and its frame shows every obstacle
    (the first step of the morning's seed-13 run drove a car into an obstacle it had not
    placed: the world refused the move and put the car back onto its follower)."""
    shell = _Shell()
    player = EpisodePlayer(EpisodePlan(("127.0.0.1", 9), steps=1, join_timeout_s=30.0))
    assert asyncio.run(player._await_fleet(shell, {1})) is True
    calibrated = [s.frame_index for s in shell.scenes if s.calibrated]
    assert calibrated and calibrated[0] > 0  # not from the first frame: the case in question
    assert len(calibrated) == shell.vision.sweep_frames + 1
    last = shell.scenes[-1]
    assert last.cells["obstacle"] == frozenset(LAYOUT["obstacle"])
    assert last.cells["water"] == frozenset(LAYOUT["water"])
