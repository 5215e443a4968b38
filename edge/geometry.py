"""The physical arena: its size, where the markers are, and arena metres <-> grid cells.

One description shared by the vision (edge), the virtual camera (hil) and the docs, so what the
camera renders and what the edge reads back cannot drift apart.

Arena frame: origin at the outer corner of cell (0, 0), ``x`` in metres along the columns, ``y``
in metres along the rows (so row 0 is the top of the image, the "up" action). The paper's arena is
2.8 m square, rasterised to 9x9 cells.

Markers (ArUco ``DICT_4X4_50`` by default), all lying flat on the floor plane:

- four calibration markers just outside the grid corners: ids 0 (top-left), 1 (top-right),
  2 (bottom-right), 3 (bottom-left); their 16 corners fix the homography image -> arena;
- one marker per car (its id is the car's ``marker`` in fleet.toml), centred on the car, its top
  edge pointing where the car faces; heading 0 faces "up" (-y), angles grow clockwise (towards +x);
- one marker per static cell, centred on the cell, whose id says what the cell is: the same id
  appears once per cell of that kind (obstacle, wall, water source; the surround target).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

CORNER_IDS = (0, 1, 2, 3)
OBSTACLE_ID = 40
WALL_ID = 41
WATER_ID = 42
TARGET_ID = 43
CELL_KIND_IDS = {"obstacle": OBSTACLE_ID, "wall": WALL_ID, "water": WATER_ID, "target": TARGET_ID}
RESERVED_IDS = frozenset(CORNER_IDS) | frozenset(CELL_KIND_IDS.values())


@dataclass(frozen=True)
class ArenaGeometry:
    """Sizes of the arena and of its markers, in metres."""

    rows: int = 9
    """Grid rows."""
    cols: int = 9
    """Grid columns."""
    cell_m: float = 2.8 / 9
    """Side of one grid cell."""
    corner_marker_m: float = 0.16
    """Side of a calibration marker."""
    corner_gap_m: float = 0.04
    """Gap between the grid's outer edge and the nearest edge of a calibration marker."""
    car_marker_m: float = 0.12
    """Side of a car's marker."""
    cell_marker_m: float = 0.16
    """Side of a static cell marker (obstacle, wall, water, target)."""
    dictionary: str = "DICT_4X4_50"
    """ArUco dictionary name (``cv2.aruco`` constant)."""

    @property
    def width_m(self) -> float:
        return self.cols * self.cell_m

    @property
    def height_m(self) -> float:
        return self.rows * self.cell_m

    def corner_centres(self) -> np.ndarray:
        """(4, 2) centres of calibration markers 0-3 (x, y) in arena metres."""
        off = self.corner_gap_m + self.corner_marker_m / 2
        w, h = self.width_m, self.height_m
        return np.array([[-off, -off], [w + off, -off], [w + off, h + off], [-off, h + off]])

    def corner_points(self) -> np.ndarray:
        """(4, 4, 2) arena coordinates of each calibration marker's four corners, in OpenCV's
        order (top-left, top-right, bottom-right, bottom-left of the marker, markers upright)."""
        return np.stack(
            [square(c, self.corner_marker_m, 0.0) for c in self.corner_centres()]
        ).astype(np.float64)

    def cell_centre(self, row: float, col: float) -> tuple[float, float]:
        """Arena (x, y) of the centre of cell (row, col)."""
        return ((col + 0.5) * self.cell_m, (row + 0.5) * self.cell_m)

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """Cells (..., 2) as (row, col) int64 of arena points ``xy`` (..., 2); may lie outside."""
        xy = np.asarray(xy, dtype=np.float64)
        return np.floor(xy[..., ::-1] / self.cell_m).astype(np.int64)

    def inside(self, cells: np.ndarray) -> np.ndarray:
        """Which ``cells`` (..., 2) lie on the grid."""
        cells = np.asarray(cells)
        return (
            (cells[..., 0] >= 0)
            & (cells[..., 0] < self.rows)
            & (cells[..., 1] >= 0)
            & (cells[..., 1] < self.cols)
        )


def square(centre: np.ndarray, side: float, heading: float) -> np.ndarray:
    """(4, 2) corners of a marker of ``side`` centred on ``centre`` facing ``heading`` (radians,
    0 = -y, clockwise), in OpenCV's corner order: top-left, top-right, bottom-right, bottom-left
    as seen with the marker upright."""
    half = side / 2
    local = np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
    c, s = math.cos(heading), math.sin(heading)
    rot = np.array([[c, -s], [s, c]])
    return np.asarray(centre, dtype=np.float64) + local @ rot.T


def heading_of(corners: np.ndarray) -> float:
    """Heading (radians, 0 = -y, clockwise, in (-pi, pi]) of a marker from its four arena-frame
    corners in OpenCV's order: the direction from the bottom edge's middle to the top edge's."""
    corners = np.asarray(corners, dtype=np.float64)
    forward = (corners[0] + corners[1]) / 2 - (corners[2] + corners[3]) / 2
    return math.atan2(forward[0], -forward[1])
