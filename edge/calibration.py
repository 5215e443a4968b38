"""Camera geometry: image pixels -> arena metres, on the floor or on a plane above it.

A calibration file (OpenCV's YAML) gives the lens; its distortion is removed from detected
corners, not from frames. The camera's pose is fitted to the corners of the calibration markers,
averaged over sightings: with a calibration, by solvePnP (six unknowns: three corner markers
place a tilted camera to a few millimetres, where an eight-unknown homography from three
clustered markers extrapolates to the fourth corner with centimetres of error); without one, by
a homography, from which a focal length is estimated (principal point at the image centre,
square pixels) for the planes above the floor. A car marker ``h`` metres above the floor is
mapped through its own plane's homography, so it lands where the car is, not where its ray meets
the floor.

One calibration marker is re-checked every frame where it was last seen; shifted by more than
``move_tolerance_px``, the camera has moved: the fit is dropped (and the vision drops its cell
readings) until three calibration markers have been seen again, with no restart.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import cv2
import numpy as np

from udan.edge.geometry import ArenaGeometry

_UNDISTORT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)


CORNER_NOISE_PX = 0.3
"""RMS image noise of a refined calibration marker corner (measured on rendered frames with
sensor noise and blur: 0.1-0.3 pixel)."""


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


def focal_from_homography(arena_to_image: np.ndarray, centre: tuple[float, float]) -> float | None:
    """The focal length (pixels) that makes a plane's homography a rotation and a translation,
    for a camera with square pixels and its principal point at `centre` (Zhang's constraints);
    None when the plane is seen nearly face-on, which leaves the focal length undetermined."""
    shift = np.array([[1.0, 0.0, -centre[0]], [0.0, 1.0, -centre[1]], [0.0, 0.0, 1.0]])
    g = shift @ arena_to_image
    g1, g2 = g[:, 0], g[:, 1]
    # columns orthogonal, and of equal length, once divided by diag(f, f, 1)
    rows = np.array([[g1[0] * g2[0] + g1[1] * g2[1], g1[2] * g2[2]]])
    rows = np.vstack(
        [rows, [g1[0] ** 2 + g1[1] ** 2 - g2[0] ** 2 - g2[1] ** 2, g1[2] ** 2 - g2[2] ** 2]]
    )
    # a * (1 / f^2) + b = 0 for each row; least squares in 1 / f^2
    a, b = rows[:, 0], rows[:, 1]
    if float(a @ a) == 0:
        return None
    inv_f2 = -float(a @ b) / float(a @ a)
    scale = float(np.abs(b).max()) / max(float(np.abs(a).max()), 1e-300)
    if inv_f2 <= 0 or scale < 1e-3 * inv_f2:
        return None
    return 1.0 / math.sqrt(inv_f2)


class ArenaFit:
    """The calibration markers seen, and the camera pose fitted to them."""

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
        self.image_size: tuple[int, int] | None = None
        """(width, height) of the frames, for the principal point of an uncalibrated camera."""
        self.reset()

    def reset(self) -> None:
        """No calibration marker seen, no fit."""
        self.corners: dict[int, np.ndarray] = {}
        """Calibration marker corners, undistorted and smoothed over sightings."""
        self.quads: dict[int, np.ndarray] = {}
        """The last sighting of each calibration marker as detected (where to look again)."""
        self.checks = 0
        self.version = 0
        """Counts fits from a new set of calibration markers (or after a camera move): what was
        computed from an older version is out of date; refits of the same set are not counted."""
        self._fitted: tuple[int, ...] = ()
        self.homography: np.ndarray | None = None
        """Undistorted image pixels -> arena metres on the floor."""
        self.camera_matrix: np.ndarray | None = None
        """The calibration's, or estimated from the fit (None when it cannot be)."""
        self.pose: tuple[np.ndarray, np.ndarray] | None = None
        """(R, t): arena (x, y, z into the floor) -> camera coordinates."""
        self.residual_m = 0.0
        """Largest distance between a calibration marker corner and where the fit puts it."""
        self.misfit_m = 0.0
        """The fit's RMS distance from the calibration marker corners beyond what corner noise
        (CORNER_NOISE_PX) explains: a lens the camera model does not describe."""
        self._estimated = False
        self._lift: np.ndarray | None = None
        """K r3, scaled like the floor's image homography: what a metre up adds to it."""
        self._planes: dict[float, np.ndarray] = {}

    @property
    def calibrated(self) -> bool:
        return self.homography is not None

    def camera_height(self) -> float | None:
        """Metres from the floor up to the camera, once its pose is known."""
        if self._lift_vector() is None:
            return None
        r, t = self.pose
        return float((r.T @ t)[2])

    def plane_homography(self, height: float) -> np.ndarray:
        """Undistorted image pixels -> arena (x, y) on the plane `height` metres above the
        floor; the floor's own homography when the pose is unknown."""
        lift = None if height == 0 else self._lift_vector()
        if lift is None:
            return self.homography
        cached = self._planes.get(height)
        if cached is None:
            # a point (x, y, -height) is at x r1 + y r2 + t - height r3 in the camera
            to_image = np.linalg.inv(self.homography)
            to_image[:, 2] -= height * lift
            cached = self._planes[height] = np.linalg.inv(to_image)
        return cached

    def to_image(self, xy: np.ndarray, height: float = 0.0) -> np.ndarray:
        """Image pixels (as detected, distorted) of arena points `xy` (..., 2) `height` metres
        above the floor."""
        xy = np.asarray(xy, dtype=np.float64)
        flat = xy.reshape(-1, 1, 2)
        pix = cv2.perspectiveTransform(flat, np.linalg.inv(self.plane_homography(height)))
        return self.distort(pix).reshape(xy.shape)

    def distort(self, pts: np.ndarray) -> np.ndarray:
        """Image pixels as the camera shows them of undistorted pixel points `pts` (..., 2)."""
        cal = self.calibration
        if cal is None:
            return pts
        k = cal.camera_matrix
        normal = cv2.undistortPoints(pts.reshape(-1, 1, 2), k, None)  # to normalised coordinates
        world = cv2.convertPointsToHomogeneous(normal).reshape(-1, 3)
        pix, _ = cv2.projectPoints(world, np.zeros(3), np.zeros(3), k, cal.dist_coeffs)
        return pix.reshape(pts.shape)

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

    def to_arena(self, pts: np.ndarray, height: float = 0.0) -> np.ndarray:
        """Arena (x, y) of image points `pts` (..., 2) that lie `height` metres above the floor."""
        flat = self.undistort(pts.reshape(-1, 2)).reshape(-1, 1, 2)
        return cv2.perspectiveTransform(flat, self.plane_homography(height)).reshape(pts.shape)

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
            self._drop_fit()

    def _drop_fit(self) -> None:
        self.homography = None
        self.pose = None
        self._lift = None
        self._planes = {}

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
            self._drop_fit()
            old = None
        self.corners[marker] = pts if old is None else 0.75 * old + 0.25 * pts
        self.quads[marker] = corners
        return old is None, moved

    def fit(self) -> None:
        """The camera pose from the calibration markers seen (three suffice); a fit that does
        not explain its own points (markers seen before and after a camera move) is refused."""
        if len(self.corners) < 3:
            return
        ids = sorted(self.corners)
        src = np.concatenate([self.corners[m] for m in ids])
        dst = np.concatenate([self._corner_arena[m] for m in ids])
        if self.calibration is not None:
            fitted = self._fit_pose(src, dst, self.calibration.camera_matrix)
        else:
            hom, _ = cv2.findHomography(src, dst, 0)
            fitted = None if hom is None else (hom, None, None, None)
        if fitted is None:
            return
        hom, k, pose, lift = fitted
        mapped = cv2.perspectiveTransform(src.reshape(-1, 1, 2), hom).reshape(-1, 2)
        misses = np.linalg.norm(mapped - dst, axis=1)
        residual = float(misses.max())
        if residual <= self._max_residual:
            back = cv2.perspectiveTransform(dst.reshape(-1, 1, 2), np.linalg.inv(hom))
            rms_px = float(np.sqrt(np.mean(np.sum((back.reshape(-1, 2) - src) ** 2, axis=1))))
            rms_m = float(np.sqrt(np.mean(misses**2)))
            # what corner noise explains is no lens misfit
            self.misfit_m = rms_m * max(0.0, 1.0 - CORNER_NOISE_PX / max(rms_px, 1e-9))
            if self.homography is None or tuple(ids) != self._fitted:
                self.version += 1
                self._fitted = tuple(ids)
            self.homography, self.camera_matrix, self.pose = hom, k, pose
            self._lift = lift
            self._estimated = False
            self.residual_m = residual
            self._planes = {}

    @staticmethod
    def _fit_pose(src: np.ndarray, dst: np.ndarray, k: np.ndarray) -> tuple | None:
        """solvePnP on the (undistorted) corners: the planar solution (IPPE), refined
        (Levenberg-Marquardt: 0.15 ms a fit; without it, three markers under a 50° tilt put
        cars up to 7 mm off instead of 5)."""
        world = np.column_stack([dst, np.zeros(len(dst))])
        ok, rvec, tvec = cv2.solvePnP(world, src, k, None, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(world, src, k, None, rvec, tvec)
        r = cv2.Rodrigues(rvec)[0]
        t = tvec.reshape(3)
        to_image = k @ np.column_stack([r[:, 0], r[:, 1], t])
        return np.linalg.inv(to_image), k, (r, t), k @ r[:, 2]

    def _lift_vector(self) -> np.ndarray | None:
        """K r3 (see `_lift`); without a calibration, estimated from the floor's homography
        the first time a plane above the floor is asked for."""
        if self._lift is None and not self._estimated and self.homography is not None:
            self._estimated = True
            self._estimate_pose()
        return self._lift

    def _estimate_pose(self) -> None:
        """The pose the floor's homography implies with an estimated focal length (principal
        point at the image centre); none when the floor is seen face-on."""
        if self.image_size is None:
            return
        w, h = self.image_size
        centre = ((w - 1) / 2, (h - 1) / 2)
        to_image = np.linalg.inv(self.homography)
        f = focal_from_homography(to_image, centre)
        if f is None:
            return
        k = np.array([[f, 0.0, centre[0]], [0.0, f, centre[1]], [0.0, 0.0, 1.0]])
        cols = np.linalg.inv(k) @ to_image
        scale = 2.0 / (np.linalg.norm(cols[:, 0]) + np.linalg.norm(cols[:, 1]))
        scale = scale if cols[2, 2] > 0 else -scale  # the arena in front of the camera
        cols = cols * scale
        r1, r2 = cols[:, 0], cols[:, 1]
        u, _, vt = np.linalg.svd(np.column_stack([r1, r2, np.cross(r1, r2)]))
        r = u @ vt
        self.camera_matrix, self.pose, self._lift = k, (r, cols[:, 2]), k @ r[:, 2] / scale
