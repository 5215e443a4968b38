"""Marker detection: ArUco calls on small images, each tuned to few candidates.

ArUco's cost is mostly per call and per candidate quadrilateral it must decode, not per pixel, so
every caller (tracking, the sweep, the calibration check) searches a window at the search
resolution with a tight contour-length range; :meth:`MarkerDetector.find` is the second chance
at a finer resolution for a small, noisy marker the first one failed to decode. Markers too
thin to read at full resolution (far markers under a tilted camera) are searched at twice it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

SEARCH_LINES = 600
"""Frames are searched downscaled by an integer factor to about this many lines."""
MIN_CONTOUR = 28
"""Shortest marker contour searched for, pixels of the search image: a 10-pixel marker turned
45 degrees (see `shape_of`); smaller ones do not decode."""
THRESHOLD_WINDOW = 5
"""One adaptive-threshold window (search pixels, under two modules of a far car's marker): each
extra window costs a full thresholding and contour pass."""
THRESHOLD_OFFSET = 12
"""How much darker than its neighbourhood a pixel must be to count as ink. OpenCV's 7 lets sensor
noise and faint floor lines (the grid) through as contours, every one of which costs; marker ink
is more than a hundred grey levels darker than its paper."""
MIN_MODULE_PX = 2.0
"""Fewest image pixels per marker module a search resolution may leave a marker: below that it
does not decode reliably, and the marker is searched for at a finer resolution instead."""
ZOOM = 0.5
"""The scale of a search at twice the full resolution (cubic interpolation)."""
ZOOM_BELOW_PX = 3.0
"""A known marker with fewer full-resolution pixels per module than this (across its
`thickness`) is searched at ZOOM: the contour of its one-module border then closes and its
corners land within a module. Measured on rendered frames (tilt 40-60 degrees, noise and
blur): 2-2.7 pixels per module decode in 94-100 % of frames at ZOOM, 80-96 % at full
resolution; 3 and more in 100 % at either."""
SUBPIX_WINDOW = 3
"""cornerSubPix half-window at the search resolution of a 1200-line frame (and finer): inside
one module of the smallest calibration marker. Coarser search resolutions (frames of more
lines) leave the corners proportionally further off, and their markers' modules are
proportionally larger: the window grows with the downscale (:meth:`MarkerDetector.refine`)."""
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
CELL_PIXELS = 8
"""Pixels per module when a candidate is unwarped to read its bits: more than OpenCV's 4 makes
small markers (3 search pixels per module) decode reliably, for no measurable cost."""


_NEXT = [1, 2, 3, 0]


def shape_of(corners: np.ndarray) -> tuple[float, float, float, float]:
    """(centre x, centre y, mean side, contour length) of a marker's image quadrilateral. The
    contour length is what the detector counts as a perimeter, the points of the 8-connected
    contour: max(|dx|, |dy|) per side, up to 30 % less than the side sum when turned 45°."""
    (ax, ay), (bx, by), (cx, cy), (dx, dy) = corners.tolist()
    sides = ((bx - ax, by - ay), (cx - bx, cy - by), (dx - cx, dy - cy), (ax - dx, ay - dy))
    side = sum(math.hypot(u, v) for u, v in sides) / 4
    length = sum(max(abs(u), abs(v)) for u, v in sides)
    return (ax + bx + cx + dx) / 4, (ay + by + cy + dy) / 4, side, length


def thickness(corners: np.ndarray) -> np.ndarray:
    """The least distance between opposite sides of marker quadrilaterals (..., 4, 2): what
    decides whether a marker's modules can be read at a resolution. A tilted camera
    foreshortens markers to a third of their width, and one turned against the tilt is a
    rhombus narrower than its shortest side."""
    q = np.asarray(corners, dtype=np.float64)
    d = q[..., _NEXT, :] - q
    sides = np.sqrt((d * d).sum(-1))
    p, r = q[..., 2, :] - q[..., 0, :], q[..., 3, :] - q[..., 1, :]
    double_area = np.abs(p[..., 0] * r[..., 1] - p[..., 1] * r[..., 0])
    pairs = np.maximum(sides[..., 0] + sides[..., 2], sides[..., 1] + sides[..., 3])
    return double_area / np.maximum(pairs, 1e-9)


def normalised(patch: np.ndarray) -> np.ndarray:
    """`patch` flattened, zero-mean and unit-norm: the dot product of two is their normalised
    correlation, which a change of light does not move."""
    a = patch.astype(np.float32).ravel()
    a -= a.mean()
    return a / max(float(np.linalg.norm(a)), 1e-6)


class MarkerDetector:
    """One ArUco detector for frames of one size (:meth:`setup`); ``s`` is the search
    resolution's downscale factor."""

    def __init__(self, dictionary: str) -> None:
        self._params = cv2.aruco.DetectorParameters()
        self._params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_CONTOUR
        self._params.minDistanceToBorder = 0
        self._params.adaptiveThreshConstant = THRESHOLD_OFFSET
        self._params.perspectiveRemovePixelPerCell = CELL_PIXELS
        self._detector = cv2.aruco.ArucoDetector(
            cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), self._params
        )
        self.shape: tuple[int, int] | None = None
        self.s = 1
        self.modules = self._detector.getDictionary().markerSize + 2
        """Modules across a marker, its black border included."""

    def setup(self, shape: tuple[int, int]) -> None:
        """Frames of ``shape`` (h, w) from now on."""
        self.shape = shape
        self.s = max(1, round(shape[0] / SEARCH_LINES))

    def scale_for(self, side: float, zoom: bool = False) -> float:
        """The coarsest downscale, at most the search resolution's, that leaves a marker whose
        `thickness` is `side` (full-resolution pixels) MIN_MODULE_PX per module; with `zoom`,
        ZOOM for one with fewer than ZOOM_BELOW_PX per module at full resolution."""
        if zoom and side < ZOOM_BELOW_PX * self.modules:
            return ZOOM
        return max(1, min(self.s, int(side / (self.modules * MIN_MODULE_PX))))

    def window_for(self, side: float | None, scale: float) -> int:
        """Adaptive-threshold window (odd, pixels of an image downscaled by `scale`) for markers
        whose `thickness` is `side` (full resolution): about two modules, at most the search
        resolution's THRESHOLD_WINDOW (that one when `side` is None). A wider window blurs a
        small marker's modules into its paper and it stops decoding."""
        widest = int(THRESHOLD_WINDOW * self.s / scale) | 1
        if side is None:
            return widest
        return min(widest, max(3, round(2 * side / self.modules / scale) | 1))

    @staticmethod
    def window_image(
        img: np.ndarray, box: tuple[int, int, int, int], scale: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The image window `box` (x0, y0, x1, y1) downscaled by `scale` (a whole factor, or
        ZOOM), and the full-resolution position of its pixel (0, 0). Full resolution is a view
        of `img`, not a copy."""
        x0, y0, x1, y1 = box
        if scale < 1:
            roi = cv2.resize(
                img[y0:y1, x0:x1], None, fx=1 / scale, fy=1 / scale, interpolation=cv2.INTER_CUBIC
            )
        else:
            s = int(scale)
            x1 -= (x1 - x0) % s
            y1 -= (y1 - y0) % s
            roi = img[y0:y1, x0:x1]
            if s > 1:
                roi = cv2.resize(
                    roi, ((x1 - x0) // s, (y1 - y0) // s), interpolation=cv2.INTER_AREA
                )
        return roi, np.array([x0 + (scale - 1) / 2, y0 + (scale - 1) / 2])

    def detect(
        self,
        img: np.ndarray,
        box: tuple[int, int, int, int],
        perimeter: tuple[float, float],
        scale: float | None = None,
        side: float | None = None,
        zoom_thin: int = 0,
    ) -> list[tuple[int, np.ndarray]]:
        """Markers in the image window `box` (x0, y0, x1, y1) whose contour length is within
        `perimeter` (full-resolution pixels, see `shape_of`), searched at the search
        resolution; returns [(id, corners (4, 2) full-resolution pixels)], corners still
        approximate. A tight range is what keeps tracking cheap: a car's body and its label are
        squares too, and every candidate the detector has to decode costs. `scale` overrides
        the search downscale factor (1: full resolution, ZOOM: twice it); `side`, the
        `thickness` expected (full-resolution pixels), sets the threshold window
        (:meth:`window_for`). Up to `zoom_thin` candidates that failed to decode and are too
        thin for `scale` (ZOOM_BELOW_PX) are searched again, each alone at ZOOM."""
        s = self.s if scale is None else scale
        x0, y0, x1, y1 = box
        if min(x1 - x0, y1 - y0) < perimeter[0] / 4:
            return []
        roi, off = self.window_image(img, box, s)
        ids, quads, rejected = self.markers(
            roi, (perimeter[0] / s, perimeter[1] / s), self.window_for(side, s)
        )
        found = dict(zip(ids, quads * s + off, strict=True))
        if zoom_thin and s > ZOOM and rejected:
            rejected = np.asarray(rejected, dtype=np.float64).reshape(-1, 4, 2) * s + off
            thin = rejected[thickness(rejected) < ZOOM_BELOW_PX * self.modules][:zoom_thin]
            for quad in thin:
                cx, cy, size, length = shape_of(quad)
                again = self.box(cx, cy, 1.3 * size + 4)
                bounds = (0.8 * length, 1.25 * length)
                for marker, corners in self.detect(img, again, bounds, ZOOM, thickness(quad)):
                    found.setdefault(marker, corners)
        return list(found.items())

    def markers(
        self, image: np.ndarray, perimeter: tuple[float, float], window: int
    ) -> tuple[list[int], np.ndarray, Sequence[np.ndarray]]:
        """One detector call: ids and corners (n, 4, 2) of the markers in `image` whose contour
        length (in its pixels) is within `perimeter`, thresholded with one `window`, and the
        corners (each (1, 4, 2), as OpenCV gives them) of the candidates that did not decode."""
        longest = max(image.shape)
        p = self._params
        p.adaptiveThreshWinSizeMin = p.adaptiveThreshWinSizeMax = window
        p.minMarkerPerimeterRate = max(perimeter[0], MIN_CONTOUR) / longest
        p.maxMarkerPerimeterRate = perimeter[1] / longest
        self._detector.setDetectorParameters(p)
        corners, ids, rejected = self._detector.detectMarkers(image)
        if ids is None:
            return [], np.zeros((0, 4, 2)), rejected
        quads = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)
        return ids.ravel().tolist(), quads, rejected

    def refine(self, img: np.ndarray, corners: np.ndarray) -> np.ndarray:
        """`corners` (4, 2) of a large marker refined at full resolution (cornerSubPix): the
        calibration markers' corners fix the camera model, and their misfit measures the lens
        model's (contour refinement at the search resolution leaves corners about a search
        pixel inside the marker, which reads as a misfit of several millimetres)."""
        half = max(SUBPIX_WINDOW, round(SUBPIX_WINDOW * self.s / 2))
        pts = corners.astype(np.float32).reshape(-1, 1, 2)
        cv2.cornerSubPix(img, pts, (half, half), (-1, -1), _SUBPIX_CRITERIA)
        return pts.reshape(4, 2).astype(np.float64)

    def box(self, cx: float, cy: float, half: float) -> tuple[int, int, int, int]:
        """The image window of half side `half` around (cx, cy), clipped to the frame."""
        h, w = self.shape
        return (
            max(int(cx - half), 0),
            max(int(cy - half), 0),
            min(int(cx + half) + 1, w),
            min(int(cy + half) + 1, h),
        )

    def find(
        self,
        img: np.ndarray,
        marker: int,
        centre: tuple[float, float],
        half: float,
        length: float,
        side: float,
        scale: float = 1,
    ) -> np.ndarray | None:
        """`marker` near `centre`, its contour length near `length` and `thickness` near
        `side`, at downscale `scale` (full resolution by default): the second chance for a
        small, noisy marker a coarser search failed to decode."""
        cx, cy = centre
        box = self.box(cx, cy, half)
        found = self.detect(img, box, (0.8 * length, 1.2 * length), scale=scale, side=side)
        hits = [c for m, c in found if m == marker]
        return min(hits, key=lambda c: math.dist(c.mean(0), (cx, cy))) if hits else None
