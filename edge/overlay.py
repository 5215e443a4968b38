"""What the controller thinks, drawn on the camera's frames: the annotated video (``--video``)
and the live page's camera thumbnail.

It runs where the frames are, in the perception process (the loop never touches a frame): the
loop sends it each step's record, reduced to what is drawn (:func:`overlay_of`), and the
perception process hands it every frame it analysed with its scene. Per frame due (the video's
next tick, or the next thumbnail), the vision's thread only projects what is to be drawn into
the image (cars, the grid, the cells; :meth:`Annotator.frame`, a few dozen microseconds);
scaling, drawing and encoding happen in a thread of their own with a short queue, and a frame
it cannot keep up with is skipped and counted, never waited for.

Drawn: the grid and the static cells, each car (its id, its marker's heading, the cell the last
step placed it in; a car the step held for a doubtful sighting in orange with a question mark:
a car in a move is between cells, doubtful by nature, and not marked), the groups (a line from
each leader to its members, the leader ringed), each car's last command as an arrow coloured by
what became of it (on time, missed, not ready), and in a corner the step, the score and the
latencies.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import queue
import threading
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import cv2
import numpy as np

from udan.edge.camera import Frame
from udan.edge.vision import Scene, Vision

VIDEO_FPS = 20.0
"""Frames a second of the annotated video (it follows the capture times, repeating a frame
over a gap)."""
VIDEO_SCALE = 0.5
"""The video at half the camera's size (a full-size encode costs as much as the vision)."""
THUMBNAIL_WIDTH = 480
THUMBNAIL_PERIOD_NS = 200_000_000
"""At most five thumbnails a second (the page updates at 10 Hz)."""
THUMBNAIL_QUALITY = 70
STEP_SHOWN_NS = 1_500_000_000
"""A step's cells, commands and groups are drawn this long after its decision (longer than the
step period): between episodes, or with the fleet stopped, the frames show no stale step."""
MAX_REPEAT_S = 5.0
"""Longest gap the video fills by repeating a frame (a camera stall); longer ones are cut."""
QUEUE = 4
DRAWING_NICENESS = 10
"""The drawing thread's niceness (the HIL camera process's, which recorded the raw video
before): below the vision (5) and the loop (0), since the video has seconds, the vision a frame
and a command 10 ms. The perception process shares the edge's session, and with it the loop's
share of the CPU (Linux autogroups): at 10 the drawing weighs a tenth of the loop there. Lower
(19, or ``SCHED_IDLE``) starved it for seconds on a saturated machine (a video of a few frames),
and a video left unfinished when its process is stopped is unreadable."""
GRID_SAMPLES = 12  # points along each grid line: a distorting lens bends them
COMMAND_DELTAS = {0: (-1, 0), 1: (1, 0), 2: (0, -1), 3: (0, 1)}  # up, down, left, right
OUTCOME_BGR = {"on_time": (60, 170, 60), "missed": (40, 40, 220), "not_ready": (150, 150, 150)}
KIND_BGR = {"obstacle": (60, 60, 200), "wall": (30, 30, 30), "water": (230, 150, 60),
            "target": (200, 60, 200)}  # fmt: skip
GROUP_BGR = ((200, 120, 30), (180, 80, 160), (200, 200, 40), (60, 90, 140), (190, 120, 230))


@dataclass(frozen=True)
class OverlaySettings:
    """What the perception process is asked to draw, sent to it as JSON."""

    video: str | None = None
    """Write the annotated video (MP4) here."""
    thumbnails: bool = False
    """Send JPEG thumbnails for the live page."""
    markers: dict[int, int] = field(default_factory=dict)
    """Car id -> its marker (the scene knows markers, the steps know cars)."""

    @property
    def wanted(self) -> bool:
        return self.video is not None or self.thumbnails

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> OverlaySettings:
        fields = json.loads(text)
        markers = {int(car): marker for car, marker in fields["markers"].items()}
        return cls(fields["video"], fields["thumbnails"], markers)


NO_OVERLAY = OverlaySettings()
"""Nothing drawn."""


def overlay_of(record: Mapping[str, Any], steps: int, on_time_share: float | None) -> dict:
    """What of a step's telemetry record is drawn, with the run's step count and on-time share
    so far (the record itself is per step)."""
    return {
        "t_ns": record.get("t_ns"),
        "steps": steps,
        "cells": record.get("cells", {}),
        "commands": record.get("commands", {}),
        "outcomes": record.get("outcomes", {}),
        "groups": record.get("groups", []),
        "uncertain": record.get("uncertain_cars", []),
        "score": record.get("score"),
        "decision_ns": record.get("state_to_commands_ns"),
        "loop_ns": record.get("frame_to_received_ns"),
        "on_time_share": on_time_share,
    }


@dataclass
class _Marks:
    """One frame's drawing in full-size image pixels, projected in the vision's thread."""

    cars: dict[int, tuple[np.ndarray, np.ndarray, bool]]
    """Car id -> (marker centre, a point ahead of it along its heading, held by the step as
    uncertain)."""
    cells: dict[int, np.ndarray]
    """Car id -> the outline of the cell the last step placed it in."""
    targets: dict[int, np.ndarray]
    """Car id -> where its last command sends it (the next cell's centre)."""
    grid: list[np.ndarray]
    static: list[tuple[str, np.ndarray]]


class Annotator:
    """Draws steps onto frames for the video and the thumbnails; see the module docstring."""

    def __init__(self, settings: OverlaySettings, vision: Vision) -> None:
        self.settings = settings
        self.vision = vision
        self.car_of = {marker: car for car, marker in settings.markers.items()}
        self.written = 0
        """Video frames written (repeats over a gap included)."""
        self.skipped = 0
        """Frames due that the drawing thread could not keep up with (the video repeats the
        next one over their time)."""
        self._overlay: dict[str, Any] = {}
        self._writer: cv2.VideoWriter | None = None
        self._t0_ns: int | None = None
        self._next_tick = 0
        self._next_thumbnail_ns = 0
        self.thumbnail: bytes | None = None
        """The newest thumbnail (JPEG), replaced as a whole: safe to read from any thread."""
        self._grid: tuple[int, list[np.ndarray]] | None = None
        self._queue: queue.Queue[tuple | None] = queue.Queue(maxsize=QUEUE)
        self._closing = False
        self._thread = threading.Thread(target=self._draw_loop, name="overlay", daemon=True)
        self._thread.start()

    def step(self, overlay: dict[str, Any]) -> None:
        """The last step (:func:`overlay_of`): drawn on the frames from now on."""
        self._overlay = overlay

    # -- in the vision's thread ----------------------------------------------------------------
    def frame(self, frame: Frame, scene: Scene) -> None:
        """A frame just analysed: if the video or a thumbnail is due, project its drawing and
        hand it to the drawing thread."""
        t = frame.t_capture_ns
        if self._t0_ns is None:
            self._t0_ns = t
        tick = int((t - self._t0_ns) * VIDEO_FPS / 1e9)
        video = self.settings.video is not None and tick >= self._next_tick
        thumbnail = self.settings.thumbnails and t >= self._next_thumbnail_ns
        if not (video or thumbnail):
            return
        repeats = min(tick - self._next_tick + 1, int(MAX_REPEAT_S * VIDEO_FPS)) if video else 0
        overlay = self._overlay
        if t - (overlay.get("t_ns") or t) > STEP_SHOWN_NS:  # the corner's figures only
            overlay = {**overlay, "cells": {}, "commands": {}, "groups": [], "uncertain": []}
        owned = frame.owned()  # drawn later, in the drawing thread: a lent image is copied
        if owned is None:
            return
        try:
            item = (owned.image, self._marks(scene, overlay), overlay, repeats, thumbnail)
            self._queue.put_nowait(item)
        except queue.Full:  # the next frame due fills the video's gap
            self.skipped += 1
            return
        if video:
            self._next_tick = tick + 1
        if thumbnail:
            self._next_thumbnail_ns = t + THUMBNAIL_PERIOD_NS

    def _marks(self, scene: Scene, overlay: Mapping[str, Any]) -> _Marks:
        fit, geometry = self.vision.fit, self.vision.geometry
        if not fit.calibrated:
            return _Marks({}, {}, {}, [], [])
        heights = self.vision.marker_heights
        cars, cells, targets = {}, {}, {}
        placed = overlay.get("cells", {})
        commands = overlay.get("commands", {})
        doubted = set(overlay.get("uncertain", ()))
        for marker, sighting in scene.cars.items():
            car = self.car_of.get(marker)
            if car is None:
                continue
            height = heights.get(marker, 0.0)
            x, y = sighting.xy
            ahead = (x + 0.1 * math.sin(sighting.heading), y - 0.1 * math.cos(sighting.heading))
            centre, front = fit.to_image(np.array([[x, y], ahead]), height)
            cars[car] = (centre, front, car in doubted)
            cell = placed.get(str(car))
            if cell is None:
                continue
            r, c = cell
            corners = np.array([[c, r], [c + 1, r], [c + 1, r + 1], [c, r + 1]]) * geometry.cell_m
            cells[car] = fit.to_image(corners)
            delta = COMMAND_DELTAS.get(commands.get(str(car), -1))
            if delta is not None:
                to = geometry.cell_centre(r + delta[0], c + delta[1])
                targets[car] = fit.to_image(np.array([to]), height)[0]
        return _Marks(cars, cells, targets, self._grid_lines(), self._static(scene))

    def _grid_lines(self) -> list[np.ndarray]:
        """The grid's lines in the image (kept while the camera model is the same)."""
        fit, geometry = self.vision.fit, self.vision.geometry
        if self._grid is None or self._grid[0] != fit.version:
            w, h = geometry.width_m, geometry.height_m
            s = np.linspace(0.0, 1.0, GRID_SAMPLES)
            lines = [np.stack([s * w, np.full_like(s, r * geometry.cell_m)], 1)
                     for r in range(geometry.rows + 1)]  # fmt: skip
            lines += [np.stack([np.full_like(s, c * geometry.cell_m), s * h], 1)
                      for c in range(geometry.cols + 1)]  # fmt: skip
            self._grid = fit.version, [fit.to_image(line) for line in lines]
        return self._grid[1]

    def _static(self, scene: Scene) -> list[tuple[str, np.ndarray]]:
        cell = self.vision.geometry.cell_m
        out = []
        for kind, cells in scene.cells.items():
            for r, c in cells:
                corners = np.array([[c, r], [c + 1, r], [c + 1, r + 1], [c, r + 1]]) * cell
                out.append((kind, self.vision.fit.to_image(corners)))
        return out

    # -- in the drawing thread -------------------------------------------------------------------
    def _draw_loop(self) -> None:
        while (item := self._queue.get()) is not None:
            with contextlib.suppress(OSError):  # again each time: the process may reset it
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), DRAWING_NICENESS)
            if self._closing:  # what is still queued at the end is skipped: finish the file
                self.skipped += 1
                continue
            image, marks, overlay, repeats, thumbnail = item
            h, w = image.shape[:2]
            size = (round(w * VIDEO_SCALE), round(h * VIDEO_SCALE))
            small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
            picture = cv2.cvtColor(small, cv2.COLOR_GRAY2BGR) if small.ndim == 2 else small
            draw(picture, marks, overlay, VIDEO_SCALE)
            if repeats:
                writer = self._open(size)
                for _ in range(repeats):
                    writer.write(picture)
                self.written += repeats
            if thumbnail:
                scale = THUMBNAIL_WIDTH / size[0]
                thumb = cv2.resize(picture, (THUMBNAIL_WIDTH, round(size[1] * scale)),
                                   interpolation=cv2.INTER_AREA)  # fmt: skip
                quality = [cv2.IMWRITE_JPEG_QUALITY, THUMBNAIL_QUALITY]
                ok, jpeg = cv2.imencode(".jpg", thumb, quality)
                if ok:
                    self.thumbnail = jpeg.tobytes()

    def _open(self, size: tuple[int, int]) -> cv2.VideoWriter:
        if self._writer is None:
            path = os.fspath(self.settings.video)
            self._writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"mp4v"), VIDEO_FPS, size)
        return self._writer

    def close(self) -> dict[str, int]:
        """Finish the frame being drawn and the video file (what is still queued is skipped);
        what was written and skipped."""
        self._closing = True
        self._queue.put(None)
        self._thread.join()
        if self._writer is not None:
            self._writer.release()
        return {"video_frames": self.written, "skipped": self.skipped}


def _pt(p: np.ndarray, scale: float) -> tuple[int, int]:
    return round(float(p[0]) * scale), round(float(p[1]) * scale)


def _poly(points: np.ndarray, scale: float) -> np.ndarray:
    return np.round(points * scale).astype(np.int32).reshape(-1, 1, 2)


def draw(picture: np.ndarray, marks: _Marks, overlay: Mapping[str, Any], scale: float) -> None:
    """The overlay onto ``picture`` (BGR, the frame scaled by ``scale``), in place."""
    for line in marks.grid:
        cv2.polylines(picture, [_poly(line, scale)], False, (160, 160, 160), 1, cv2.LINE_AA)
    for kind, outline in marks.static:
        cv2.polylines(picture, [_poly(outline, scale)], True, KIND_BGR.get(kind, (0, 0, 0)), 2)
    outcomes = overlay.get("outcomes", {})
    for car, outline in marks.cells.items():
        doubted = car in marks.cars and marks.cars[car][2]
        cv2.polylines(picture, [_poly(outline, scale)], True,
                      (0, 140, 255) if doubted else (0, 220, 255), 2)  # fmt: skip
    for g, group in enumerate(overlay.get("groups", [])):
        colour = GROUP_BGR[g % len(GROUP_BGR)]
        if group[0] not in marks.cars:
            continue
        leader = _pt(marks.cars[group[0]][0], scale)
        cv2.circle(picture, leader, 22, colour, 3, cv2.LINE_AA)
        for member in group[1:]:
            if member in marks.cars:
                cv2.line(picture, leader, _pt(marks.cars[member][0], scale), colour, 2, cv2.LINE_AA)
    for car, target in marks.targets.items():
        if car in marks.cars:
            colour = OUTCOME_BGR.get(outcomes.get(str(car), ""), (150, 150, 150))
            start = _pt(marks.cars[car][0], scale)
            cv2.arrowedLine(picture, start, _pt(target, scale), colour, 3, cv2.LINE_AA,
                            tipLength=0.25)  # fmt: skip
    for car, (centre, front, doubted) in marks.cars.items():
        c = _pt(centre, scale)
        colour = (0, 140, 255) if doubted else (20, 20, 20)
        cv2.circle(picture, c, 15, colour, 2, cv2.LINE_AA)
        cv2.line(picture, c, _pt(front, scale), colour, 2, cv2.LINE_AA)
        label = f"{car}?" if doubted else str(car)
        (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.55, 2)
        at = (c[0] + 12, c[1] - 12)
        cv2.rectangle(picture, (at[0] - 2, at[1] - th - 3), (at[0] + tw + 2, at[1] + 3),
                      (255, 255, 255), -1)  # fmt: skip
        cv2.putText(picture, label, at, cv2.FONT_HERSHEY_SIMPLEX, 0.55, colour, 2, cv2.LINE_AA)
    _corner(picture, overlay)


def _corner(picture: np.ndarray, overlay: Mapping[str, Any]) -> None:
    """The step, the score and the latencies, in the top-left corner."""

    def ms(ns: int | None) -> str:
        return "-" if ns is None else f"{ns / 1e6:.2f} ms"

    score, share = overlay.get("score"), overlay.get("on_time_share")
    lines = [
        f"step {overlay.get('steps', 0)}   score {'-' if score is None else f'{score:.2f}'}",
        f"decision {ms(overlay.get('decision_ns'))}   frame->cars {ms(overlay.get('loop_ns'))}",
        f"on time {'-' if share is None else f'{100 * share:.1f} %'}",
    ]
    cv2.rectangle(picture, (0, 0), (360, 22 * len(lines) + 8), (0, 0, 0), -1)
    for i, text in enumerate(lines):
        cv2.putText(picture, text, (8, 22 * i + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55,
                    (255, 255, 255), 1, cv2.LINE_AA)  # fmt: skip
