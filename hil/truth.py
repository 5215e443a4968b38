"""A recording's sightings against where the HIL world's cars really were.

The world writes every change of its cars (``--truth``: when, each car's cell, the moves in
progress; :meth:`udan.hil.world.HilWorld.write_history`). A sighting the edge's vision took
with confidence (inside the grid, not uncertain), recorded in a flight recording's
``/vision/scene``, is right when its cell is one the car held, or moved between, during the
``lag_ns`` before the frame's capture time: a camera's picture can be older than its timestamp
(the fake GigE camera serves the newest rendered frame when its own frame clock fires, up to a
render period later, and stamps a picture older than the lag with its own capture time; the
virtual camera stamps the instant it draws, lag 0). Anything else is a
confident wrong cell, the one failure the vision must never have.
"""

from __future__ import annotations

import bisect
import json
from pathlib import Path
from typing import Any

from udan.edge.flightlog import FlightLog

Cell = tuple[int, int]


class Truth:
    """Where each car was over a run, from the world's history file."""

    def __init__(self, path: Path) -> None:
        self.times: list[int] = []
        self.states: list[tuple[dict[int, Cell], dict[int, tuple[Cell, Cell]]]] = []
        for line in path.read_text(encoding="utf-8").splitlines():
            record = json.loads(line)
            pose = {int(c): tuple(p) for c, p in record["pose"].items()}
            motion = {int(c): (tuple(a), tuple(b)) for c, (a, b, _) in record["motion"].items()}
            self.times.append(record["t_ns"])
            self.states.append((pose, motion))

    def cells(self, car: int, start_ns: int, end_ns: int) -> set[Cell]:
        """The cells ``car`` was on, or moving between, from ``start_ns`` to ``end_ns``."""
        first = max(bisect.bisect_right(self.times, start_ns) - 1, 0)
        last = bisect.bisect_right(self.times, end_ns)
        found: set[Cell] = set()
        for pose, motion in self.states[first:last]:
            if car in pose:
                found.add(pose[car])
            if car in motion:
                found.update(motion[car])
        return found


def check_sightings(log: FlightLog, truth: Truth, lag_ns: int = 0) -> dict[str, Any]:
    """Every confident sighting of a fleet car in the recording against the truth: how many,
    how many were taken while the car moved, and the wrong ones."""
    car_of = {c["marker"]: c["id"] for c in log.meta["fleet"]}
    checked = moving = 0
    wrong: list[dict[str, Any]] = []
    for entry in log.entries:
        if entry.call != "see":
            continue
        t_ns = entry.message["t_capture_ns"]
        for s in entry.message["cars"]:
            car = car_of.get(s["marker"])
            if car is None or not s["inside"] or s["uncertain"]:
                continue
            cells = truth.cells(car, t_ns - lag_ns, t_ns)
            if not cells:
                continue  # not on the arena then (parked between episodes)
            checked += 1
            moving += len(cells) > 1
            if tuple(s["cell"]) not in cells:
                wrong.append({"frame": entry.message["frame"], "car": car, "seen": s["cell"],
                              "truth": sorted(cells)})  # fmt: skip
    return {"sightings": checked, "while_moving": moving, "wrong": len(wrong),
            "wrong_cells": wrong[:50]}  # fmt: skip
