"""The virtual camera's renderer: the arena as an overhead camera would see it.

It has to hold 40 FPS in one process next to the simulated world, so nothing full-frame is
computed per frame except one copy and the noise. Every image pixel's arena coordinates (through
the pinhole, the tilt and the lens distortion) are computed once; the static scene (floor, grid,
calibration and cell markers) is rendered once per layout through those coordinates; per frame,
only the car sprites are resampled into their own small windows, blurred there, and a
pre-drawn noise field is added. Sprites are resampled from textures whose marker edges fall on
texel boundaries, so the marker corners land where `project` says they do: tests use it as the
ground truth.

The surround target moves, so it is drawn per frame like a car, not into the static scene (a
rebuild costs several frames' time).

The lens uses OpenCV's distortion model (k1, k2), so an OpenCV calibration file holding
`Renderer.camera_matrix` and `dist_coeffs` describes this camera to the edge's vision. The camera
may be tilted (up to 60 degrees and more), turned and rolled; car markers may be printed at
another size than the vision is told (a different `ArenaGeometry`) and sit above the floor on
top of their car (`marker_heights`), as in a real lab.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from udan.edge.geometry import CELL_KIND_IDS, CORNER_IDS, ArenaGeometry, square

FLOOR = 172.0
GRID_LINE = 158.0
OUTSIDE = 105.0
PAPER = 238.0
INK = 22.0
CAR_BODY = 62.0
CAR_BODY_M = 0.22
"""Side of a car's body; its marker sits on a white label with a one-module margin."""
PX_PER_MODULE = 8
"""Texels per marker module: marker edges fall on texel boundaries."""
GRID_LINE_M = 0.004
MAP_STEP = 4
"""The per-pixel arena coordinates are solved exactly on this pixel grid, interpolated between."""
NOISE_ROWS = 64
"""Extra rows of the pre-drawn noise field; each frame uses a random window of it."""
_UNDISTORT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)


@dataclass(frozen=True)
class CameraModel:
    """An overhead camera: pose above the arena, lens, sensor. Angles in degrees."""

    width: int = 1920
    height: int = 1200
    distance_m: float = 3.0
    """From the camera to the arena's centre, along the optical axis (at least: see
    `focal_px`)."""
    tilt_deg: float = 0.0
    """Optical axis away from vertical: the camera moves towards row 0 (-y) and still looks at
    the arena centre, so row 0 looks bigger."""
    yaw_deg: float = 0.0
    """Rotation of the camera about the vertical."""
    roll_deg: float = 0.0
    """Rotation of the camera about its own optical axis (a camera mounted askew)."""
    fill: float = 0.94
    """Fraction of the frame (in its tighter direction) the arena plus corner markers fill."""
    focal_px: float | None = None
    """A lens of this focal length (pixels). The camera then stands back along its axis from
    `distance_m` until the arena fits within `fill` of the frame (a lab that tilts its camera
    moves it back). None: the lens that makes the arena fill `fill` from `distance_m`."""
    k1: float = 0.0
    k2: float = 0.0
    noise_sigma: float = 0.0
    """Gaussian sensor noise, grey levels (scaled by the gain)."""
    blur_sigma: float = 0.0
    """Gaussian blur (defocus, motion), pixels."""
    exposure: float = 1.0
    gain: float = 1.0
    seed: int = 0

    def rotation(self) -> np.ndarray:
        """World -> camera rotation. World: x along columns, y along rows, z into the floor."""
        t, y = math.radians(self.tilt_deg), math.radians(self.yaw_deg)
        rx = np.array([[1, 0, 0], [0, math.cos(t), -math.sin(t)], [0, math.sin(t), math.cos(t)]])
        return _about_z(math.radians(self.roll_deg)) @ rx @ _about_z(y)

    def standoff(self, geometry: ArenaGeometry) -> float:
        """Metres from the camera to the arena's centre along the optical axis: `distance_m`,
        or with a given lens (`focal_px`) the least distance from there at which the arena
        fits within `fill` of the frame."""
        if self.focal_px is None or self._fill_focal(geometry, self.distance_m) >= self.focal_px:
            return self.distance_m
        near, far = self.distance_m, 2 * self.distance_m
        while self._fill_focal(geometry, far) < self.focal_px:
            near, far = far, 2 * far
        for _ in range(40):
            mid = (near + far) / 2
            near, far = (
                (mid, far) if self._fill_focal(geometry, mid) < self.focal_px else (near, mid)
            )
        return far

    def position(self, geometry: ArenaGeometry) -> np.ndarray:
        """Where the camera is (world metres): `standoff` back along its optical axis from
        the arena's centre."""
        return self._position(geometry, self.standoff(geometry))

    def _position(self, geometry: ArenaGeometry, distance: float) -> np.ndarray:
        centre = np.array([geometry.width_m / 2, geometry.height_m / 2, 0.0])
        return centre - self.rotation().T @ np.array([0.0, 0.0, distance])

    def distortion(self) -> np.ndarray:
        """OpenCV distortion coefficients (k1, k2, p1, p2, k3)."""
        return np.array([self.k1, self.k2, 0.0, 0.0, 0.0])

    def intrinsics(self, geometry: ArenaGeometry) -> tuple[np.ndarray, np.ndarray]:
        """Camera matrix and distortion coefficients, as a calibration file would hold them: the
        lens `focal_px`, or the one with which the arena and its corner markers fill `fill` of
        the frame."""
        f = self.focal_px or self._fill_focal(geometry, self.distance_m)
        k = np.array([[f, 0, (self.width - 1) / 2], [0, f, (self.height - 1) / 2], [0, 0, 1]])
        return k, self.distortion()

    def _fill_focal(self, geometry: ArenaGeometry, distance: float) -> float:
        """The focal length (pixels) with which the arena and its corner markers fill `fill` of
        the frame seen from `distance`."""
        r = self.rotation()
        cam = self._position(geometry, distance)
        out = geometry.corner_gap_m + geometry.corner_marker_m
        lo, hi_x, hi_y = -out, geometry.width_m + out, geometry.height_m + out
        s = np.linspace(0.0, 1.0, 64)
        edges = np.concatenate(
            [
                np.stack([lo + s * (hi_x - lo), np.full_like(s, lo)], 1),
                np.stack([lo + s * (hi_x - lo), np.full_like(s, hi_y)], 1),
                np.stack([np.full_like(s, lo), lo + s * (hi_y - lo)], 1),
                np.stack([np.full_like(s, hi_x), lo + s * (hi_y - lo)], 1),
            ]
        )
        world = np.column_stack([edges, np.zeros(len(edges))])
        p = (world - cam) @ r.T
        x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
        r2 = x * x + y * y
        d = 1 + self.k1 * r2 + self.k2 * r2 * r2
        x, y = x * d, y * d
        return self.fill * min(self.width / 2 / np.abs(x).max(), self.height / 2 / np.abs(y).max())


def _about_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def marker_texture(
    dictionary: cv2.aruco.Dictionary, marker: int, margin_modules: int = 1
) -> tuple[np.ndarray, int]:
    """A marker on white paper with a quiet zone of `margin_modules`, PX_PER_MODULE texels per
    module; returns (texture, texels across the marker)."""
    bits = dictionary.markerSize + 2
    side = bits * PX_PER_MODULE
    img = cv2.aruco.generateImageMarker(dictionary, marker, side, borderBits=1)
    tex = np.where(img > 127, PAPER, INK).astype(np.float32)
    pad = margin_modules * PX_PER_MODULE
    return cv2.copyMakeBorder(tex, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=PAPER), side


_ARENA = ArenaGeometry()
_CAMERA = CameraModel()


class _Sprite:
    """A square texture lying flat on the floor, `metres_per_texel` per texel."""

    def __init__(self, texture: np.ndarray, metres_per_texel: float, scale: float) -> None:
        self.texture = np.clip(np.rint(texture * scale), 0, 255).astype(np.uint8)
        self.m = metres_per_texel
        self.side_m = texture.shape[0] * metres_per_texel


class Renderer:
    """Renders the arena seen by `camera`: static scene once per layout, cars per frame.

    `geometry` is the arena as printed, which may differ from what the vision is told (a lab
    printing its car markers at another size); `marker_heights` lifts car markers (by marker id,
    metres above the floor: a marker on top of a real car) together with their car's body."""

    def __init__(
        self,
        geometry: ArenaGeometry = _ARENA,
        camera: CameraModel = _CAMERA,
        marker_heights: Mapping[int, float] | None = None,
    ) -> None:
        self.geometry = geometry
        self.camera = camera
        self.marker_heights = dict(marker_heights or {})
        self.camera_matrix, self.dist_coeffs = camera.intrinsics(geometry)
        r = camera.rotation()
        self._cam_centre = camera.position(geometry)
        self._r = r
        self.rvec = cv2.Rodrigues(r)[0]
        self.tvec = -r @ self._cam_centre
        self._dictionary = cv2.aruco.getPredefinedDictionary(
            getattr(cv2.aruco, geometry.dictionary)
        )
        self._scale = camera.exposure * camera.gain
        self._ax, self._ay = self._arena_maps()
        self._floor = self._draw_floor()
        self._sprites: dict[tuple[str, int], _Sprite] = {}
        self._layout: frozenset | None = None
        self._static = self._floor
        self._sharp = self._floor.copy()
        self._background = self._floor
        self._rng = np.random.default_rng(camera.seed)
        self._noise = self._draw_noise()

    # -- geometry -------------------------------------------------------------------------
    def project(self, xy: np.ndarray, height: float = 0.0) -> np.ndarray:
        """Image pixel coordinates (..., 2) of arena points ``xy`` (..., 2) ``height`` metres
        above the floor."""
        xy = np.asarray(xy, dtype=np.float64)
        flat = xy.reshape(-1, 2)
        world = np.column_stack([flat, np.full(len(flat), -height)])
        img, _ = cv2.projectPoints(
            world, self.rvec, self.tvec, self.camera_matrix, self.dist_coeffs
        )
        return img.reshape(xy.shape)

    def _arena_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """Arena (x, y) of every pixel centre: solved on a coarse grid (undistort, then the ray
        meets the floor), bilinearly interpolated in between: both maps are smooth."""
        w, h = self.camera.width, self.camera.height
        gu = np.arange(0, w + MAP_STEP, MAP_STEP, dtype=np.float64)
        gv = np.arange(0, h + MAP_STEP, MAP_STEP, dtype=np.float64)
        uu, vv = np.meshgrid(gu, gv)
        pix = np.stack([uu, vv], -1).reshape(-1, 1, 2)
        norm = cv2.undistortPoints(
            pix, self.camera_matrix, self.dist_coeffs, criteria=_UNDISTORT
        ).reshape(-1, 2)
        rays = np.column_stack([norm, np.ones(len(norm))]) @ self._r  # = R^T @ ray, per row
        t = -self._cam_centre[2] / rays[:, 2]
        ground = self._cam_centre[:2] + rays[:, :2] * t[:, None]
        coarse = ground.reshape(len(gv), len(gu), 2).astype(np.float32)
        mx = np.tile(np.arange(w, dtype=np.float32) / MAP_STEP, (h, 1))
        my = np.tile((np.arange(h, dtype=np.float32) / MAP_STEP)[:, None], (1, w))
        fine = cv2.remap(coarse, mx, my, cv2.INTER_LINEAR)
        return np.ascontiguousarray(fine[..., 0]), np.ascontiguousarray(fine[..., 1])

    # -- scene ----------------------------------------------------------------------------
    def _draw_floor(self) -> np.ndarray:
        """Floor, faint grid lines, darker surroundings (before any marker)."""
        g = self.geometry
        ax, ay = self._ax, self._ay
        out = g.corner_gap_m + g.corner_marker_m + 0.05
        on_floor = (ax > -out) & (ax < g.width_m + out) & (ay > -out) & (ay < g.height_m + out)
        img = np.where(on_floor, FLOOR, OUTSIDE).astype(np.float32)
        in_grid = (ax >= 0) & (ax <= g.width_m) & (ay >= 0) & (ay <= g.height_m)
        dx = np.abs(ax / g.cell_m - np.round(ax / g.cell_m)) * g.cell_m
        dy = np.abs(ay / g.cell_m - np.round(ay / g.cell_m)) * g.cell_m
        line = in_grid & (np.minimum(dx, dy) < GRID_LINE_M / 2)
        img[line] = GRID_LINE
        return np.clip(np.rint(img * self._scale), 0, 255).astype(np.uint8)

    def _draw_noise(self) -> np.ndarray:
        """Two uint8 fields (positive and negative part) of a taller Gaussian noise image, so a
        frame adds noise with two saturating uint8 operations on a random row window."""
        sigma = self.camera.noise_sigma * self.camera.gain
        if sigma <= 0:
            return np.zeros((0,), np.uint8)
        shape = (self.camera.height + NOISE_ROWS, self.camera.width)
        n = np.rint(self._rng.normal(0.0, sigma, shape).astype(np.float32))
        return np.stack([np.clip(n, 0, 255), np.clip(-n, 0, 255)]).astype(np.uint8)

    def _sprite(self, kind: str, marker: int) -> _Sprite:
        key = (kind, marker)
        sprite = self._sprites.get(key)
        if sprite is None:
            g = self.geometry
            tex, side = marker_texture(self._dictionary, marker)
            marker_m = {"car": g.car_marker_m, "corner": g.corner_marker_m}.get(
                kind, g.cell_marker_m
            )
            m = marker_m / side
            if kind == "car":
                body = round(CAR_BODY_M / m)
                pad = max(0, (body - tex.shape[0]) // 2)
                tex = cv2.copyMakeBorder(
                    tex, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=CAR_BODY
                )
            sprite = self._sprites[key] = _Sprite(tex, m, self._scale)
        return sprite

    def _paste(
        self,
        canvas: np.ndarray,
        sprite: _Sprite,
        x: float,
        y: float,
        heading: float,
        height: float = 0.0,
    ) -> tuple[int, int, int, int] | None:
        """Resample `sprite` centred on arena (x, y) facing `heading`, `height` metres above the
        floor, into `canvas`; returns the touched window (x0, y0, x1, y1) or None when it is
        off the image."""
        corners = self.project(square((x, y), sprite.side_m, heading), height)
        x0, y0 = np.floor(corners.min(0)).astype(int) - 1
        x1, y1 = np.ceil(corners.max(0)).astype(int) + 2
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, self.camera.width), min(y1, self.camera.height)
        if x1 <= x0 or y1 <= y0:
            return None
        # a pixel's ray meets the plane at `height` closer to the camera's foot than the floor,
        # by the factor (camera height - height) / camera height
        lift = np.float32(1 + height / self._cam_centre[2])
        foot_x, foot_y = np.float32(self._cam_centre[0]), np.float32(self._cam_centre[1])
        dx = foot_x + (self._ax[y0:y1, x0:x1] - foot_x) * lift - np.float32(x)
        dy = foot_y + (self._ay[y0:y1, x0:x1] - foot_y) * lift - np.float32(y)
        c, s = np.float32(math.cos(heading) / sprite.m), np.float32(math.sin(heading) / sprite.m)
        half = np.float32(sprite.texture.shape[0] / 2 - 0.5)
        u = c * dx + s * dy + half
        v = c * dy - s * dx + half
        window = canvas[y0:y1, x0:x1].copy()
        cv2.remap(
            sprite.texture, u, v, cv2.INTER_LINEAR, dst=window, borderMode=cv2.BORDER_TRANSPARENT
        )
        canvas[y0:y1, x0:x1] = window
        return x0, y0, x1, y1

    def _build_background(self, cells: Mapping[str, Iterable[tuple[int, int]]]) -> None:
        """Static scene: floor, corner markers, one marker per static cell; sharp and blurred."""
        g = self.geometry
        sharp = self._floor.copy()
        for marker, (cx, cy) in zip(CORNER_IDS, g.corner_centres(), strict=True):
            self._paste(sharp, self._sprite("corner", marker), cx, cy, 0.0)
        for kind, where in cells.items():
            sprite = self._sprite("cell", CELL_KIND_IDS[kind])
            for row, col in where:
                self._paste(sharp, sprite, *g.cell_centre(row, col), 0.0)
        self._static = sharp
        self._sharp = sharp.copy()
        self._background = self._blur(sharp)

    def _blur(self, img: np.ndarray) -> np.ndarray:
        sigma = self.camera.blur_sigma
        return cv2.GaussianBlur(img, (0, 0), sigma) if sigma > 0 else img

    def render(
        self,
        cars: Sequence[tuple[int, float, float, float]],
        cells: Mapping[str, Iterable[tuple[int, int]]],
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """One grayscale frame (uint8, H x W): `cars` as (marker, x, y, heading) in arena metres
        and radians, `cells` the cells per kind ("obstacle", "wall", "water", "target"); drawn
        into `out` when given (the virtual camera's shared slot), else into a new image."""
        layout = frozenset(
            (kind, frozenset(map(tuple, where)))
            for kind, where in cells.items()
            if kind != "target" and where
        )
        if layout != self._layout:
            self._build_background(dict(layout))
            self._layout = layout
        lifted = self.marker_heights
        sprites = [(self._sprite("car", m), x, y, h, lifted.get(m, 0.0)) for m, x, y, h in cars]
        target = self._sprite("cell", CELL_KIND_IDS["target"])
        sprites += [
            (target, *self.geometry.cell_centre(*c), 0.0, 0.0) for c in cells.get("target", ())
        ]
        h = self.camera.height
        frame = np.empty((h, self.camera.width), np.uint8) if out is None else out
        # the noise is added as the background is laid down, and to each sprite's window as it
        # goes in: one pass over the frame fewer than laying down, then adding
        if self._noise.size:
            off = int(self._rng.integers(0, NOISE_ROWS + 1))
            above, below = self._noise[0, off : off + h], self._noise[1, off : off + h]
            cv2.add(self._background, above, dst=frame)
        else:
            above = below = None
            np.copyto(frame, self._background)
        pad = math.ceil(3 * self.camera.blur_sigma)
        windows = []
        for sprite, x, y, heading, height in sorted(sprites, key=lambda s: s[4]):
            win = self._paste(self._sharp, sprite, x, y, heading, height)
            if win is not None:
                windows.append(win)
        for x0, y0, x1, y1 in windows:
            a0, b0 = max(x0 - pad, 0), max(y0 - pad, 0)
            a1, b1 = min(x1 + pad, self.camera.width), min(y1 + pad, self.camera.height)
            patch = self._blur(self._sharp[b0:b1, a0:a1])[y0 - b0 : y1 - b0, x0 - a0 : x1 - a0]
            if above is not None:
                patch = cv2.add(patch, above[y0:y1, x0:x1])
            frame[y0:y1, x0:x1] = patch
        for x0, y0, x1, y1 in windows:
            self._sharp[y0:y1, x0:x1] = self._static[y0:y1, x0:x1]
        if below is not None:
            cv2.subtract(frame, below, dst=frame)
        return frame


def render_plane(
    texture: np.ndarray,
    metres_per_texel: float,
    pose: tuple[np.ndarray, np.ndarray],
    camera_matrix: np.ndarray,
    dist_coeffs: np.ndarray,
    size: tuple[int, int],
    background: float = OUTSIDE,
) -> np.ndarray:
    """A flat printed sheet (a calibration board: `texture`, texel (0, 0) at its origin, x and
    y along its columns and rows) seen by a camera with lens distortion, `pose` = (rvec, tvec)
    sheet -> camera, as a grayscale (uint8) image of `size` (width, height): the views a lab
    takes to calibrate its camera."""
    w, h = size
    gu = np.arange(0, w + MAP_STEP, MAP_STEP, dtype=np.float64)
    gv = np.arange(0, h + MAP_STEP, MAP_STEP, dtype=np.float64)
    uu, vv = np.meshgrid(gu, gv)
    pix = np.stack([uu, vv], -1).reshape(-1, 1, 2)
    norm = cv2.undistortPoints(pix, camera_matrix, dist_coeffs, criteria=_UNDISTORT).reshape(-1, 2)
    r = cv2.Rodrigues(np.asarray(pose[0], dtype=np.float64))[0]
    t = np.asarray(pose[1], dtype=np.float64).reshape(3)
    rays = np.column_stack([norm, np.ones(len(norm))]) @ r  # sheet coordinates, per row
    origin = -r.T @ t  # the camera in sheet coordinates
    along = -origin[2] / rays[:, 2]
    hits = origin[:2] + rays[:, :2] * along[:, None]
    hits[along <= 0] = -1e6  # behind the camera: off the sheet
    coarse = (hits / metres_per_texel - 0.5).reshape(len(gv), len(gu), 2).astype(np.float32)
    mx = np.tile(np.arange(w, dtype=np.float32) / MAP_STEP, (h, 1))
    my = np.tile((np.arange(h, dtype=np.float32) / MAP_STEP)[:, None], (1, w))
    fine = cv2.remap(coarse, mx, my, cv2.INTER_LINEAR)
    return cv2.remap(
        texture,
        fine[..., 0],
        fine[..., 1],
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=background,
    )


def circling_cars(renderer: Renderer, frames: int, cars: int = 5) -> list[np.ndarray]:
    """``frames`` frames of ``cars`` cars (markers 5, 6, ...), each going round a circle a cell
    across once over the frames, in a fixed layout: frames drawn once and replayed in a loop
    (the benches' camera)."""
    geometry = renderer.geometry
    cells = {"obstacle": [(4, 4)], "wall": [(0, 1)], "water": [(0, 4)], "target": []}
    out = []
    for f in range(frames):
        angle = 2 * math.pi * f / frames
        placed = []
        for k in range(cars):
            cx, cy = geometry.cell_centre(2 + k, 1 + (3 * k) % 7)
            r = geometry.cell_m / 2
            placed.append((5 + k, cx + r * math.cos(angle), cy + r * math.sin(angle), angle + k))
        out.append(renderer.render(placed, cells))
    return out
