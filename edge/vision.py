"""Frame -> Scene: where every car is (cell, metres, heading) and what the static cells are.

The budget is 5 ms per 1920x1200 frame on a busy 2-core machine, and a full-frame ArUco search
costs 11-34 ms there, so no frame runs one. ArUco's cost is mostly per call and per candidate
quadrilateral it must decode, not per pixel, so the scheme calls it on small images that hold
few candidates:

- Cars are tracked. A known car is looked for only in a window around where its last sighting
  and velocity put it, at the search resolution (half size for a 1200-line frame); the windows
  of cars of similar apparent size are stacked into one image and searched in one call, with a
  contour-length range so tight that a car's body and label, squares too, are not candidates.
  A marker the search resolution fails to decode (small and noisy) is looked for again at full
  resolution. Corners are refined on the contour (CORNER_REFINE_CONTOUR): at half size that is
  accurate enough for 2 cm and a few degrees, where cornerSubPix gets pulled off the corners of
  small markers by their inner pattern.
- The rest of the image is swept one tile per frame (4 x 3 tiles overlapping by more than a
  marker), with everything already known painted out first: tracked cars, calibration markers,
  and cell markers that still look as they did when decoded (normalised correlation). So the
  sweep decodes only what is new: a car that joined or that its track lost, a changed cell, a
  calibration marker after a camera move. A sweep takes 12 frames (300 ms at 40 FPS): that is
  how long a new car or a changed obstacle takes to appear; tracked cars do not wait for it.
- Calibration is a homography (undistorted image pixels -> arena metres) fitted to the corners
  of the calibration markers, averaged over sightings. One of them is re-checked every frame
  where it was last seen; shifted by more than `move_tolerance_px`, the camera has moved: the
  fit and the cell readings are dropped and the scene says it is uncalibrated (no cars, no
  cells) rather than wrong, until the sweep has found three calibration markers again, with no
  restart. Lens distortion (a calibration file) is removed from detected corners, not frames.
- A cell marker that one sweep misses stays until the next one misses it too, so noise cannot
  make an obstacle flicker. The surround target moves, so it is tracked like a car (by its id:
  one target; its window allows for a hop to the next cell) and reported as the frame's
  "target" cell.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from edge.camera import Frame
from edge.geometry import (
    CELL_KIND_IDS,
    CORNER_IDS,
    RESERVED_IDS,
    TARGET_ID,
    ArenaGeometry,
    heading_of,
)

SEARCH_LINES = 600
"""Frames are searched downscaled by an integer factor to about this many lines."""
MIN_CONTOUR = 28
"""Shortest marker contour searched for, pixels of the search image: a 10-pixel marker turned
45 degrees (see `_shape_of`); smaller ones do not decode."""
THRESHOLD_WINDOW = 5
"""One adaptive-threshold window (search pixels, under two modules of a far car's marker): each
extra window costs a full thresholding and contour pass."""
THRESHOLD_OFFSET = 12
"""How much darker than its neighbourhood a pixel must be to count as ink. OpenCV's 7 lets sensor
noise and faint floor lines (the grid) through as contours, every one of which costs; marker ink
is more than a hundred grey levels darker than its paper."""
CELL_PIXELS = 8
"""Pixels per module when a candidate is unwarped to read its bits: more than OpenCV's 4 makes
small markers (3 search pixels per module) decode reliably, for no measurable cost."""
SIZE_GROUP = 1.15
"""Cars whose markers' contour lengths are within this ratio are searched in one call; a wider
range would let a small car's label (1.33 times its marker) pass as a candidate."""
MASK = 1.15
"""Known markers are painted out of the sweep image over this many times their size, with the
paper just around them (markers are printed with a one-module margin): only the marker's own
footprint, so a marker next to it is never hidden, and what is left (a blank label, a car's
body) is rejected at a glance instead of decoded."""
TEMPLATE_MATCH = 0.9
"""Normalised correlation with its last decoded look above which a static marker is taken to be
unchanged, and painted out instead of decoded again."""
_ARENA = ArenaGeometry()
_KIND_OF_ID = {marker: kind for kind, marker in CELL_KIND_IDS.items()}
_UNDISTORT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)


class VisionError(Exception):
    """A configuration problem the vision cannot run with (one-line message)."""


@dataclass(frozen=True)
class CameraCalibration:
    """Intrinsics as OpenCV's calibration sample writes them."""

    camera_matrix: np.ndarray
    dist_coeffs: np.ndarray
    image_size: tuple[int, int] | None = None
    """(width, height) the calibration was made at, when the file says."""


def save_calibration(path: str | os.PathLike, calibration: CameraCalibration) -> None:
    """Write an OpenCV FileStorage YAML with the calibration sample's keys."""
    fs = cv2.FileStorage(os.fspath(path), cv2.FILE_STORAGE_WRITE)
    if calibration.image_size is not None:
        fs.write("image_width", int(calibration.image_size[0]))
        fs.write("image_height", int(calibration.image_size[1]))
    fs.write("camera_matrix", np.asarray(calibration.camera_matrix, dtype=np.float64))
    fs.write(
        "distortion_coefficients",
        np.asarray(calibration.dist_coeffs, dtype=np.float64).reshape(-1, 1),
    )
    fs.release()


def load_calibration(path: str | os.PathLike) -> CameraCalibration:
    """Read `camera_matrix` and `distortion_coefficients` (and the image size if present) from
    an OpenCV FileStorage file; anything missing or malformed is a one-line VisionError."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise VisionError(f"camera calibration file not found: {path}")
    try:
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):  # a parse error surfaces as either, by OpenCV version
        raise VisionError(
            f"camera calibration {path} is not an OpenCV FileStorage YAML/XML file"
        ) from None
    try:
        if not fs.isOpened():
            raise VisionError(f"cannot open camera calibration {path}")
        k = fs.getNode("camera_matrix").mat()
        d = fs.getNode("distortion_coefficients").mat()
        w, h = fs.getNode("image_width"), fs.getNode("image_height")
        numbers = all(n.isInt() or n.isReal() for n in (w, h))
        size = (int(w.real()), int(h.real())) if numbers else None
    finally:
        fs.release()
    if k is None or k.shape != (3, 3) or not np.isfinite(k).all() or k[0, 0] <= 0:
        raise VisionError(f"camera calibration {path} has no valid 3x3 camera_matrix")
    if d is None or d.size not in (4, 5, 8, 12, 14) or not np.isfinite(d).all():
        raise VisionError(
            f"camera calibration {path} has no valid distortion_coefficients (4, 5, 8, 12 or 14)"
        )
    return CameraCalibration(k.astype(np.float64), d.reshape(-1).astype(np.float64), size)


@dataclass(frozen=True)
class CarSighting:
    """One car marker seen in one frame."""

    marker: int
    cell: tuple[int, int]
    """(row, col); may lie off the grid (see `inside`)."""
    xy: tuple[float, float]
    """Arena metres of the marker's centre."""
    heading: float
    """Radians, 0 = up (-y), clockwise."""
    offset: tuple[float, float]
    """(dx, dy) metres from the centre of `cell`."""
    inside: bool


@dataclass(frozen=True)
class Scene:
    """What one frame shows, in arena terms."""

    t_capture_ns: int
    frame_index: int
    calibrated: bool
    cars: dict[int, CarSighting]
    cells: dict[str, frozenset[tuple[int, int]]]
    vision_ns: int
    """Time `Vision.process` spent on this frame."""


@dataclass
class _Track:
    corners: np.ndarray
    """(4, 2) full-resolution image pixels (as detected, distorted)."""
    index: int
    shape: tuple[float, float, float, float]
    """`_shape_of(corners)`."""
    velocity: tuple[float, float] = (0.0, 0.0)
    """Pixels per frame index."""
    misses: int = 0


@dataclass
class _Known:
    """A cell marker the last visit of its sweep tile decoded."""

    marker: int
    quad: np.ndarray
    """(4, 2) full-resolution image pixels."""
    box: tuple[int, int, int, int]
    """Its bounding box in the tile's search image."""
    template: np.ndarray
    """The box's pixels then, zero-mean and unit-norm."""
    cell: tuple[str, tuple[int, int]] | None = None
    """(kind, (row, col)) once calibrated."""


def _normalised(patch: np.ndarray) -> np.ndarray:
    a = patch.astype(np.float32).ravel()
    a -= a.mean()
    return a / max(float(np.linalg.norm(a)), 1e-6)


def _shape_of(corners: np.ndarray) -> tuple[float, float, float, float]:
    """(centre x, centre y, mean side, contour length) of a marker's image quadrilateral. The
    contour length is what the detector counts as a perimeter, the points of the 8-connected
    contour: max(|dx|, |dy|) per side, up to 30 % less than the side sum when turned 45°."""
    (ax, ay), (bx, by), (cx, cy), (dx, dy) = corners.tolist()
    sides = ((bx - ax, by - ay), (cx - bx, cy - by), (dx - cx, dy - cy), (ax - dx, ay - dy))
    side = sum(math.hypot(u, v) for u, v in sides) / 4
    length = sum(max(abs(u), abs(v)) for u, v in sides)
    return (ax + bx + cx + dx) / 4, (ay + by + cy + dy) / 4, side, length


class Vision:
    """Tracks the arena's markers frame after frame; see the module docstring for the scheme."""

    def __init__(
        self,
        geometry: ArenaGeometry = _ARENA,
        *,
        car_markers: Iterable[int] | None = None,
        calibration_file: str | os.PathLike | None = None,
        sweep_tiles: tuple[int, int] = (4, 3),
        lost_after: int = 3,
        move_tolerance_px: float = 2.0,
        max_residual_m: float = 0.05,
    ) -> None:
        self.geometry = geometry
        self._car_ids = None if car_markers is None else frozenset(car_markers)
        self._calibration = None if calibration_file is None else load_calibration(calibration_file)
        self._sweep_tiles = sweep_tiles
        self._lost_after = lost_after
        self._move_tol = move_tolerance_px
        self._max_residual = max_residual_m
        self._params = cv2.aruco.DetectorParameters()
        self._params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_CONTOUR
        self._params.minDistanceToBorder = 0
        self._params.adaptiveThreshConstant = THRESHOLD_OFFSET
        self._params.perspectiveRemovePixelPerCell = CELL_PIXELS
        self._detector = cv2.aruco.ArucoDetector(
            cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, geometry.dictionary)),
            self._params,
        )
        self._corner_arena = geometry.corner_points()
        self._target_jump = 1.1 * geometry.cell_m / geometry.cell_marker_m
        """A target marker is drawn on its cell and may hop to the next: its search window
        allows for a cell's step (in marker sides) besides its velocity."""
        self.reset()

    def reset(self) -> None:
        """Forget tracks, static cells and calibration (e.g. a different camera)."""
        self._shape: tuple[int, int] | None = None
        self._tracks: dict[int, _Track] = {}
        self._corners: dict[int, np.ndarray] = {}
        """Calibration marker corners, undistorted and smoothed over sightings."""
        self._corner_quads: dict[int, np.ndarray] = {}
        """The last sighting of each calibration marker as detected (where to look again)."""
        self._checks = 0
        self._homography: np.ndarray | None = None
        self._tiles: list[tuple[tuple[int, int, int, int], tuple[int, int, int, int]]] = []
        """Sweep tiles: (core, core plus overlap) as x0, y0, x1, y1."""
        self._static: list[list[frozenset[tuple[str, tuple[int, int]]]]] = []
        """Per sweep tile, the static cells (kind, cell) its last two visits found."""
        self._known: list[list[_Known]] = []
        """Per sweep tile, the cell markers its last visit decoded or recognised."""
        self._cells: dict[str, frozenset[tuple[int, int]]] | None = None
        self._tile = 0

    @property
    def sweep_frames(self) -> int:
        """Frames one sweep of the whole image takes: a layout that changed is fully read after
        this many frames (cars, tracked, are found sooner)."""
        return self._sweep_tiles[0] * self._sweep_tiles[1]

    @property
    def calibrated(self) -> bool:
        return self._homography is not None

    # -- layout ---------------------------------------------------------------------------
    def _setup(self, shape: tuple[int, int]) -> None:
        if self._calibration and self._calibration.image_size not in (None, shape[::-1]):
            w, h = self._calibration.image_size
            raise VisionError(
                f"camera calibration is for {w}x{h} frames, the camera gives {shape[1]}x{shape[0]}"
            )
        self.reset()
        self._shape = shape
        h, w = shape
        self._s = s = max(1, round(h / SEARCH_LINES))
        nx, ny = self._sweep_tiles
        overlap = s * round(h / 20 / s)
        self._sweep_perimeter = (s * MIN_CONTOUR, h / 3)
        xs = [s * round(w * i / nx / s) for i in range(nx + 1)]
        ys = [s * round(h * j / ny / s) for j in range(ny + 1)]
        for j in range(ny):
            for i in range(nx):
                core = (xs[i], ys[j], xs[i + 1], ys[j + 1])
                ext = (
                    max(0, xs[i] - overlap),
                    max(0, ys[j] - overlap),
                    min(w, xs[i + 1] + overlap),
                    min(h, ys[j + 1] + overlap),
                )
                self._tiles.append((core, ext))
        self._static = [[frozenset(), frozenset()] for _ in self._tiles]
        self._known = [[] for _ in self._tiles]

    # -- detection ------------------------------------------------------------------------
    def _detect(
        self,
        img: np.ndarray,
        box: tuple[int, int, int, int],
        perimeter: tuple[float, float],
        scale: int | None = None,
    ) -> list[tuple[int, np.ndarray]]:
        """Markers in the image window `box` (x0, y0, x1, y1) whose contour length is within
        `perimeter` (full-resolution pixels, see `_shape_of`), searched at the search
        resolution; returns [(id, corners (4, 2) full-resolution pixels)], corners still
        approximate. A tight range is what keeps tracking cheap: a car's body and its label are
        squares too, and every candidate the detector has to decode costs. `scale` overrides
        the search downscale factor (1: full resolution)."""
        s = self._s if scale is None else scale
        x0, y0, x1, y1 = box
        x1 -= (x1 - x0) % s
        y1 -= (y1 - y0) % s
        if min(x1 - x0, y1 - y0) < perimeter[0] / 4:
            return []
        roi = img[y0:y1, x0:x1]
        if s > 1:
            roi = cv2.resize(roi, ((x1 - x0) // s, (y1 - y0) // s), interpolation=cv2.INTER_AREA)
        off = np.array([x0 + (s - 1) / 2, y0 + (s - 1) / 2])
        window = THRESHOLD_WINDOW * self._s // s | 1
        ids, quads = self._markers(roi, (perimeter[0] / s, perimeter[1] / s), window)
        return list(zip(ids, quads * s + off, strict=True))

    def _markers(
        self, image: np.ndarray, perimeter: tuple[float, float], window: int
    ) -> tuple[list[int], np.ndarray]:
        """One detector call: ids and corners (n, 4, 2) of the markers in `image` whose contour
        length (in its pixels) is within `perimeter`, thresholded with one `window`."""
        longest = max(image.shape)
        p = self._params
        p.adaptiveThreshWinSizeMin = p.adaptiveThreshWinSizeMax = window
        p.minMarkerPerimeterRate = max(perimeter[0], MIN_CONTOUR) / longest
        p.maxMarkerPerimeterRate = perimeter[1] / longest
        self._detector.setDetectorParameters(p)
        corners, ids, _ = self._detector.detectMarkers(image)
        if ids is None:
            return [], np.zeros((0, 4, 2))
        return ids.ravel().tolist(), np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)

    def _undistort(self, pts: np.ndarray) -> np.ndarray:
        if self._calibration is None:
            return pts
        cal = self._calibration
        out = cv2.undistortPoints(
            pts.reshape(-1, 1, 2),
            cal.camera_matrix,
            cal.dist_coeffs,
            P=cal.camera_matrix,
            criteria=_UNDISTORT,
        )
        return out.reshape(pts.shape)

    def _to_arena(self, pts: np.ndarray) -> np.ndarray:
        flat = self._undistort(pts.reshape(-1, 2)).reshape(-1, 1, 2)
        return cv2.perspectiveTransform(flat, self._homography).reshape(pts.shape)

    def _box(self, cx: float, cy: float, half: float) -> tuple[int, int, int, int]:
        """The image window of half side `half` around (cx, cy), clipped to the frame."""
        h, w = self._shape
        return (
            max(int(cx - half), 0),
            max(int(cy - half), 0),
            min(int(cx + half) + 1, w),
            min(int(cy + half) + 1, h),
        )

    def _find(
        self, img: np.ndarray, marker: int, cx: float, cy: float, half: float, length: float
    ) -> np.ndarray | None:
        """`marker` near (cx, cy), its contour length near `length`, at full resolution: the
        second chance for a small, noisy marker the search resolution failed to decode."""
        hits = [
            c
            for m, c in self._detect(
                img, self._box(cx, cy, half), (0.8 * length, 1.2 * length), scale=1
            )
            if m == marker
        ]
        return min(hits, key=lambda c: math.dist(c.mean(0), (cx, cy))) if hits else None

    def _is_tracked(self, marker: int) -> bool:
        """Cars, and the surround target: it moves like one."""
        if marker == TARGET_ID:
            return True
        if self._car_ids is not None:
            return marker in self._car_ids
        return marker not in RESERVED_IDS

    # -- per-frame stages -----------------------------------------------------------------
    def _track(self, img: np.ndarray, index: int) -> dict[int, np.ndarray]:
        """Each tracked car, searched for in a window around its predicted position; returns
        the approximate corners of those found. Windows of cars whose markers look alike in
        size are stacked into one image and searched in one detector call (a call has a fixed
        cost comparable to decoding a marker); a car the search resolution misses is looked
        for again at full resolution (a small, noisy marker sometimes fails to decode)."""
        wanted = []
        for marker, tr in self._tracks.items():
            gap = max(1, index - tr.index)
            cx, cy, side, length = tr.shape
            vx, vy = tr.velocity
            half = (1.3 * side + math.hypot(vx, vy) * gap + 8) * (1 + 0.5 * tr.misses)
            if marker == TARGET_ID or tr.misses:  # a hop, or a car faster than its velocity
                half += self._target_jump * side
            wanted.append((length, marker, cx + vx * gap, cy + vy * gap, half))
        wanted.sort()
        found: dict[int, np.ndarray] = {}
        while wanted:
            n = sum(1 for w in wanted if w[0] <= SIZE_GROUP * wanted[0][0])
            found.update(self._track_group(img, wanted[:n]))
            wanted = wanted[n:]
        return found

    def _track_group(
        self, img: np.ndarray, group: list[tuple[float, int, float, float, float]]
    ) -> dict[int, np.ndarray]:
        """Search the windows of `group` [(contour length, marker, x, y, half side)] stacked
        into one image (windows of one common size, shifted to lie inside the frame)."""
        h, w = self._shape
        s = self._s
        size = min(s * math.ceil(2 * max(g[4] for g in group) / s), h - h % s, w - w % s)
        k = size // s
        stack = np.empty((k * len(group), k), np.uint8)
        origins = []
        for i, (_, _, cx, cy, _) in enumerate(group):
            x0 = min(max(int(cx - size / 2), 0), w - size)
            y0 = min(max(int(cy - size / 2), 0), h - size)
            window = img[y0 : y0 + size, x0 : x0 + size]
            if s > 1:
                cv2.resize(
                    window, (k, k), dst=stack[i * k : (i + 1) * k], interpolation=cv2.INTER_AREA
                )
            else:
                stack[i * k : (i + 1) * k] = window
            origins.append((x0 + (s - 1) / 2, y0 + (s - 1) / 2 - i * size))
        bounds = (0.8 * group[0][0] / s, 1.2 * group[-1][0] / s)
        ids, quads = self._markers(stack, bounds, THRESHOLD_WINDOW)
        found: dict[int, np.ndarray] = {}
        for marker, quad in zip(ids, quads, strict=True):
            i = int(quad[:, 1].mean() // k)
            _, want, cx, cy, _ = group[i]
            if marker != want:
                continue
            full = quad * s + origins[i]
            if marker not in found or math.dist(full.mean(0), (cx, cy)) < math.dist(
                found[marker].mean(0), (cx, cy)
            ):
                found[marker] = full
        for length, marker, cx, cy, half in group:
            if marker not in found and s > 1:
                quad = self._find(img, marker, cx, cy, half, length)
                if quad is not None:
                    found[marker] = quad
        return found

    def _sweep(self, img: np.ndarray, cars: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """One tile of the sweep: adds cars the tracks do not have to `cars`, records the tile's
        static cells, returns the calibration markers it found that were not known. What is
        known (tracked cars, calibration markers, cell markers that still look as they did)
        is painted out first, so the detector decodes only what is new."""
        t = self._tile
        self._tile = (t + 1) % len(self._tiles)
        (cx0, cy0, cx1, cy1), (x0, y0, x1, y1) = self._tiles[t]
        s = self._s
        roi = img[y0:y1, x0:x1]
        roi = cv2.resize(roi, ((x1 - x0) // s, (y1 - y0) // s), interpolation=cv2.INTER_AREA)
        off = np.array([x0 + (s - 1) / 2, y0 + (s - 1) / 2])
        known = [k for k in self._known[t] if self._unchanged(roi, k)]
        masks = [*cars.values(), *self._corner_quads.values(), *(k.quad for k in known)]
        masks += [k.quad for i, ks in enumerate(self._known) if i != t for k in ks]
        self._paint(roi, off, masks)
        lo, hi = self._sweep_bounds()
        ids, quads = self._markers(roi, (lo / s, hi / s), THRESHOLD_WINDOW)
        corners_seen = {}
        for marker, quad in zip(ids, quads, strict=True):
            full = quad * s + off
            if marker in CORNER_IDS:
                corners_seen[marker] = full
            elif marker in _KIND_OF_ID and marker != TARGET_ID:
                cx, cy = full.mean(0)
                if cx0 <= cx < cx1 and cy0 <= cy < cy1:
                    bx0, by0 = np.maximum(np.floor(quad.min(0)).astype(int) - 1, 0)
                    bx1, by1 = np.ceil(quad.max(0)).astype(int) + 2
                    box = (int(bx0), int(by0), int(bx1), int(by1))
                    template = _normalised(roi[by0:by1, bx0:bx1])
                    known.append(_Known(marker, full, box, template))
            elif self._is_tracked(marker) and marker not in cars:
                cars[marker] = full
        self._known[t] = known
        unplaced = [k for k in known if k.cell is None]
        if unplaced and self.calibrated:
            where = self.geometry.cell_of(
                self._to_arena(np.stack([k.quad for k in unplaced])).mean(1)
            )
            for k, (row, col), ok in zip(
                unplaced, where.tolist(), self.geometry.inside(where), strict=True
            ):
                if ok:
                    k.cell = (_KIND_OF_ID[k.marker], (row, col))
        cells = frozenset(k.cell for k in known if k.cell is not None)
        if cells != self._static[t][0]:
            self._cells = None
        self._static[t] = [self._static[t][1], cells]
        return corners_seen

    @staticmethod
    def _unchanged(roi: np.ndarray, known: _Known) -> bool:
        x0, y0, x1, y1 = known.box
        patch = roi[y0:y1, x0:x1]
        if patch.size != known.template.size:
            return False
        return float(_normalised(patch) @ known.template) >= TEMPLATE_MATCH

    def _paint(self, roi: np.ndarray, off: np.ndarray, quads: list[np.ndarray]) -> None:
        """Paint each marker `quads` (full resolution) over with its paper, in the search image
        `roi` whose full-resolution origin is `off` (all at once: there are dozens)."""
        if not quads:
            return
        limit = np.array(roi.shape[::-1]) - 1
        local = (np.stack(quads) - off) / self._s
        centre = local.mean(1, keepdims=True)
        paper = centre + (local - centre) * (MASK + 0.1)
        near = (paper.max(1) >= 0).all(1) & (paper.min(1) <= limit).all(1)
        ring = np.clip(paper[near], 0, limit).astype(int)
        value = np.median(roi[ring[..., 1], ring[..., 0]], axis=1).tolist()
        paint = np.round(centre[near] + (local[near] - centre[near]) * MASK).astype(np.int32)
        for poly, v in zip(paint, value, strict=True):
            cv2.fillConvexPoly(roi, poly, v)

    def _update_tracks(self, cars: dict[int, np.ndarray], index: int) -> None:
        for marker, corners in cars.items():
            shape = _shape_of(corners)
            tr = self._tracks.get(marker)
            if tr is None or index <= tr.index:
                self._tracks[marker] = _Track(corners, index, shape)
            else:
                gap = index - tr.index
                tr.velocity = ((shape[0] - tr.shape[0]) / gap, (shape[1] - tr.shape[1]) / gap)
                tr.corners, tr.index, tr.shape, tr.misses = corners, index, shape, 0
        for marker in [m for m, tr in self._tracks.items() if tr.index != index]:
            tr = self._tracks[marker]
            tr.misses += 1
            if tr.misses > self._lost_after:
                del self._tracks[marker]

    def _sweep_bounds(self) -> tuple[float, float]:
        """Contour lengths the sweep accepts. The largest markers are the calibration and cell
        markers (same size), so once calibration markers have been seen nothing much longer
        is looked at: floor seams, such as the grid's lines, enclose squares too, and each one
        in range would cost a decode. Until then, a marker side up to a twelfth of the frame."""
        if not self._corner_quads:
            return self._sweep_perimeter
        longest = max(_shape_of(q)[3] for q in self._corner_quads.values())
        return self._sweep_perimeter[0], 1.4 * longest

    def _check_corner(self, img: np.ndarray) -> dict[int, np.ndarray]:
        """Look for one calibration marker (a different one each frame) where it was last seen,
        so a moved camera is noticed within four frames rather than a sweep. Returns it if
        found; a marker not found stops counting for the fit."""
        if not self._corner_quads:
            return {}
        ids = sorted(self._corner_quads)
        marker = ids[self._checks % len(ids)]
        self._checks += 1
        cx, cy, side, length = _shape_of(self._corner_quads[marker])
        box = self._box(cx, cy, 2.5 * side)
        hits = [c for m, c in self._detect(img, box, (0.8 * length, 1.2 * length)) if m == marker]
        if hits:
            return {marker: hits[0]}
        if (
            self._s > 1
            and (quad := self._find(img, marker, cx, cy, 2.5 * side, length)) is not None
        ):
            return {marker: quad}
        del self._corner_quads[marker]
        self._corners.pop(marker, None)
        if len(self._corners) < 3:
            self._homography = None
        return {}

    def _observe_corner(self, marker: int, corners: np.ndarray) -> bool:
        """A calibration marker seen: folded into its average, unless it has shifted beyond the
        tolerance: then the camera has moved and everything measured through the old fit goes.
        Returns whether the set of markers to fit changed."""
        pts = self._undistort(corners)
        old = self._corners.get(marker)
        if old is not None and math.dist(pts.mean(0), old.mean(0)) > self._move_tol:
            self._corners = {}
            self._corner_quads = {}
            self._homography = None
            self._static = [[frozenset(), frozenset()] for _ in self._tiles]
            self._known = [[] for _ in self._tiles]
            self._cells = None
            old = None
        self._corners[marker] = pts if old is None else 0.75 * old + 0.25 * pts
        self._corner_quads[marker] = corners
        return old is None

    def _fit(self) -> None:
        """Homography from the calibration markers seen (three suffice); a fit that does not
        explain its own points (markers seen before and after a camera move) is refused."""
        if len(self._corners) < 3:
            return
        ids = sorted(self._corners)
        src = np.concatenate([self._corners[m] for m in ids])
        dst = np.concatenate([self._corner_arena[m] for m in ids])
        hom, _ = cv2.findHomography(src, dst, 0)
        if hom is None:
            return
        fitted = cv2.perspectiveTransform(src.reshape(-1, 1, 2), hom).reshape(-1, 2)
        if float(np.abs(fitted - dst).max()) <= self._max_residual:
            self._homography = hom

    def _static_cells(self) -> dict[str, frozenset[tuple[int, int]]]:
        if self._cells is None:
            found: dict[str, set[tuple[int, int]]] = {kind: set() for kind in CELL_KIND_IDS}
            for visits in self._static:
                for kind, cell in visits[0] | visits[1]:
                    found[kind].add(cell)
            self._cells = {kind: frozenset(c) for kind, c in found.items()}
        return self._cells

    def _sightings(self, index: int) -> dict[int, CarSighting]:
        seen = [(m, tr) for m, tr in self._tracks.items() if tr.index == index]
        if not seen or not self.calibrated:
            return {}
        arena = self._to_arena(np.stack([tr.corners for _, tr in seen]))
        centres = arena.mean(1)
        cells = self.geometry.cell_of(centres)
        inside = self.geometry.inside(cells)
        out = {}
        for k, (marker, _) in enumerate(seen):
            row, col = int(cells[k, 0]), int(cells[k, 1])
            cx, cy = self.geometry.cell_centre(row, col)
            x, y = float(centres[k, 0]), float(centres[k, 1])
            out[marker] = CarSighting(
                marker=marker,
                cell=(row, col),
                xy=(x, y),
                heading=heading_of(arena[k]),
                offset=(x - cx, y - cy),
                inside=bool(inside[k]),
            )
        return out

    def process(self, frame: Frame) -> Scene:
        """The scene in one frame: track the known cars, sweep one tile, convert to the arena."""
        t0 = time.perf_counter_ns()
        img = frame.image
        if img.shape != self._shape:
            self._setup(img.shape)
        cars = self._track(img, frame.index)
        swept = self._sweep(img, cars)
        checked = self._check_corner(img)
        self._update_tracks(cars, frame.index)
        changed = False
        for marker, quad in [*swept.items(), *checked.items()]:
            changed |= self._observe_corner(marker, quad)
        if changed or (checked and self._checks % len(CORNER_IDS) == 0):
            self._fit()
        sightings = self._sightings(frame.index)
        cells = self._static_cells()
        target = sightings.pop(TARGET_ID, None)
        if target is not None and target.inside:
            cells = {**cells, "target": frozenset([target.cell])}
        return Scene(
            t_capture_ns=frame.t_capture_ns,
            frame_index=frame.index,
            calibrated=self.calibrated,
            cars=sightings,
            cells=cells,
            vision_ns=time.perf_counter_ns() - t0,
        )
