"""The overlay: a step's record drawn onto the frames the vision analysed (real rendered frames,
real OpenCV), as the annotated video and the page's thumbnail; and ``udan-edge --video``."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from udan.edge.camera import Frame
from udan.edge.geometry import ArenaGeometry
from udan.edge.overlay import (
    QUEUE,
    THUMBNAIL_WIDTH,
    VIDEO_FPS,
    VIDEO_SCALE,
    Annotator,
    OverlaySettings,
    overlay_of,
)
from udan.edge.vision import Vision
from udan.hil.render import Renderer

GEOMETRY = ArenaGeometry()
MARKERS = {1: 11, 2: 12}  # car id: marker
CELLS = {11: (2, 3), 12: (6, 5)}
LAYOUT = {"obstacle": [(4, 4)], "wall": [], "water": [(0, 4)], "target": []}
FRAME_NS = 25_000_000  # 40 FPS
YELLOW = np.array([0, 220, 255])  # the cell the step placed a car in
GREEN = np.array([60, 170, 60])  # a command that arrived on time


def _frames(n: int) -> list[Frame]:
    cars = [(m, *GEOMETRY.cell_centre(*cell), 0.0) for m, cell in CELLS.items()]
    image = Renderer(GEOMETRY).render(cars, LAYOUT)
    return [Frame(image, 10**9 + i * FRAME_NS, i) for i in range(n)]


STEP = {
    "t_ns": 10**9 + 39 * FRAME_NS,
    "cells": {"1": [2, 3], "2": [6, 5]}, "commands": {"1": 3, "2": 4},
    "outcomes": {"1": "on_time", "2": "missed"}, "groups": [[1, 2]], "uncertain_cars": [],
    "score": 12.5, "state_to_commands_ns": 600_000, "frame_to_received_ns": 7_000_000,
}  # fmt: skip


def _near(image: np.ndarray, colour: np.ndarray, box: tuple[int, int, int, int]) -> int:
    """Pixels of ``colour`` (BGR, give or take the encoder's error) inside ``box``."""
    x0, y0, x1, y1 = box
    patch = image[y0:y1, x0:x1].astype(int)
    return int(np.sum(np.abs(patch - colour).max(axis=2) < 45))


def test_the_video_follows_the_capture_times_and_shows_the_step(tmp_path: Path) -> None:
    video = tmp_path / "run.mp4"
    vision = Vision(GEOMETRY, car_markers=CELLS)
    annotator = Annotator(OverlaySettings(str(video), False, MARKERS), vision)
    frames = _frames(80)  # 2 s at 40 FPS: the vision has swept the layout and placed the cars
    for i, frame in enumerate(frames):
        if i == 40:
            annotator.step(overlay_of(STEP, steps=7, on_time_share=0.75))
        annotator.frame(frame, vision.process(frame))
        time.sleep(FRAME_NS / 1e9)  # a camera's pace
    counts = annotator.close()
    # 2 s at 20 FPS: a frame the drawing thread could not take is made up by repeating the
    # next one; only the last ones have none after them (a loaded machine)
    assert 40 - QUEUE <= counts["video_frames"] <= 40
    capture = cv2.VideoCapture(str(video))
    assert capture.get(cv2.CAP_PROP_FPS) == VIDEO_FPS
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == counts["video_frames"]
    capture.set(cv2.CAP_PROP_POS_FRAMES, counts["video_frames"] - 1)
    ok, last = capture.read()
    assert ok and last.shape == (600, 960, 3)  # half of 1200 x 1920, in colour
    # car 1's cell (2, 3), outlined where the camera model puts it, and its command (right) in
    # green from the car towards (2, 4); nothing of it in the cell of car 2 before the step
    corners = vision.fit.to_image(np.array([[3, 2], [4, 3]]) * GEOMETRY.cell_m) * VIDEO_SCALE
    (x0, y0), (x1, y1) = corners.astype(int)
    assert _near(last, YELLOW, (x0 - 3, y0 - 3, x1 + 3, y1 + 3)) > 100
    assert _near(last, GREEN, (x0, y0, x1 + (x1 - x0), y1)) > 20
    capture.set(cv2.CAP_PROP_POS_FRAMES, 5)
    ok, early = capture.read()
    assert ok and _near(early, YELLOW, (x0 - 3, y0 - 3, x1 + 3, y1 + 3)) < 10
    # the corner: a black box with the step's figures
    assert early[5:60, 5:300].mean() < last[100:200, 300:600].mean()


def test_a_step_is_drawn_while_it_is_current(tmp_path: Path) -> None:
    """Between episodes (or once stopped) no step is decided: after the step period and a half
    its cells, commands and groups go; the corner's figures stay."""
    video = tmp_path / "run.mp4"
    vision = Vision(GEOMETRY, car_markers=CELLS)
    annotator = Annotator(OverlaySettings(str(video), False, MARKERS), vision)
    frames = _frames(40)
    for frame in frames:
        vision.process(frame)
    annotator.step(overlay_of(STEP, steps=7, on_time_share=0.75))
    later = STEP["t_ns"] + 2 * 10**9
    late = [Frame(f.image, later + i * FRAME_NS, i) for i, f in enumerate(frames)]
    for frame in late:
        annotator.frame(frame, vision.process(frame))
        time.sleep(FRAME_NS / 1e9)
    annotator.close()
    capture = cv2.VideoCapture(str(video))
    ok, image = capture.read()
    corners = vision.fit.to_image(np.array([[3, 2], [4, 3]]) * GEOMETRY.cell_m) * VIDEO_SCALE
    (x0, y0), (x1, y1) = corners.astype(int)
    assert ok and _near(image, YELLOW, (x0 - 3, y0 - 3, x1 + 3, y1 + 3)) < 10


def test_thumbnails_are_small_jpegs_a_few_times_a_second() -> None:
    vision = Vision(GEOMETRY, car_markers=CELLS)
    annotator = Annotator(OverlaySettings(None, True, MARKERS), vision)
    seen = []
    for frame in _frames(80):
        annotator.frame(frame, vision.process(frame))
        time.sleep(FRAME_NS / 1e9)
        if annotator.thumbnail is not None and (not seen or seen[-1] is not annotator.thumbnail):
            seen.append(annotator.thumbnail)
    annotator.close()
    seen.append(annotator.thumbnail)
    distinct = {id(t) for t in seen}
    assert 5 <= len(distinct) <= 11  # 2 s at most 5 a second
    image = cv2.imdecode(np.frombuffer(seen[-1], np.uint8), cv2.IMREAD_COLOR)
    assert image.shape[1] == THUMBNAIL_WIDTH and len(seen[-1]) < 60_000


def test_settings_travel_as_json() -> None:
    settings = OverlaySettings("/x/run.mp4", True, {1: 11, 2: 12})
    assert OverlaySettings.from_json(settings.to_json()) == settings


@pytest.mark.parametrize("perception", ["process", pytest.param("thread", marks=pytest.mark.slow)])
def test_udan_edge_sim_video_is_annotated(tmp_path: Path, perception: str) -> None:
    video, report = tmp_path / "run.mp4", tmp_path / "report.json"
    done = subprocess.run(
        [
            str(Path(sys.executable).with_name("udan-edge")), "--sim", "--cars", "3",
            "--duration", "8", "--cell-time-ms", "60", "--video", str(video),
            "--report", str(report), "--quiet", "--perception", perception,
        ],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    written = json.loads(report.read_text())["camera"]["video"]
    capture = cv2.VideoCapture(str(video))
    frames = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    # 20 a second of the run; a saturated machine starves the drawing (nicer than the vision
    # and the loop), and the video then holds fewer frames, each repeated over its time
    assert frames == written["video_frames"] >= 40
    capture.set(cv2.CAP_PROP_POS_FRAMES, frames - 10)
    ok, image = capture.read()
    spread = image.astype(int).max(axis=2) - image.astype(int).min(axis=2)
    assert ok and np.count_nonzero(spread > 80) > 500  # colour drawn on a grey camera
