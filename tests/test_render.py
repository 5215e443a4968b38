"""The virtual camera's renderer: its projection is the ground truth the vision tests rely on."""

import copy
import dataclasses
import math

import cv2
import numpy as np
import pytest

from udan.edge.geometry import CORNER_IDS, ArenaGeometry, square
from udan.hil.render import NOISE_ROWS, CameraModel, Renderer

GEOMETRY = ArenaGeometry()
CELLS = {"obstacle": [(2, 3)], "water": [(0, 4)], "wall": [(0, 3)], "target": [(6, 6)]}


def detect(image):
    """Full-resolution ArUco, corners refined with a 7x7 cornerSubPix: {id: [corners (4, 2)]}."""
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    corners, ids, _ = detector.detectMarkers(image)
    found = {}
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 0.001)
    for marker, quad in zip(ids.ravel().tolist(), corners, strict=True):
        pts = quad.reshape(-1, 1, 2).copy()
        cv2.cornerSubPix(image, pts, (3, 3), (-1, -1), criteria)
        found.setdefault(marker, []).append(pts.reshape(4, 2))
    return found


@pytest.fixture(scope="module")
def tilted():
    return Renderer(GEOMETRY, CameraModel(tilt_deg=18, yaw_deg=5, k1=-0.1, k2=0.02))


def test_markers_land_where_project_says(tilted):
    """Through tilt and lens distortion, every detected marker corner sits within half a pixel
    of the projected ground truth: the renderer and `project` agree."""
    cars = [(5, 0.7, 0.6, 0.4), (6, 2.1, 2.3, -2.0), (7, 1.4, 1.5, math.pi / 2)]
    found = detect(tilted.render(cars, CELLS))
    for marker, x, y, heading in cars:
        truth = tilted.project(square((x, y), GEOMETRY.car_marker_m, heading))
        assert np.abs(found[marker][0] - truth).max() < 0.5
    for marker, truth in zip(CORNER_IDS, GEOMETRY.corner_points(), strict=True):
        assert np.abs(found[marker][0] - tilted.project(truth)).max() < 0.5
    obstacle = square(GEOMETRY.cell_centre(2, 3), GEOMETRY.cell_marker_m, 0.0)
    assert np.abs(found[40][0] - tilted.project(obstacle)).max() < 0.5
    target = square(GEOMETRY.cell_centre(6, 6), GEOMETRY.cell_marker_m, 0.0)
    assert np.abs(found[43][0] - tilted.project(target)).max() < 0.5


def test_arena_fills_the_frame(tilted):
    """The outer corners of the calibration markers are inside the frame and span most of it."""
    outer = tilted.project(GEOMETRY.corner_points().reshape(-1, 2))
    w, h = tilted.camera.width, tilted.camera.height
    assert (outer >= 0).all() and (outer[:, 0] < w).all() and (outer[:, 1] < h).all()
    assert np.ptp(outer[:, 1]) > 0.8 * h


@pytest.mark.parametrize("tilt", [0, 30, 60])
def test_a_camera_with_a_fixed_lens_stands_back_when_tilted(tilt):
    """With the lens that frames the arena from 3 m overhead, a tilted camera stands farther
    back, just far enough that the arena still fits the frame as tightly."""
    lens = CameraModel().intrinsics(GEOMETRY)[0][0, 0]
    camera = CameraModel(tilt_deg=tilt, focal_px=lens)
    renderer = Renderer(GEOMETRY, camera)
    assert renderer.camera_matrix[0, 0] == lens
    standoff = camera.standoff(GEOMETRY)
    centre = np.array([GEOMETRY.width_m / 2, GEOMETRY.height_m / 2, 0.0])
    assert np.linalg.norm(camera.position(GEOMETRY) - centre) == pytest.approx(standoff)
    if tilt == 0:
        assert standoff == 3.0
    else:
        assert 3.1 < standoff < 3.5
    outer = renderer.project(GEOMETRY.corner_points().reshape(-1, 2))
    half = np.array([camera.width - 1, camera.height - 1]) / 2
    assert (np.abs(outer - half).max(0) / half).max() == pytest.approx(camera.fill, abs=0.005)


def test_frame_format_and_cars_leave_no_trace():
    """Grayscale uint8 H x W; a car drawn in one frame is gone from the next (the renderer
    restores its background), and without noise equal scenes render identically."""
    r = Renderer(GEOMETRY, CameraModel(blur_sigma=1.0))
    empty = r.render([], CELLS)
    assert empty.shape == (1200, 1920) and empty.dtype == np.uint8
    with_car = r.render([(9, 1.4, 1.4, 0.3)], CELLS)
    changed = np.argwhere(with_car != empty)
    assert len(changed) > 1000
    centre = r.project(np.array([1.4, 1.4]))
    assert np.abs(changed[:, ::-1] - centre).max() < 70  # only around the car
    assert np.array_equal(r.render([], CELLS), empty)


def test_layout_change_redraws_static_markers_and_the_target_moves():
    r = Renderer(GEOMETRY, CameraModel())
    assert 40 not in detect(r.render([], {}))
    assert len(detect(r.render([], {"obstacle": [(1, 1), (7, 7)]}))[40]) == 2
    assert 40 not in detect(r.render([], {}))
    for cell in [(3, 3), (3, 4)]:
        (quad,) = detect(r.render([], {"target": [cell]}))[43]
        centre = r.project(np.array(GEOMETRY.cell_centre(*cell)))
        assert np.abs(quad.mean(0) - centre).max() < 0.5


def test_noise_and_gain():
    """Noise of the configured sigma, different every frame, reproducible from the seed; the
    gain and exposure scale the scene."""
    model = CameraModel(noise_sigma=4.0, seed=3)
    a, b = Renderer(GEOMETRY, model), Renderer(GEOMETRY, model)
    f1, f2 = a.render([], {}), a.render([], {})
    diff = f1.astype(np.int16) - f2.astype(np.int16)
    assert 4.0 * math.sqrt(2) * 0.9 < diff.std() < 4.0 * math.sqrt(2) * 1.1
    assert np.array_equal(b.render([], {}), f1)
    dark = Renderer(GEOMETRY, CameraModel(exposure=0.5)).render([], {})
    bright = Renderer(GEOMETRY, CameraModel(gain=1.2)).render([], {})
    centre = (slice(550, 650), slice(900, 1000))
    plain = Renderer(GEOMETRY, CameraModel()).render([], {})[centre].mean()
    assert dark[centre].mean() == pytest.approx(plain * 0.5, abs=1)
    assert bright[centre].mean() == pytest.approx(plain * 1.2, abs=1)


def test_a_frame_drawn_into_the_slot_is_the_noisy_scene():
    """``render(out=)`` draws into the image given (the virtual camera's shared slot) the frame
    ``render()`` returns; the noise, added while the frame is laid down rather than after, is the
    noise-free scene's plus the noise field, saturating, cars and overlapping windows included."""
    cars = [(5, 1.0, 1.1, 0.4), (6, 1.06, 1.18, 1.0), (7, 2.2, 0.4, 2.0)]
    model = CameraModel(noise_sigma=3.0, blur_sigma=0.8, seed=5)
    a, b = Renderer(GEOMETRY, model), Renderer(GEOMETRY, model)
    clean = Renderer(GEOMETRY, dataclasses.replace(model, noise_sigma=0.0)).render(cars, CELLS)
    offset = int(copy.deepcopy(a._rng).integers(0, NOISE_ROWS + 1))
    above, below = a._noise[:, offset : offset + model.height]
    expected = cv2.subtract(cv2.add(clean, above), below)
    assert np.array_equal(a.render(cars, CELLS), expected)
    out = np.zeros((model.height, model.width), np.uint8)
    assert b.render(cars, CELLS, out=out) is out
    assert np.array_equal(out, expected)


@pytest.mark.parametrize(
    "camera",
    [
        CameraModel(tilt_deg=45, roll_deg=8, k1=0.15),
        CameraModel(tilt_deg=60, yaw_deg=-20, k1=-0.2, k2=0.03),
        CameraModel(roll_deg=-25, k1=0.08),
    ],
    ids=["tilt45-roll", "tilt60-barrel", "roll-only"],
)
def test_raised_and_rescaled_markers_land_where_project_says(camera):
    """Car markers printed at another size and lifted to their car's top are drawn where the
    projection of their own plane puts them, through tilt, roll and distortion (within 0.75
    pixel: the detector refines markers foreshortened to half their width less exactly)."""
    printed = dataclasses.replace(GEOMETRY, car_marker_m=0.18)
    heights = {5: 0.0, 6: 0.08, 7: 0.15}
    renderer = Renderer(printed, camera, marker_heights=heights)
    cars = [(5, 0.8, 1.9, 0.4), (6, 2.0, 0.9, -1.2), (7, 1.3, 1.4, 2.5)]
    found = detect(renderer.render(cars, {}))
    for marker, x, y, heading in cars:
        truth = renderer.project(square((x, y), printed.car_marker_m, heading), heights[marker])
        assert np.abs(found[marker][0] - truth).max() < 0.75, marker


def test_a_raised_marker_moves_away_from_the_camera_foot():
    """Lifting a marker off the floor shifts its image outward from the point below the camera,
    by the ratio of the heights (the parallax the vision must undo)."""
    camera = CameraModel(tilt_deg=30)
    renderer = Renderer(GEOMETRY, camera)
    foot = camera.position(GEOMETRY)
    xy = np.array([0.5, 2.4])
    lifted = renderer.project(xy, 0.15)
    height = -foot[2]
    seen_on_floor = foot[:2] + (xy - foot[:2]) * height / (height - 0.15)
    assert np.abs(lifted - renderer.project(seen_on_floor)).max() < 1e-6
    assert math.dist(lifted, renderer.project(xy)) > 10


def test_roll_turns_the_image_about_its_centre():
    straight = Renderer(GEOMETRY, CameraModel(tilt_deg=20))
    rolled = Renderer(GEOMETRY, CameraModel(tilt_deg=20, roll_deg=30))
    centre = (np.array([1920, 1200]) - 1) / 2
    xy = GEOMETRY.corner_centres()
    a = straight.project(xy) - centre
    b = rolled.project(xy) - centre
    turn = np.degrees(np.arctan2(b[:, 1], b[:, 0]) - np.arctan2(a[:, 1], a[:, 0]))
    assert np.allclose((turn + 180) % 360 - 180, 30, atol=1e-6)
