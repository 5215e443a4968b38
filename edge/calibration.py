"""Camera geometry: image pixels -> arena metres.

A calibration file (OpenCV's YAML) gives the lens; its distortion is removed from detected
corners, not from frames. A homography (undistorted image pixels -> arena metres) is fitted to
the corners of the calibration markers, averaged over sightings. One of them is re-checked every
frame where it was last seen; shifted by more than ``move_tolerance_px``, the camera has moved:
the fit is dropped (and the vision drops its cell readings) until three calibration markers have
been seen again, with no restart.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import cv2
import numpy as np

from udan.edge.geometry import ArenaGeometry

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


class ArenaFit:
    """The calibration markers seen, and the homography fitted to them."""

    def __init__(
        self,
        geometry: ArenaGeometry,
        calibration: CameraCalibration | None,
        move_tolerance_px: float,
        max_residual_m: float,
    ) -> None:
        self.calibration = calibration
        self._corner_arena = geometry.corner_points()
        self._move_tol = move_tolerance_px
        self._max_residual = max_residual_m
        self.reset()

    def reset(self) -> None:
        """No calibration marker seen, no fit."""
        self.corners: dict[int, np.ndarray] = {}
        """Calibration marker corners, undistorted and smoothed over sightings."""
        self.quads: dict[int, np.ndarray] = {}
        """The last sighting of each calibration marker as detected (where to look again)."""
        self.checks = 0
        self.homography: np.ndarray | None = None

    @property
    def calibrated(self) -> bool:
        return self.homography is not None

    def undistort(self, pts: np.ndarray) -> np.ndarray:
        if self.calibration is None:
            return pts
        cal = self.calibration
        out = cv2.undistortPoints(
            pts.reshape(-1, 1, 2),
            cal.camera_matrix,
            cal.dist_coeffs,
            P=cal.camera_matrix,
            criteria=_UNDISTORT,
        )
        return out.reshape(pts.shape)

    def to_arena(self, pts: np.ndarray) -> np.ndarray:
        flat = self.undistort(pts.reshape(-1, 2)).reshape(-1, 1, 2)
        return cv2.perspectiveTransform(flat, self.homography).reshape(pts.shape)

    def next_check(self) -> tuple[int, np.ndarray] | None:
        """The calibration marker to look for again this frame (a different one each frame),
        with its last sighting; None before any was seen."""
        if not self.quads:
            return None
        ids = sorted(self.quads)
        marker = ids[self.checks % len(ids)]
        self.checks += 1
        return marker, self.quads[marker]

    def lost(self, marker: int) -> None:
        """A calibration marker not found where it was: it stops counting for the fit."""
        del self.quads[marker]
        self.corners.pop(marker, None)
        if len(self.corners) < 3:
            self.homography = None

    def observe(self, marker: int, corners: np.ndarray) -> tuple[bool, bool]:
        """A calibration marker seen: folded into its average, unless it has shifted beyond the
        tolerance: then the camera has moved and the fit goes. Returns whether the set of
        markers to fit changed, and whether the camera moved."""
        pts = self.undistort(corners)
        old = self.corners.get(marker)
        moved = old is not None and math.dist(pts.mean(0), old.mean(0)) > self._move_tol
        if moved:
            self.corners = {}
            self.quads = {}
            self.homography = None
            old = None
        self.corners[marker] = pts if old is None else 0.75 * old + 0.25 * pts
        self.quads[marker] = corners
        return old is None, moved

    def fit(self) -> None:
        """Homography from the calibration markers seen (three suffice); a fit that does not
        explain its own points (markers seen before and after a camera move) is refused."""
        if len(self.corners) < 3:
            return
        ids = sorted(self.corners)
        src = np.concatenate([self.corners[m] for m in ids])
        dst = np.concatenate([self._corner_arena[m] for m in ids])
        hom, _ = cv2.findHomography(src, dst, 0)
        if hom is None:
            return
        fitted = cv2.perspectiveTransform(src.reshape(-1, 1, 2), hom).reshape(-1, 2)
        if float(np.abs(fitted - dst).max()) <= self._max_residual:
            self.homography = hom
