"""Car tracking: a known car is looked for only in a window around where its last sighting and
velocity put it.

The windows of cars of similar apparent size are stacked into one image and searched in one
detector call, with a contour-length range so tight that a car's body and label, squares too,
are not candidates. A marker the search resolution fails to decode (small and noisy) is looked
for again one resolution finer. One still missed whose pixels look as they did when it was last
decoded (a car standing still, seen by a tilted camera from afar: the thinnest markers fail to
decode in one frame in twenty) is where it was. The surround target moves, so it is tracked like
a car (by its id: one target; its window allows for a hop to the next cell).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from udan.edge.detect import ZOOM, MarkerDetector, normalised, shape_of, thickness
from udan.edge.geometry import RESERVED_IDS, TARGET_ID

SIZE_GROUP = 1.15
"""Cars whose markers' contour lengths are within this ratio are searched in one call; a wider
range would let a small car's label (1.33 times its marker) pass as a candidate."""
UNCHANGED = 0.95
"""Normalised correlation with its look when last decoded above which a marker the detector
missed is taken to stand where it was decoded. Measured on rendered frames under a 60° tilt
(noise and blur): the same marker unmoved 0.998, moved 5 mm 0.81-0.87, turned 1° 0.99, another
marker in its place 0.62-0.73."""


@dataclass
class Track:
    """One tracked marker's last sighting."""

    corners: np.ndarray
    """(4, 2) full-resolution image pixels (as detected, distorted)."""
    index: int
    shape: tuple[float, float, float, float]
    """`shape_of(corners)`."""
    thickness: float
    """`thickness(corners)`."""
    velocity: tuple[float, float] = (0.0, 0.0)
    """Pixels per frame index."""
    misses: int = 0
    look: np.ndarray | None = None
    """The image's pixels in `look_box` when the marker was last decoded; kept for markers
    too thin for the search resolution, the ones that may fail to decode."""
    look_box: tuple[int, int, int, int] = (0, 0, 0, 0)
    """The marker's bounding box (x0, y0, x1, y1) then, with a pixel of margin."""


class CarTracker:
    """The tracks of the cars (and the surround target) seen so far."""

    def __init__(
        self,
        detector: MarkerDetector,
        car_markers: Iterable[int] | None,
        target_jump: float,
        lost_after: int,
    ) -> None:
        self._detector = detector
        self._car_ids = None if car_markers is None else frozenset(car_markers)
        self._target_jump = target_jump
        """A target marker is drawn on its cell and may hop to the next: its search window
        allows for a cell's step (in marker sides) besides its velocity."""
        self._lost_after = lost_after
        self.tracks: dict[int, Track] = {}
        self.unmoved: set[int] = set()
        """Markers `track` found by their look, not decoded, in the current frame."""

    def reset(self) -> None:
        """No car seen yet."""
        self.tracks = {}
        self.unmoved = set()

    def is_tracked(self, marker: int) -> bool:
        """Cars, and the surround target: it moves like one."""
        if marker == TARGET_ID:
            return True
        if self._car_ids is not None:
            return marker in self._car_ids
        return marker not in RESERVED_IDS

    def missing(self) -> bool:
        """Whether a car may be in view untracked: a listed car without a track (with no list,
        any car could join)."""
        return self._car_ids is None or not self._car_ids <= self.tracks.keys()

    def track(self, img: np.ndarray, index: int) -> dict[int, np.ndarray]:
        """Each tracked car, searched for in a window around its predicted position; returns
        the approximate corners of those found. Windows of cars whose markers look alike in
        size are stacked into one image and searched in one detector call (a call has a fixed
        cost comparable to decoding a marker); a car the search resolution misses is looked
        for again one resolution finer (a small, noisy marker sometimes fails to decode), and
        one still missed whose pixels look as when it was last decoded is where it was then."""
        wanted = []
        for marker, tr in self.tracks.items():
            gap = max(1, index - tr.index)
            cx, cy, side, length = tr.shape
            vx, vy = tr.velocity
            half = (1.3 * side + math.hypot(vx, vy) * gap + 8) * (1 + 0.5 * tr.misses)
            if marker == TARGET_ID or tr.misses:  # a hop, or a car faster than its velocity
                half += self._target_jump * side
            scale = self._detector.scale_for(tr.thickness, zoom=True)
            wanted.append((scale, length, marker, cx + vx * gap, cy + vy * gap, half, tr.thickness))
        wanted.sort()
        found: dict[int, np.ndarray] = {}
        while wanted:
            scale, length = wanted[0][:2]
            n = sum(1 for w in wanted if w[0] == scale and w[1] <= SIZE_GROUP * length)
            found.update(self._track_group(img, [w[1:] for w in wanted[:n]], scale))
            wanted = wanted[n:]
        self.unmoved = {
            m for m, tr in self.tracks.items() if m not in found and self._looks_unmoved(img, tr)
        }
        found.update((m, self.tracks[m].corners) for m in self.unmoved)
        return found

    @staticmethod
    def _looks_unmoved(img: np.ndarray, tr: Track) -> bool:
        if tr.look is None:
            return False
        x0, y0, x1, y1 = tr.look_box
        return float(normalised(img[y0:y1, x0:x1]) @ normalised(tr.look)) >= UNCHANGED

    def _track_group(
        self, img: np.ndarray, group: list[tuple[float, int, float, float, float, float]], s: float
    ) -> dict[int, np.ndarray]:
        """Search the windows of `group` [(contour length, marker, x, y, half side,
        thickness)] stacked into one image (windows of one common size, shifted to lie inside
        the frame), downscaled by `s` (markers too small for the search resolution are tracked
        at a finer one, the thinnest at ZOOM). A marker not found there is looked for again
        alone, one resolution finer (at ZOOM, with a threshold window twice as wide)."""
        detector = self._detector
        h, w = detector.shape
        step = max(1, int(s))
        size = min(
            step * math.ceil(2 * max(g[4] for g in group) / step), h - h % step, w - w % step
        )
        k = round(size / s)
        stack = np.empty((k * len(group), k), np.uint8)
        origins = []
        for i, (_, _, cx, cy, _, _) in enumerate(group):
            x0 = min(max(int(cx - size / 2), 0), w - size)
            y0 = min(max(int(cy - size / 2), 0), h - size)
            window = img[y0 : y0 + size, x0 : x0 + size]
            if s != 1:
                how = cv2.INTER_AREA if s > 1 else cv2.INTER_CUBIC
                cv2.resize(window, (k, k), dst=stack[i * k : (i + 1) * k], interpolation=how)
            else:
                stack[i * k : (i + 1) * k] = window
            origins.append((x0 + (s - 1) / 2, y0 + (s - 1) / 2 - i * size))
        bounds = (0.8 * group[0][0] / s, 1.2 * group[-1][0] / s)
        side = min(g[5] for g in group)
        ids, quads, _ = detector.markers(stack, bounds, detector.window_for(side, s))
        found: dict[int, np.ndarray] = {}
        for marker, quad in zip(ids, quads, strict=True):
            i = int(quad[:, 1].mean() // k)
            _, want, cx, cy, _, _ = group[i]
            if marker != want:
                continue
            full = quad * s + origins[i]
            if marker not in found or math.dist(full.mean(0), (cx, cy)) < math.dist(
                found[marker].mean(0), (cx, cy)
            ):
                found[marker] = full
        finer = 1 if s > 1 else ZOOM
        for length, marker, cx, cy, half, side in group:
            if marker not in found:
                wider = 2 * side if s == ZOOM else side
                quad = detector.find(img, marker, (cx, cy), half, length, wider, finer)
                if quad is not None:
                    found[marker] = quad
        return found

    def update(
        self, cars: dict[int, np.ndarray], index: int, img: np.ndarray, *, misses: bool = True
    ) -> None:
        """The cars found in frame ``index`` of `img`: their tracks move on (and keep the look
        of those decoded); a track missed more than ``lost_after`` frames in a row is dropped
        (the sweep finds the car again). ``misses=False``: more cars of a frame already
        counted (the sweep's), no track missed again."""
        h, w = img.shape
        thick = thickness(np.stack(list(cars.values()))).tolist() if cars else []
        for (marker, corners), thin in zip(cars.items(), thick, strict=True):
            shape = shape_of(corners)
            tr = self.tracks.get(marker)
            if tr is None or index <= tr.index:
                tr = self.tracks[marker] = Track(corners, index, shape, thin)
            else:
                gap = index - tr.index
                tr.velocity = ((shape[0] - tr.shape[0]) / gap, (shape[1] - tr.shape[1]) / gap)
                tr.corners, tr.index, tr.shape, tr.misses = corners, index, shape, 0
                tr.thickness = thin
            if self._detector.scale_for(thin, zoom=True) == self._detector.s:
                tr.look = None  # the search resolution, then the full one, decode it every time
            elif marker not in self.unmoved:
                (x0, y0), (x1, y1) = corners.min(0).tolist(), corners.max(0).tolist()
                x0, y0 = max(math.floor(x0) - 1, 0), max(math.floor(y0) - 1, 0)
                x1, y1 = min(math.ceil(x1) + 2, w), min(math.ceil(y1) + 2, h)
                tr.look_box = (x0, y0, x1, y1)
                tr.look = img[y0:y1, x0:x1].copy()
        if not misses:
            return
        for marker in [m for m, tr in self.tracks.items() if tr.index != index]:
            tr = self.tracks[marker]
            tr.misses += 1
            if tr.misses > self._lost_after:
                del self.tracks[marker]
