"""Frame -> Scene: where every car is (cell, metres, heading) and what the static cells are.

The budget is 5 ms per 1920x1200 frame on a busy 2-core machine, and a full-frame ArUco search
costs 11-34 ms there, so no frame runs one. ArUco's cost is mostly per call and per candidate
quadrilateral it must decode, not per pixel, so the scheme calls it on small images that hold
few candidates. This module puts the stages together (and sweeps); each concern has its own:

- Detection (:mod:`udan.edge.detect`): one ArUco detector, called on windows at the search
  resolution (half size for a 1200-line frame), a full-resolution second chance for small
  markers. Corners are refined on the contour (CORNER_REFINE_CONTOUR): at half size that is
  accurate enough for 2 cm and a few degrees, where cornerSubPix gets pulled off the corners of
  small markers by their inner pattern.
- Tracking (:mod:`udan.edge.tracking`): a known car is looked for only in a window around where its
  last sighting and velocity put it; the windows of cars of similar apparent size are stacked
  into one image and searched in one call. Markers too thin for full resolution (far markers
  under a tilted camera) are searched at twice it, and a still car whose marker fails to decode
  in a frame is seen by its unchanged look.
- The rest of the image is swept one tile per frame (4 x 3 tiles overlapping by more than a
  marker), after the frame's scene is made (:meth:`Vision.survey`: half the vision's time,
  which the scene need not wait for; its finds are in the next scene), with everything known
  painted out first: tracked cars, calibration markers, and cell markers that still look as
  they did when decoded (normalised correlation). So the sweep decodes only what is new: a car
  that joined or that its track lost, a changed cell, a calibration marker after a camera move.
  A sweep takes 12 frames (300 ms at 40 FPS): that is how long a new car or a changed obstacle
  takes to appear; tracked cars do not wait for it.
  Its size gates, search resolution and threshold window follow the size markers should have
  where each tile looks, from the camera model (:class:`_ExpectedSizes`): a tilted camera sees
  markers near it several times larger than far ones, and labs print car markers at other
  sizes than configured (half to twice). Car markers too small for the search resolution are
  looked for by a second, full-resolution sweep while a listed car is untracked.
- Geometry (:mod:`udan.edge.calibration`): the camera model, fitted to the corners of the
  calibration markers (averaged over sightings), maps a car marker through the plane at its
  height (`marker_heights`, from the fleet file) to the floor. One of them is re-checked every
  frame where it was last seen; shifted by more than `move_tolerance_px`, the camera has moved:
  the fit and the cell readings are dropped and the scene says it is uncalibrated (no cars, no
  cells) rather than wrong, until the sweep has found three calibration markers again, with no
  restart. Lens distortion (a calibration file) is removed from detected corners, not frames.
- Every car sighting carries an error budget; closer to a cell border than that it is
  uncertain, and the control core holds the car rather than command it from a guessed cell.
- A cell marker that one sweep misses stays until the next one misses it too, so noise cannot
  make an obstacle flicker. The surround target moves, so it is tracked like a car (by its id:
  one target; its window allows for a hop to the next cell) and reported as the frame's
  "target" cell.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from udan.edge.calibration import ArenaFit, VisionError, load_calibration
from udan.edge.camera import Frame
from udan.edge.detect import (
    MIN_CONTOUR,
    THRESHOLD_WINDOW,
    ZOOM,
    MarkerDetector,
    normalised,
    shape_of,
    thickness,
)
from udan.edge.geometry import (
    CELL_KIND_IDS,
    CORNER_IDS,
    TARGET_ID,
    ArenaGeometry,
    heading_of,
    square,
)
from udan.edge.heights import HeightCheck
from udan.edge.tracking import CarTracker

MASK = 1.15
"""Known markers are painted out of the sweep image over this many times their size, with the
paper just around them (markers are printed with a one-module margin): only the marker's own
footprint, so a marker next to it is never hidden, and what is left (a blank label, a car's
body) is rejected at a glance instead of decoded."""
TEMPLATE_MATCH = 0.9
"""Normalised correlation with its last decoded look above which a static marker is taken to be
unchanged, and painted out instead of decoded again."""
KEPT_VISITS = 2
"""A tile's static cells are those its last this many visits found: a detection missed once does
not free a cell, and so a marker taken away leaves the map only after this many sweeps without
it (a new one is placed at its tile's next visit)."""
OVERLAP_LINES = 12
"""Sweep tiles overlap by the frame height over this: more than the largest marker's half
extent (a calibration marker, or a car marker printed twice as large, near a tilted camera)."""
CAR_SCALES = (0.5, 2.0)
"""Car markers are found printed from half to twice the configured side."""
SMALL_ZOOMS = 4
"""Candidates of a small-marker sweep window searched again at twice the resolution, at most:
a car marker too thin to decode at full resolution (under a camera tilted 60 degrees, from
afar) is found, and a window full of thin seams costs no more than that."""
SIZE_GRID = 13
"""Arena points per side at which expected marker sizes are computed."""
SIZE_MARGIN = (0.8, 1.25)
"""Slack on the expected sizes (between grid points, corner rounding, a camera just moved)."""
HEIGHT_MODULE_PX = 4.0
"""Car markers with at least this many full-resolution pixels per module are measured for the
height check: cornerSubPix pulls the corners of smaller ones off by their inner pattern."""
STILL_SHARE = 0.01
"""Share of its marker's side a car may move per frame and count as standing still for the
height check (motion blurs a marker's edges); a car crossing a cell in 200 ms at 40 FPS moves
a fifth of its side per frame."""
BUDGET_FLOOR_M = 0.004
"""The least error budget a sighting has (metres): corner refinement and image noise."""
BUDGET_PIXELS = 1.0
"""Image pixels of position error allowed for, at the marker's own scale."""
MISFIT_GAIN = 10.0
"""Times the fit's RMS misfit on the calibration marker corners that a position elsewhere may
be off: an uncorrected lens (k1 from -0.2 to 0.2, tilt 0-60 degrees, roll) puts points between
the markers up to 7.8 times as far off (measured on rendered frames)."""
UNSQUARE_GAIN = 0.5
"""Times its distance from a square that a marker's position may be off."""
PARALLAX_DOUBT = 0.25
"""Without a calibration, the focal length is estimated: this share of a raised marker's
parallax correction is doubted."""
_ARENA = ArenaGeometry()
_KIND_OF_ID = {marker: kind for kind, marker in CELL_KIND_IDS.items()}


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
    uncertain: bool = False
    """Closer to a cell border than `error_budget_m`: the cell may be the next one, so the
    car is held (it waits) rather than commanded from a guessed cell."""
    error_budget_m: float = 0.0
    """How far the car may be from `xy`: the lens model's misfit on the calibration markers,
    a pixel's size where the marker is, how far the marker is from a square, the parallax of
    a raised marker seen through an estimated focal length."""


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
    t_arrival_ns: int | None = None
    """When the camera source handed the frame over (its age: this minus the capture)."""
    warnings: tuple[str, ...] = ()
    """One-line warnings about the setup first known in this frame (each comes once): the arena
    lost or not found (every car held) and found again, a car marker whose size says it is not
    at the fleet file's height (:mod:`udan.edge.heights`).
    Whoever drops a scene passes them on to the next (:meth:`after`)."""

    def after(self, dropped: Scene | None) -> Scene:
        """This scene, carrying the warnings of the scene `dropped` before it."""
        if dropped is None or not dropped.warnings:
            return self
        return dataclasses.replace(self, warnings=dropped.warnings + self.warnings)


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
    scale: int
    """The downscale of the search image it was decoded in."""
    cell: tuple[str, tuple[int, int]] | None = None
    """(kind, (row, col)) once calibrated."""


class _ExpectedSizes:
    """How large markers should look across the image, from the camera model: on a grid of
    arena points (the grid and its calibration markers), the contour lengths of car markers
    printed at CAR_SCALES of their configured side, turned 0 or 45 degrees, on the floor or at
    the highest car marker, and of cell and calibration markers; so the sweep accepts what may
    be a marker where it looks and nothing else."""

    def __init__(self, fit: ArenaFit, geometry: ArenaGeometry, top_m: float) -> None:
        self.version = fit.version
        """The fit these sizes were computed from (:attr:`ArenaFit.version`)."""
        out = geometry.corner_gap_m + geometry.corner_marker_m
        xs = np.linspace(-out, geometry.width_m + out, SIZE_GRID)
        ys = np.linspace(-out, geometry.height_m + out, SIZE_GRID)
        centres = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
        self.image = fit.to_image(centres)
        small, large = CAR_SCALES
        car_lo = side_lo = np.inf
        car_hi = 0.0
        for height in {0.0, top_m}:
            for heading in (0.0, math.pi / 4):
                marker = square((0.0, 0.0), geometry.car_marker_m, heading)
                length, side = _contours(fit.to_image(centres[:, None] + marker, height))
                car_lo = np.minimum(car_lo, small * length)
                side_lo = np.minimum(side_lo, side)
                car_hi = np.maximum(car_hi, large * length)
        floor_m = max(geometry.cell_marker_m, geometry.corner_marker_m)
        marker = square((0.0, 0.0), floor_m, 0.0)
        floor_hi = _contours(fit.to_image(centres[:, None] + marker))[0]
        self.lo = SIZE_MARGIN[0] * car_lo
        self.hi = SIZE_MARGIN[1] * np.maximum(car_hi, floor_hi)
        self.side = side_lo

    def within(self, box: tuple[int, int, int, int]) -> tuple[float, float, float]:
        """(shortest contour, longest contour, least thickness as configured) of a car
        marker in the image window `box`, from the grid points it holds (or, when it holds
        none, the nearest)."""
        x0, y0, x1, y1 = box
        u, v = self.image[:, 0], self.image[:, 1]
        inside = (u >= x0) & (u < x1) & (v >= y0) & (v < y1)
        if not inside.any():
            near = np.hypot(u - (x0 + x1) / 2, v - (y0 + y1) / 2)
            inside = near <= np.partition(near, 3)[3]
        return (
            float(self.lo[inside].min()),
            float(self.hi[inside].max()),
            float(self.side[inside].min()),
        )


def _contours(quads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Contour lengths (as :func:`udan.edge.detect.shape_of`) and thicknesses
    (:func:`udan.edge.detect.thickness`) of quads (n, 4, 2)."""
    length = np.abs(np.roll(quads, -1, axis=1) - quads).max(-1).sum(-1)
    return length, thickness(quads)


def _side_lengths(quads: np.ndarray) -> np.ndarray:
    """The four side lengths (n, 4) of quads (n, 4, 2)."""
    return np.linalg.norm(np.roll(quads, -1, axis=1) - quads, axis=2)


class Vision:
    """Tracks the arena's markers frame after frame; see the module docstring for the scheme."""

    def __init__(
        self,
        geometry: ArenaGeometry = _ARENA,
        *,
        car_markers: Iterable[int] | None = None,
        calibration_file: str | os.PathLike | None = None,
        marker_heights: Mapping[int, float] | None = None,
        sweep_tiles: tuple[int, int] = (4, 3),
        lost_after: int = 3,
        move_tolerance_px: float = 2.0,
        max_residual_m: float = 0.05,
    ) -> None:
        self.geometry = geometry
        self.marker_heights = {m: h for m, h in (marker_heights or {}).items() if h}
        """Car marker id -> metres above the floor (markers not listed lie on it)."""
        self.heights = HeightCheck(self.marker_heights, geometry.car_marker_m)
        calibration = None if calibration_file is None else load_calibration(calibration_file)
        self._sweep_tiles = sweep_tiles
        self.detector = MarkerDetector(geometry.dictionary)
        target_jump = 1.1 * geometry.cell_m / geometry.cell_marker_m
        self.tracker = CarTracker(self.detector, car_markers, target_jump, lost_after)
        self.fit = ArenaFit(geometry, calibration, move_tolerance_px, max_residual_m)
        self.reset()

    def reset(self) -> None:
        """Forget tracks, static cells and calibration (e.g. a different camera)."""
        self.detector.shape = None  # set up again by the next frame
        self.tracker.reset()
        self.fit.reset()
        self._tiles: list[tuple[tuple[int, int, int, int], tuple[int, int, int, int]]] = []
        """Sweep tiles: (core, core plus overlap) as x0, y0, x1, y1."""
        self._static: list[list[frozenset[tuple[str, tuple[int, int]]]]] = []
        """Per sweep tile, the static cells (kind, cell) its last ``KEPT_VISITS`` visits found."""
        self._known: list[list[_Known]] = []
        """Per sweep tile, the cell markers its last visit decoded or recognised."""
        self._cells: dict[str, frozenset[tuple[int, int]]] | None = None
        self._tile = 0
        self._small_tiles: list[tuple[int, int, int, int]] = []
        """Windows of the small-marker sweep (x0, y0, x1, y1): halves of the sweep tiles."""
        self._small_tile = 0
        self._sweeps = 0
        """Sweeps of the whole image completed."""
        self._unsurveyed: tuple[Frame, dict[int, np.ndarray]] | None = None
        """The last frame processed and the cars tracked in it, until :meth:`survey`."""
        self._sizes: _ExpectedSizes | None = None
        self._arena_missing = False
        """The scenes have said that there is no arena (:meth:`_arena_news`)."""
        self._camera_moved = False
        """A calibration marker shifted: why the arena was lost."""

    @property
    def sweep_frames(self) -> int:
        """Frames one sweep of the whole image takes: a layout that changed is fully read after
        ``KEPT_VISITS`` sweeps (markers added after one; cars, tracked, are found sooner)."""
        return self._sweep_tiles[0] * self._sweep_tiles[1]

    @property
    def calibrated(self) -> bool:
        return self.fit.calibrated

    # -- layout ---------------------------------------------------------------------------
    def _setup(self, shape: tuple[int, int]) -> None:
        calibration = self.fit.calibration
        if calibration and calibration.image_size not in (None, shape[::-1]):
            w, h = calibration.image_size
            raise VisionError(
                f"camera calibration is for {w}x{h} frames, the camera gives {shape[1]}x{shape[0]}"
            )
        self.reset()
        self.detector.setup(shape)
        h, w = shape
        self.fit.image_size = (w, h)
        s = self.detector.s
        nx, ny = self._sweep_tiles
        overlap = s * round(h / OVERLAP_LINES / s)
        self._sweep_perimeter = (s * MIN_CONTOUR, h / 2)
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
                middle, half = (ext[1] + ext[3]) // 2, overlap // 2
                self._small_tiles += [
                    (ext[0], ext[1], ext[2], middle + half),
                    (ext[0], middle - half, ext[2], ext[3]),
                ]
        self._static = [[frozenset()] * KEPT_VISITS for _ in self._tiles]
        self._known = [[] for _ in self._tiles]

    # -- per-frame stages -----------------------------------------------------------------
    def _sweep(self, img: np.ndarray, cars: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """One tile of the sweep: adds cars the tracks do not have to `cars`, records the tile's
        static cells, returns the calibration markers it found that were not known. What is
        known (tracked cars, calibration markers, cell markers that still look as they did)
        is painted out first, so the detector decodes only what is new."""
        t = self._tile
        self._tile = (t + 1) % len(self._tiles)
        self._sweeps += self._tile == 0
        (cx0, cy0, cx1, cy1), (x0, y0, x1, y1) = self._tiles[t]
        lo, hi, s, window = self._sweep_bounds(t)
        roi, off = self.detector.window_image(img, (x0, y0, x1, y1), s)
        if s == 1:
            roi = roi.copy()  # painted over below
        known = [k for k in self._known[t] if k.scale == s and self._unchanged(roi, k)]
        masks = [*cars.values(), *self.fit.quads.values(), *(k.quad for k in known)]
        masks += [k.quad for i, ks in enumerate(self._known) if i != t for k in ks]
        self._paint(roi, off, masks, s)
        ids, quads, _ = self.detector.markers(roi, (lo / s, hi / s), window)
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
                    template = normalised(roi[by0:by1, bx0:bx1])
                    known.append(_Known(marker, full, box, template, s))
            elif self.tracker.is_tracked(marker) and marker not in cars:
                cars[marker] = full
        self._known[t] = known
        unplaced = [k for k in known if k.cell is None]
        if unplaced and self.calibrated:
            where = self.geometry.cell_of(
                self.fit.to_arena(np.stack([k.quad for k in unplaced])).mean(1)
            )
            for k, (row, col), ok in zip(
                unplaced, where.tolist(), self.geometry.inside(where), strict=True
            ):
                if ok:
                    k.cell = (_KIND_OF_ID[k.marker], (row, col))
        cells = frozenset(k.cell for k in known if k.cell is not None)
        if cells != self._static[t][0]:  # the visit dropped: the union changes unless equal
            self._cells = None
        self._static[t] = [*self._static[t][1:], cells]
        return corners_seen

    @staticmethod
    def _unchanged(roi: np.ndarray, known: _Known) -> bool:
        x0, y0, x1, y1 = known.box
        patch = roi[y0:y1, x0:x1]
        if patch.size != known.template.size:
            return False
        return float(normalised(patch) @ known.template) >= TEMPLATE_MATCH

    @staticmethod
    def _paint(roi: np.ndarray, off: np.ndarray, quads: list[np.ndarray], scale: int) -> None:
        """Paint each marker `quads` (full resolution) over with its paper, in the search image
        `roi` downscaled by `scale` whose full-resolution origin is `off` (all at once: there
        are dozens)."""
        if not quads:
            return
        limit = np.array(roi.shape[::-1]) - 1
        local = (np.stack(quads) - off) / scale
        centre = local.mean(1, keepdims=True)
        paper = centre + (local - centre) * (MASK + 0.1)
        near = (paper.max(1) >= 0).all(1) & (paper.min(1) <= limit).all(1)
        ring = np.clip(paper[near], 0, limit).astype(int)
        value = np.median(roi[ring[..., 1], ring[..., 0]], axis=1).tolist()
        paint = np.round(centre[near] + (local[near] - centre[near]) * MASK).astype(np.int32)
        for poly, v in zip(paint, value, strict=True):
            cv2.fillConvexPoly(roi, poly, v)

    def _sweep_bounds(self, tile: int) -> tuple[float, float, int, int]:
        """Contour lengths (full-resolution pixels) the sweep of `tile` accepts, the downscale
        to search it at and the threshold window there. Once the camera model is known, they
        follow the markers' expected image size where the tile looks (:class:`_ExpectedSizes`):
        floor seams, such as the grid's lines, enclose squares too, and each one in range would
        cost a decode, while under a tilted camera a marker near it is several times one far
        away. Until
        then, a marker side up to an eighth of the frame, every other sweep at full
        resolution (a far calibration marker of a tilted camera may be too small for the
        search resolution)."""
        if not self.calibrated:
            scale = self.detector.s if self._sweeps % 2 == 0 else 1
            return (*self._sweep_perimeter, scale, THRESHOLD_WINDOW * self.detector.s // scale | 1)
        if self._sizes is None or self._sizes.version != self.fit.version:
            self._sizes = _ExpectedSizes(
                self.fit, self.geometry, max(self.marker_heights.values(), default=0.0)
            )
        _, ext = self._tiles[tile]
        lo, hi, side = self._sizes.within(ext)
        # markers printed smaller than configured are looked for every other sweep, at the
        # resolution they need: most labs print them as configured, and it costs
        scale = self.detector.scale_for(side)
        return max(lo, scale * MIN_CONTOUR), hi, scale, self.detector.window_for(side, scale)

    def _sweep_small(self, img: np.ndarray, cars: dict[int, np.ndarray]) -> None:
        """One window of the small-marker sweep: car markers printed smaller than configured
        may be too small for the search resolution, so while a car of the fleet is not tracked,
        one window a frame (half a sweep tile) is searched at full resolution for
        markers between the smallest car marker expected there and the configured size, and
        the thinnest candidates that do not decode there once more at twice it."""
        if not self.calibrated or not self.tracker.missing():
            return
        t = self._small_tile
        self._small_tile = (t + 1) % len(self._small_tiles)
        box = self._small_tiles[t]
        lo, _, side = self._sizes.within(box)
        small = side * CAR_SCALES[0]
        if self.detector.scale_for(small) >= self.detector.s:
            return  # the main sweep reads them
        hi = lo / CAR_SCALES[0] * SIZE_MARGIN[1] / SIZE_MARGIN[0]
        found = self.detector.detect(img, box, (lo, hi), 1, small, zoom_thin=SMALL_ZOOMS)
        for marker, quad in found:
            if self.tracker.is_tracked(marker) and marker not in cars:
                cars[marker] = quad

    def _check_corner(self, img: np.ndarray) -> dict[int, np.ndarray]:
        """Look for one calibration marker (a different one each frame) where it was last seen,
        so a moved camera is noticed within four frames rather than a sweep; a second time one
        resolution finer if the first search misses it. Returns it if found; a marker not found
        stops counting for the fit."""
        check = self.fit.next_check()
        if check is None:
            return {}
        marker, quad = check
        detector = self.detector
        cx, cy, side, length = shape_of(quad)
        thin = float(thickness(quad))
        scale = detector.scale_for(thin, zoom=True)
        for s in dict.fromkeys((scale, 1 if scale > 1 else ZOOM)):
            found = detector.find(img, marker, (cx, cy), 2.5 * side, length, thin, s)
            if found is not None:
                return {marker: found}
        self.fit.lost(marker)
        return {}

    def _observe_corner(self, marker: int, corners: np.ndarray) -> bool:
        """A calibration marker seen (:meth:`udan.edge.calibration.ArenaFit.observe`); if the camera
        has moved, everything measured through the old fit goes too. Returns whether the set
        of markers to fit changed."""
        changed, moved = self.fit.observe(marker, corners)
        if moved:
            self._camera_moved = True
            self._static = [[frozenset()] * KEPT_VISITS for _ in self._tiles]
            self._known = [[] for _ in self._tiles]
            self._cells = None
        return changed

    def _static_cells(self) -> dict[str, frozenset[tuple[int, int]]]:
        if self._cells is None:
            found: dict[str, set[tuple[int, int]]] = {kind: set() for kind in CELL_KIND_IDS}
            for visits in self._static:
                for kind, cell in frozenset().union(*visits):
                    found[kind].add(cell)
            self._cells = {kind: frozenset(c) for kind, c in found.items()}
        return self._cells

    def _sightings(self, index: int) -> dict[int, CarSighting]:
        seen = [(m, tr) for m, tr in self.tracker.tracks.items() if tr.index == index]
        if not seen or not self.calibrated:
            return {}
        arena = np.empty((len(seen), 4, 2))
        heights = np.array([self.marker_heights.get(m, 0.0) for m, _ in seen])
        for height in set(heights.tolist()):
            on = heights == height
            corners = np.stack([tr.corners for (_, tr), o in zip(seen, on, strict=True) if o])
            arena[on] = self.fit.to_arena(corners, height)
        centres = arena.mean(1)
        cells = self.geometry.cell_of(centres)
        inside = self.geometry.inside(cells)
        budgets = self._error_budgets(arena, np.array([tr.shape[2] for _, tr in seen]))
        if self.fit.calibration is None and heights.any():
            floor = self.fit.to_arena(np.stack([tr.corners for _, tr in seen])).mean(1)
            budgets += PARALLAX_DOUBT * np.linalg.norm(floor - centres, axis=1)
        half = self.geometry.cell_m / 2
        out = {}
        for k, (marker, _) in enumerate(seen):
            row, col = int(cells[k, 0]), int(cells[k, 1])
            cx, cy = self.geometry.cell_centre(row, col)
            x, y = float(centres[k, 0]), float(centres[k, 1])
            budget = float(budgets[k])
            out[marker] = CarSighting(
                marker=marker,
                cell=(row, col),
                xy=(x, y),
                heading=heading_of(arena[k]),
                offset=(x - cx, y - cy),
                inside=bool(inside[k]),
                uncertain=half - max(abs(x - cx), abs(y - cy)) < budget,
                error_budget_m=budget,
            )
        return out

    def _arena_news(self) -> str | None:
        """The line that says the arena is gone (no camera model: no car is placed, the control
        core holds every car), with why; and the one that says it is back. Gone means lost
        after a fit, or not found in two sweeps from the start."""
        # said already (placed, or gone), or still looking for the arena at the start
        if self.calibrated != self._arena_missing or (self.fit.version == 0 and self._sweeps < 2):
            return None
        seen = ", ".join(map(str, sorted(self.fit.corners))) or "none"
        if self.calibrated:
            self._arena_missing = self._camera_moved = False
            return f"arena found again (calibration markers {seen}): cars are placed again"
        self._arena_missing = True
        why = "the camera moved, " if self._camera_moved else ""
        return (
            f"no arena: {why}calibration markers seen: {seen} (3 of {CORNER_IDS[0]}-"
            f"{CORNER_IDS[-1]} needed); every car is held until they are"
        )

    def _check_height(self, img: np.ndarray, index: int) -> str | None:
        """Measure one car marker a frame (in turn) for the height check
        (:mod:`udan.edge.heights`): one decoded in this frame, standing still, large enough
        for its corners to be refined at full resolution; returns its warning if this sighting
        completes one. Only with a calibration file: without one the camera's height is an
        estimate, and a lens not described bends the markers' sides."""
        if self.fit.calibration is None or not self.calibrated:
            return None  # the camera's height is only estimated, the lens maybe not described
        thick = HEIGHT_MODULE_PX * self.detector.modules
        ready = [
            (m, tr)
            for m, tr in self.tracker.tracks.items()
            if tr.index == index
            and m != TARGET_ID
            and m not in self.heights.done
            and m not in self.tracker.unmoved
            and tr.thickness >= thick
            and math.hypot(*tr.velocity) < STILL_SHARE * tr.shape[2]
        ]
        if not ready:
            return None
        marker, tr = ready[index % len(ready)]
        camera_height = self.fit.camera_height()
        refined = self.detector.refine(img, tr.corners)
        side = float(
            _side_lengths(self.fit.to_arena(refined, self.heights.told(marker))[None]).mean()
        )
        r, t = self.fit.pose
        foot = -(r.T @ t)[:2]
        g = self.geometry
        grid = np.array([[0.0, 0.0], [g.width_m, 0.0], [g.width_m, g.height_m], [0.0, g.height_m]])
        reach = float(np.linalg.norm(grid - foot, axis=1).max())
        return self.heights.add(marker, side, camera_height, reach)

    def budgets_at_cells(self) -> np.ndarray:
        """(rows, cols): the error budget (metres) of a car marker on the floor at each cell's
        centre, the worse of two headings; what `udan-calibrate check` shows a lab."""
        g = self.geometry
        rows, cols = np.mgrid[0 : g.rows, 0 : g.cols]
        centres = np.stack([(cols.ravel() + 0.5) * g.cell_m, (rows.ravel() + 0.5) * g.cell_m], 1)
        worst = np.zeros(len(centres))
        for heading in (0.0, math.pi / 4):
            arena = centres[:, None] + square((0.0, 0.0), g.car_marker_m, heading)
            image = self.fit.to_image(arena)
            sides = _side_lengths(image).mean(1)
            worst = np.maximum(worst, self._error_budgets(arena, sides))
        return worst.reshape(g.rows, g.cols)

    def _error_budgets(self, arena: np.ndarray, image_sides: np.ndarray) -> np.ndarray:
        """Per marker (arena corners (n, 4, 2), mean image sides (n,)): how far its true position
        may be from the measured one (metres); see `CarSighting.error_budget_m`."""
        edges = _side_lengths(arena)
        side = edges.mean(1)
        diagonals = np.linalg.norm(arena[:, 2:] - arena[:, :2], axis=2)
        unsquare = np.maximum(
            np.abs(edges - side[:, None]).max(1),
            np.abs(diagonals - side[:, None] * math.sqrt(2)).max(1) / math.sqrt(2),
        )
        pixel = side / np.maximum(image_sides, 1.0)
        return (
            BUDGET_FLOOR_M
            + BUDGET_PIXELS * pixel
            + MISFIT_GAIN * self.fit.misfit_m
            + UNSQUARE_GAIN * unsquare
        )

    def process(self, frame: Frame) -> Scene:
        """The scene in one frame: the known cars tracked (and a calibration marker checked),
        converted to the arena. The frame's :meth:`survey` is left for later: the caller runs
        it once the scene is on its way, or this runs it first for the next frame."""
        self.survey()
        t0 = time.perf_counter_ns()
        img = frame.image
        if img.shape != self.detector.shape:
            self._setup(img.shape)
        cars = self.tracker.track(img, frame.index)
        checked = self._check_corner(img)
        self.tracker.update(cars, frame.index, img)
        self._observe(img, checked, every_check=True)
        sightings = self._sightings(frame.index)
        warnings = (self._arena_news(), self._check_height(img, frame.index))
        cells = self._static_cells()
        target = sightings.pop(TARGET_ID, None)
        if target is not None and target.inside:
            cells = {**cells, "target": frozenset([target.cell])}
        self._unsurveyed = (frame, cars)
        return Scene(
            t_capture_ns=frame.t_capture_ns,
            frame_index=frame.index,
            calibrated=self.calibrated,
            cars=sightings,
            cells=cells,
            vision_ns=time.perf_counter_ns() - t0,
            t_arrival_ns=frame.t_arrival_ns,
            warnings=tuple(w for w in warnings if w is not None),
        )

    def survey(self) -> None:
        """The last processed frame's survey, if not run yet: one tile of the sweep (cars the
        tracks lack, the tile's cell markers, calibration markers) and, while a car is
        missing, one window of the small-marker sweep. What it finds is in the next scene."""
        if self._unsurveyed is None:
            return
        frame, tracked = self._unsurveyed
        self._unsurveyed = None
        if not frame.intact():
            return  # its lent image has been reused: the next frame's tile waits a frame
        img, cars = frame.image, dict(tracked)
        swept = self._sweep(img, cars)
        self._sweep_small(img, cars)
        self.tracker.update(
            {m: q for m, q in cars.items() if m not in tracked}, frame.index, img, misses=False
        )
        self._observe(img, swept, every_check=False)

    def _observe(self, img: np.ndarray, corners: dict[int, np.ndarray], every_check: bool) -> None:
        """Calibration markers found (refined first) into the fit, refitted when the set of
        markers changed or, for the markers checked one a frame, once a round of checks."""
        changed = False
        for marker, quad in corners.items():
            changed |= self._observe_corner(marker, self.detector.refine(img, quad))
        if changed or (every_check and corners and self.fit.checks % len(CORNER_IDS) == 0):
            self.fit.fit()
