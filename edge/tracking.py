"""Car tracking: a known car is looked for only in a window around where its last sighting and
velocity put it.

The windows of cars of similar apparent size are stacked into one image and searched in one
detector call, with a contour-length range so tight that a car's body and label, squares too,
are not candidates. A marker the search resolution fails to decode (small and noisy) is looked
for again at full resolution. The surround target moves, so it is tracked like a car (by its id:
one target; its window allows for a hop to the next cell).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from udan.edge.detect import MarkerDetector, shape_of, shortest_side
from udan.edge.geometry import RESERVED_IDS, TARGET_ID

SIZE_GROUP = 1.15
"""Cars whose markers' contour lengths are within this ratio are searched in one call; a wider
range would let a small car's label (1.33 times its marker) pass as a candidate."""


@dataclass
class Track:
    """One tracked marker's last sighting."""

    corners: np.ndarray
    """(4, 2) full-resolution image pixels (as detected, distorted)."""
    index: int
    shape: tuple[float, float, float, float]
    """`shape_of(corners)`."""
    shortest: float
    """`shortest_side(corners)`."""
    velocity: tuple[float, float] = (0.0, 0.0)
    """Pixels per frame index."""
    misses: int = 0


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

    def reset(self) -> None:
        """No car seen yet."""
        self.tracks = {}

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
        for again at full resolution (a small, noisy marker sometimes fails to decode)."""
        wanted = []
        for marker, tr in self.tracks.items():
            gap = max(1, index - tr.index)
            cx, cy, side, length = tr.shape
            vx, vy = tr.velocity
            half = (1.3 * side + math.hypot(vx, vy) * gap + 8) * (1 + 0.5 * tr.misses)
            if marker == TARGET_ID or tr.misses:  # a hop, or a car faster than its velocity
                half += self._target_jump * side
            scale = self._detector.scale_for(tr.shortest)
            wanted.append((scale, length, marker, cx + vx * gap, cy + vy * gap, half, tr.shortest))
        wanted.sort()
        found: dict[int, np.ndarray] = {}
        while wanted:
            scale, length = wanted[0][:2]
            n = sum(1 for w in wanted if w[0] == scale and w[1] <= SIZE_GROUP * length)
            found.update(self._track_group(img, [w[1:] for w in wanted[:n]], scale))
            wanted = wanted[n:]
        return found

    def _track_group(
        self, img: np.ndarray, group: list[tuple[float, int, float, float, float, float]], s: int
    ) -> dict[int, np.ndarray]:
        """Search the windows of `group` [(contour length, marker, x, y, half side, shortest
        side)] stacked
        into one image (windows of one common size, shifted to lie inside the frame), downscaled
        by `s` (markers too small for the search resolution are tracked at a finer one)."""
        detector = self._detector
        h, w = detector.shape
        size = min(s * math.ceil(2 * max(g[4] for g in group) / s), h - h % s, w - w % s)
        k = size // s
        stack = np.empty((k * len(group), k), np.uint8)
        origins = []
        for i, (_, _, cx, cy, _, _) in enumerate(group):
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
        side = min(g[5] for g in group)
        ids, quads = detector.markers(stack, bounds, detector.window_for(side, s))
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
        for length, marker, cx, cy, half, side in group:
            if marker not in found and s > 1:
                quad = detector.find(img, marker, (cx, cy), half, length, side)
                if quad is not None:
                    found[marker] = quad
        return found

    def update(self, cars: dict[int, np.ndarray], index: int) -> None:
        """The cars found in frame ``index``: their tracks move on; a track missed more than
        ``lost_after`` frames in a row is dropped (the sweep finds the car again)."""
        for marker, corners in cars.items():
            shape = shape_of(corners)
            tr = self.tracks.get(marker)
            if tr is None or index <= tr.index:
                self.tracks[marker] = Track(corners, index, shape, shortest_side(corners))
            else:
                gap = index - tr.index
                tr.velocity = ((shape[0] - tr.shape[0]) / gap, (shape[1] - tr.shape[1]) / gap)
                tr.corners, tr.index, tr.shape, tr.misses = corners, index, shape, 0
                tr.shortest = shortest_side(corners)
        for marker in [m for m, tr in self.tracks.items() if tr.index != index]:
            tr = self.tracks[marker]
            tr.misses += 1
            if tr.misses > self._lost_after:
                del self.tracks[marker]
