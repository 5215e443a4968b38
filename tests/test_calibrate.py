"""udan-calibrate: a printable board, a camera calibration from rendered views of it, and the
arena check; every bad input one line and exit status 2."""

from __future__ import annotations

import math
import re

import cv2
import numpy as np
import pytest

from udan.edge.calibrate import BoardSpec, main
from udan.edge.calibration import CameraCalibration, load_calibration, save_calibration
from udan.edge.geometry import ArenaGeometry
from udan.hil.render import CameraModel, Renderer, render_plane

SIZE = (1280, 800)
TEXELS_PER_MM = 8


def views_of_the_board(folder, camera_matrix, dist, count=20, seed=0):
    """`count` images of the default board held at different places, distances and angles in
    front of the camera, with sensor noise and a little blur."""
    spec = BoardSpec()
    texture = spec.image(TEXELS_PER_MM)
    centre = np.array([spec.squares[0] * spec.square_mm, spec.squares[1] * spec.square_mm, 0])
    centre = centre / 2000
    rng = np.random.default_rng(seed)
    inverse = np.linalg.inv(camera_matrix)
    spots = [(u, v) for u in np.linspace(0.25, 0.75, 5) for v in np.linspace(0.3, 0.7, 4)]
    folder.mkdir(exist_ok=True)
    for i in range(count):
        u, v = spots[i % len(spots)]
        rvec = rng.uniform(-0.5, 0.5, 3) * np.array([1, 1, 0.4])
        rotation = cv2.Rodrigues(rvec)[0]
        depth = rng.uniform(0.4, 0.55)
        ray = inverse @ np.array([u * SIZE[0], v * SIZE[1], 1.0])
        tvec = depth * ray - rotation @ centre
        image = render_plane(
            texture, 0.001 / TEXELS_PER_MM, (rvec, tvec), camera_matrix, dist, SIZE, 120
        )
        image = cv2.GaussianBlur(image, (0, 0), 0.6)
        noisy = image + rng.normal(0, 2, image.shape)
        cv2.imwrite(str(folder / f"view{i:02d}.png"), np.clip(noisy, 0, 255).astype(np.uint8))


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_the_board_prints_at_its_true_size_and_reads_back(tmp_path, capsys):
    code, out, _ = run(capsys, "board", "--out", tmp_path / "board.pdf")
    assert code == 0 and "squares 30 mm" in out
    pdf = (tmp_path / "board.pdf").read_bytes()
    assert pdf.startswith(b"%PDF-1.4") and pdf.rstrip().endswith(b"%%EOF")
    # the page holds the board at 210 x 150 mm (in points) plus margins
    media = re.search(rb"/MediaBox \[0 0 ([\d.]+) ([\d.]+)\]", pdf)
    assert float(media[1]) == pytest.approx((210 + 30) * 72 / 25.4, abs=0.01)
    drawn = re.search(rb"q ([\d.]+) 0 0 ([\d.]+) [\d.]+ [\d.]+ cm /Board Do", pdf)
    assert float(drawn[1]) == pytest.approx(210 * 72 / 25.4, abs=0.01)
    start = int(re.search(rb"startxref\n(\d+)", pdf)[1])
    assert pdf[start:].startswith(b"xref")
    code, _, _ = run(capsys, "board", "--out", tmp_path / "board.png")
    image = cv2.imread(str(tmp_path / "board.png"), cv2.IMREAD_GRAYSCALE)
    padded = cv2.copyMakeBorder(image, 40, 40, 40, 40, cv2.BORDER_CONSTANT, value=255)
    _, ids, _, _ = cv2.aruco.CharucoDetector(BoardSpec().board()).detectBoard(padded)
    assert code == 0 and len(ids) == 6 * 4  # every inner corner of a 7x5 board


@pytest.mark.parametrize("k1", [-0.15, pytest.param(0.1, marks=pytest.mark.slow)])
def test_camera_calibration_recovers_the_lens_from_20_views(k1, tmp_path, capsys):
    focal = 1000.0
    k = np.array([[focal, 0, 639.5], [0, focal, 399.5], [0, 0, 1]])
    views_of_the_board(tmp_path / "views", k, np.array([k1, 0, 0, 0, 0]), seed=round(abs(k1) * 100))
    out_file = tmp_path / "cam.yaml"
    code, out, err = run(capsys, "camera", "--images", tmp_path / "views", "--out", out_file)
    assert code == 0, err
    assert "20 views, 1280x800" in out and "RMS reprojection error" in out
    assert "frame coverage" in err  # the progress display
    fs = cv2.FileStorage(str(out_file), cv2.FILE_STORAGE_READ)
    matrix = fs.getNode("camera_matrix").mat()
    dist = fs.getNode("distortion_coefficients").mat().ravel()
    size = (int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real()))
    fs.release()
    assert size == SIZE
    assert abs(dist[0] - k1) < 0.01
    assert matrix[0, 0] == pytest.approx(focal, rel=0.01)
    assert matrix[1, 1] == pytest.approx(focal, rel=0.01)
    assert load_calibration(out_file).image_size == SIZE  # udan-edge --calibration reads it
    rms = float(re.search(r"RMS reprojection error ([\d.]+) px", out)[1])
    assert rms < 0.5


def arena_frames(folder, camera, count=30, corners_covered=()):
    """`count` frames of the arena with five cars, some calibration markers covered."""
    geometry = ArenaGeometry()
    renderer = Renderer(geometry, camera)
    cars = [(5 + i, 0.5 + 0.45 * i, 0.4 + 0.5 * i, 0.3 * i) for i in range(5)]
    folder.mkdir(exist_ok=True)
    image = renderer.render(cars, {"obstacle": [(4, 4)]})
    for marker in corners_covered:
        quad = geometry.corner_points()[marker]
        centre = quad.mean(0)
        paper = renderer.project(centre + (quad - centre) * 1.4)
        cv2.fillConvexPoly(image, np.round(paper).astype(np.int32), 172)
    for i in range(count):
        cv2.imwrite(str(folder / f"frame{i:03d}.png"), image)
    return renderer


def test_check_reports_the_pose_the_markers_and_every_cells_budget(tmp_path, capsys):
    renderer = arena_frames(tmp_path / "frames", CameraModel(tilt_deg=30, k1=-0.1, noise_sigma=2))
    cal = tmp_path / "cam.yaml"
    save_calibration(
        cal, CameraCalibration(renderer.camera_matrix, renderer.dist_coeffs, (1920, 1200))
    )
    picture = tmp_path / "arena.png"
    code, out, err = run(
        capsys, "check", "--camera", tmp_path / "frames", "--calibration", cal, "--frames", 30,
        "--out", picture,
    )  # fmt: skip
    assert code == 0, err
    tilt = float(re.search(r"tilted ([\d.]+)°", out)[1])
    height = float(re.search(r"camera: ([\d.]+) m above the floor", out)[1])
    assert tilt == pytest.approx(30, abs=0.5)
    assert height == pytest.approx(-renderer.camera.position(ArenaGeometry())[2], rel=0.01)
    errors = [float(e) for e in re.findall(r"reprojection error ([\d.]+) px RMS", out)]
    assert len(errors) == 4 and max(errors) < 0.5
    rows = [line.split() for line in out.splitlines() if re.fullmatch(r"\s+(\d+\s+){8}\d+", line)]
    assert len(rows) == 9 and all(0 < int(b) < 40 for row in rows for b in row)
    assert cv2.imread(str(picture)).shape == (1200, 1920, 3)


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    """A missing folder, a folder where the board never shows, a calibration for another image
    size, an arena whose calibration markers are mostly covered, a wrong board."""
    renderer = arena_frames(tmp_path / "arena", CameraModel(), count=14, corners_covered=(0, 2))
    other = tmp_path / "other.yaml"
    save_calibration(
        other, CameraCalibration(renderer.camera_matrix, renderer.dist_coeffs, (1280, 720))
    )
    cases = [
        (("camera", "--images", tmp_path / "nope", "--out", tmp_path / "c.yaml"), "no such folder"),
        (
            ("camera", "--images", tmp_path / "arena", "--out", tmp_path / "c.yaml"),
            "was not found in any of 14 images",
        ),
        (
            ("check", "--camera", tmp_path / "arena", "--calibration", other),
            "1280x720 frames, the camera gives 1920x1200",
        ),
        (
            ("check", "--camera", tmp_path / "arena", "--frames", 14),
            "calibration markers found: 1, 3",
        ),
        (("board", "--out", tmp_path / "b.pdf", "--dictionary", "DICT_NOPE"), "not an OpenCV"),
        (("board", "--out", tmp_path / "b.pdf", "--marker-mm", 40), "below --square-mm"),
        (("check", "--camera", tmp_path / "nope"), "no camera, video file or image folder"),
    ]
    for argv, says in cases:
        code, out, err = run(capsys, *argv)
        assert code == 2, (argv, out, err)
        message = err.strip().splitlines()[-1]
        assert says in message and message.startswith("udan-calibrate: "), (argv, err)
        assert "Traceback" not in err
    assert math.isfinite(renderer.camera_matrix[0, 0])
