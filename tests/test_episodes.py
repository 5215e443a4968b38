"""Playing the HIL world's episodes (edge/episodes.py): when an episode's first step may be
decided. The vision is the real one, on rendered frames."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

from udan.edge.camera import Frame
from udan.edge.episodes import EpisodePlan, EpisodePlayer
from udan.edge.geometry import ArenaGeometry
from udan.edge.vision import KEPT_VISITS, Scene, Vision
from udan.hil.render import CameraModel, Renderer

GEOMETRY = ArenaGeometry()
LAYOUT = {
    "obstacle": [(1, 2), (2, 6), (4, 2), (4, 7), (6, 4), (7, 1)],
    "wall": [(0, 1), (0, 7)],
    "water": [(0, 3), (0, 4), (0, 5)],
    "target": [],
}

NEXT = {
    "obstacle": [(2, 2), (3, 5), (5, 7)],
    "wall": [(0, 2)],
    "water": [(0, 5), (0, 6)],
    "target": [],
}


class _Shell:
    """What the player reads of a shell while it waits: the next scene (the real vision on a
    rendered frame of ``LAYOUT``), the fleet (its one car joined from the start: the wait is
    the vision's), the vision's sweep length and the stop."""

    def __init__(self, layout: dict[str, list[tuple[int, int]]] = LAYOUT) -> None:
        self.layout = layout
        self.renderer = Renderer(GEOMETRY, CameraModel())
        self.vision = Vision(GEOMETRY)
        self.perception = SimpleNamespace(sweep_frames=self.vision.sweep_frames)
        self.core = SimpleNamespace(fleet=SimpleNamespace(slot={1: 0}))
        self.stop = asyncio.Event()
        self.scenes: list[Scene] = []

    async def next_scene(self) -> Scene:
        index = len(self.scenes)
        image = self.renderer.render([], self.layout)
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
    assert asyncio.run(player._await_fleet(shell, {1}, 0)) is True
    calibrated = [s.frame_index for s in shell.scenes if s.calibrated]
    assert calibrated and calibrated[0] > 0  # not from the first frame: the case in question
    assert len(calibrated) == KEPT_VISITS * shell.vision.sweep_frames + 1
    last = shell.scenes[-1]
    assert last.cells["obstacle"] == frozenset(LAYOUT["obstacle"])
    assert last.cells["water"] == frozenset(LAYOUT["water"])


def test_the_first_step_sees_the_new_layout_and_nothing_of_the_last() -> None:
    """The world lays out the next episode: its first step must see that layout exactly. Taken
    away, a marker stays on the map until its tile has been visited ``KEPT_VISITS`` times
    without it; the first steps of episodes waited one sweep, and most of them decided on the
    last episode's obstacles, walls and water beside the new ones (in a 40-s HIL run, 15 of 19)."""
    shell = _Shell()
    for _ in range(3 * shell.vision.sweep_frames):
        asyncio.run(shell.next_scene())
    assert shell.scenes[-1].cells["obstacle"] == frozenset(LAYOUT["obstacle"])
    shell.layout = NEXT
    laid_out = 25_000_000 * len(shell.scenes)
    player = EpisodePlayer(EpisodePlan(("127.0.0.1", 9), steps=1, join_timeout_s=30.0))
    assert asyncio.run(player._await_fleet(shell, {1}, laid_out)) is True
    last = shell.scenes[-1]
    for kind, cells in NEXT.items():
        assert last.cells[kind] == frozenset(cells), kind
