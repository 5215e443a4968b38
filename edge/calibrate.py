"""`udan-calibrate`: the camera calibration and the arena check a lab makes before real runs.

- ``udan-calibrate board --out board.pdf``: a printable ChArUco board, at its true size (a line
  under it says the square size, to check the print with a ruler).
- ``udan-calibrate probe --camera URL``: the mode a camera URL gets (``?width=...&fps=...``, the
  one place a mode is set, as for ``udan-edge --camera``) and the modes and controls the camera
  offers.
- ``udan-calibrate camera --images DIR | --camera URL --out cam.yaml``: OpenCV's ChArUco
  calibration from views of that board (a folder of images, or a camera in the mode its URL
  asks for, which it says on stderr: a calibration holds for that mode only),
  with the frame coverage as views come in and the RMS reprojection error at the end; writes the
  OpenCV FileStorage YAML that ``udan-edge --calibration`` reads.
- ``udan-calibrate check --camera URL [--calibration cam.yaml]``: the arena as the edge's vision
  sees it: the camera's pose, each calibration marker's reprojection error, the accuracy budget
  of every cell (how close to a border a car may be and still be placed with confidence), and
  a picture of the detected arena.

Every bad input (a missing folder, a board never seen, a calibration for another image size, an
arena whose calibration markers are missing) is one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import math
import sys
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from udan.edge.calibration import CameraCalibration, VisionError, save_calibration
from udan.edge.camera import CameraError, CameraSource, Frame, open_camera
from udan.edge.geometry import CORNER_IDS, ArenaGeometry
from udan.edge.vision import Vision

MIN_VIEWS = 4
"""Fewest views with the board found that a calibration is made from."""
COVERAGE_GRID = (8, 6)
"""The frame is divided into these many cells (across, down) to measure coverage."""
GOOD_COVERAGE = 0.6
"""Share of the coverage cells below which the calibration is said to be poorly constrained."""
MIN_CORNERS = 6
"""Fewest ChArUco corners a view must show to be used."""
PIXELS_PER_MM = 8
"""Resolution of the board image in the PDF (200 dpi)."""
MM_TO_PT = 72 / 25.4
PAGE_MARGIN_MM = 15


class CalibrateError(Exception):
    """Input the command cannot work with; the message is one line."""


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board: squares across and down, their sides in millimetres, its dictionary."""

    squares: tuple[int, int] = (7, 5)
    square_mm: float = 30.0
    marker_mm: float = 22.0
    dictionary: str = "DICT_5X5_100"

    def board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board, lengths in metres (the calibration's translations come out so)."""
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            self.squares, self.square_mm / 1000, self.marker_mm / 1000, dictionary
        )

    def image(self, pixels_per_mm: float = PIXELS_PER_MM) -> np.ndarray:
        """The board as a grayscale image, `pixels_per_mm` across."""
        w = round(self.squares[0] * self.square_mm * pixels_per_mm)
        h = round(self.squares[1] * self.square_mm * pixels_per_mm)
        return self.board().generateImage((w, h), marginSize=0, borderBits=1)


def _board_spec(args: argparse.Namespace) -> BoardSpec:
    try:
        across, down = (int(n) for n in args.squares.lower().split("x"))
    except ValueError:
        raise CalibrateError(f"--squares {args.squares}: give ACROSSxDOWN, e.g. 7x5") from None
    if min(across, down) < 3:
        raise CalibrateError(f"--squares {args.squares}: at least 3x3 squares")
    if not 0 < args.marker_mm < args.square_mm:
        raise CalibrateError(
            f"--marker-mm {args.marker_mm} must be above 0 and below --square-mm {args.square_mm}"
        )
    if not hasattr(cv2.aruco, args.dictionary) or not args.dictionary.startswith("DICT_"):
        raise CalibrateError(f"--dictionary {args.dictionary}: not an OpenCV ArUco dictionary")
    spec = BoardSpec((across, down), args.square_mm, args.marker_mm, args.dictionary)
    markers = spec.board().getIds().size
    if markers > spec.board().getDictionary().bytesList.shape[0]:
        raise CalibrateError(f"--dictionary {args.dictionary} has too few markers for the board")
    return spec


# -- board ------------------------------------------------------------------------------------
def pdf_with_image(image: np.ndarray, width_mm: float, height_mm: float, caption: str) -> bytes:
    """A one-page PDF showing the grayscale `image` at `width_mm` x `height_mm`, centred, with
    `caption` under it (written by hand: the edge has no PDF library)."""
    page_w = (width_mm + 2 * PAGE_MARGIN_MM) * MM_TO_PT
    page_h = (height_mm + 3 * PAGE_MARGIN_MM) * MM_TO_PT
    img_w, img_h = width_mm * MM_TO_PT, height_mm * MM_TO_PT
    x0, y0 = PAGE_MARGIN_MM * MM_TO_PT, 2 * PAGE_MARGIN_MM * MM_TO_PT
    text = caption.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)")
    content = (
        f"q {img_w:.3f} 0 0 {img_h:.3f} {x0:.3f} {y0:.3f} cm /Board Do Q\n"
        f"BT /Caption 10 Tf {x0:.3f} {PAGE_MARGIN_MM * MM_TO_PT:.3f} Td ({text}) Tj ET\n"
    ).encode("ascii")
    pixels = zlib.compress(np.ascontiguousarray(image, dtype=np.uint8).tobytes())
    objects = [
        b"<< /Type /Catalog /Pages 2 0 R >>",
        b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
        (
            f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {page_w:.3f} {page_h:.3f}] "
            "/Resources << /XObject << /Board 4 0 R >> /Font << /Caption 6 0 R >> >> "
            "/Contents 5 0 R >>"
        ).encode("ascii"),
        (
            f"<< /Type /XObject /Subtype /Image /Width {image.shape[1]} "
            f"/Height {image.shape[0]} /ColorSpace /DeviceGray /BitsPerComponent 8 "
            f"/Filter /FlateDecode /Length {len(pixels)} >>\nstream\n"
        ).encode("ascii")
        + pixels
        + b"\nendstream",
        f"<< /Length {len(content)} >>\nstream\n".encode("ascii") + content + b"endstream",
        b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica >>",
    ]
    out = bytearray(b"%PDF-1.4\n")
    offsets = []
    for number, body in enumerate(objects, 1):
        offsets.append(len(out))
        out += f"{number} 0 obj\n".encode("ascii") + body + b"\nendobj\n"
    xref = len(out)
    out += f"xref\n0 {len(objects) + 1}\n0000000000 65535 f \n".encode("ascii")
    out += b"".join(f"{o:010d} 00000 n \n".encode("ascii") for o in offsets)
    out += (
        f"trailer\n<< /Size {len(objects) + 1} /Root 1 0 R >>\nstartxref\n{xref}\n%%EOF\n"
    ).encode("ascii")
    return bytes(out)


def make_board(spec: BoardSpec, out: Path) -> str:
    """Write the board to `out` (.pdf at its true size, or an image); returns what was made."""
    image = spec.image()
    across, down = spec.squares
    caption = (
        f"ChArUco {across}x{down}, {spec.dictionary}: squares {spec.square_mm:g} mm, "
        f"markers {spec.marker_mm:g} mm. Print at 100 % and check a square with a ruler."
    )
    if out.suffix.lower() == ".pdf":
        out.write_bytes(
            pdf_with_image(image, across * spec.square_mm, down * spec.square_mm, caption)
        )
    elif not cv2.imwrite(str(out), image):
        raise CalibrateError(f"--out {out}: cannot write an image there (use .pdf or .png)")
    return caption


# -- camera -----------------------------------------------------------------------------------
@dataclass
class Views:
    """The board's corners in every view where it was found, and the frame coverage."""

    size: tuple[int, int] | None = None
    object_points: list[np.ndarray] = field(default_factory=list)
    image_points: list[np.ndarray] = field(default_factory=list)
    covered: np.ndarray | None = None

    def add(self, board: cv2.aruco.CharucoBoard, corners: np.ndarray, ids: np.ndarray) -> None:
        obj, img = board.matchImagePoints(corners, ids)
        self.object_points.append(obj.reshape(-1, 3))
        self.image_points.append(img.reshape(-1, 2))
        w, h = self.size
        nx, ny = COVERAGE_GRID
        cells = np.floor(img.reshape(-1, 2) / (w / nx, h / ny)).astype(int)
        cells = np.clip(cells, 0, (nx - 1, ny - 1))
        self.covered[cells[:, 1], cells[:, 0]] = True

    @property
    def count(self) -> int:
        return len(self.image_points)

    @property
    def coverage(self) -> float:
        return 0.0 if self.covered is None else float(self.covered.mean())


def collect_views(source: str, spec: BoardSpec, wanted: int, live: bool) -> Views:
    """Views of the board from the camera or image folder `source`: every image of a folder;
    from a live camera, up to `wanted` views, each with the board moved since the last one."""
    board = spec.board()
    detector = cv2.aruco.CharucoDetector(board)
    views = Views()
    seen = 0
    last: np.ndarray | None = None
    try:
        with open_camera(source) as camera:
            _say_mode(camera)
            for frame in camera:
                seen += 1
                image = _gray(frame)
                size = (image.shape[1], image.shape[0])
                if views.size is None:
                    views.size = size
                    views.covered = np.zeros(COVERAGE_GRID[::-1], bool)
                elif size != views.size:
                    raise CalibrateError(
                        f"{source}: frame {seen} is {size[0]}x{size[1]}, the first was "
                        f"{views.size[0]}x{views.size[1]} (one camera mode per calibration)"
                    )
                corners, ids, _, _ = detector.detectBoard(image)
                if ids is None or len(ids) < MIN_CORNERS:
                    print(f"view {seen}: board not found", file=sys.stderr)
                    continue
                centre = corners.reshape(-1, 2).mean(0)
                if live and last is not None and math.dist(centre, last) < 0.05 * size[0]:
                    continue  # a camera gives the same view many times over
                last = centre
                views.add(board, corners, ids)
                print(
                    f"view {seen}: {len(ids)} corners; {views.count} views, "
                    f"frame coverage {100 * views.coverage:.0f} %",
                    file=sys.stderr,
                )
                if live and views.count >= wanted:
                    break
    except CameraError as err:
        raise CalibrateError(str(err)) from None
    if views.count == 0:
        raise CalibrateError(
            f"the board ({spec.squares[0]}x{spec.squares[1]} {spec.dictionary}) was not found "
            f"in any of {seen} images from {source}"
        )
    if views.count < MIN_VIEWS:
        raise CalibrateError(
            f"the board was found in {views.count} of {seen} images from {source}; "
            f"a calibration needs {MIN_VIEWS} or more views"
        )
    return views


def _say_mode(camera: CameraSource) -> None:
    """The mode a camera runs in (a calibration holds for that mode only) and how it differs
    from the one its URL asked for, on stderr."""
    if camera.mode is not None:
        print(f"camera {camera.url}: {camera.mode.summary()}", file=sys.stderr)
    for warning in camera.warnings:
        print(f"camera {camera.url}: warning: {warning}", file=sys.stderr)


def probe_camera(url: str) -> list[str]:
    """``udan-calibrate probe``: the mode a camera URL gets, and the modes and controls the
    camera offers."""
    try:
        with open_camera(url) as camera:
            lines = [f"camera {camera.url}"]
            if camera.mode is not None:
                lines.append(f"  mode: {camera.mode.summary()}")
            if camera.options.given:
                asked = "&".join(
                    f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
                    for k, v in camera.options.given.items()
                )
                lines.append(f"  asked: {asked}")
            lines += [f"  warning: {w}" for w in camera.warnings]
            for name, value in camera.describe().items():
                if isinstance(value, str) and "\n" in value:
                    lines += [f"  {name}:", *(f"    {line}" for line in value.splitlines())]
                else:
                    lines.append(f"  {name}: {value}")
    except CameraError as err:
        raise CalibrateError(str(err)) from None
    return lines


def _gray(frame: Frame) -> np.ndarray:
    image = frame.image
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def calibrate(views: Views) -> tuple[CameraCalibration, float]:
    """OpenCV's calibration (k1, k2, p1, p2, k3) from the views; returns it and the RMS
    reprojection error in pixels."""
    rms, k, dist, _, _ = cv2.calibrateCamera(
        [p.astype(np.float32) for p in views.object_points],
        [p.astype(np.float32) for p in views.image_points],
        views.size,
        None,
        None,
    )
    return CameraCalibration(k, dist.reshape(-1), views.size), float(rms)


# -- check ------------------------------------------------------------------------------------
def check_arena(
    source: str, calibration: str | None, frames: int, picture: Path | None
) -> list[str]:
    """Run the edge's vision on `frames` frames of `source`; returns the report's lines."""
    geometry = ArenaGeometry()
    vision = Vision(geometry, calibration_file=calibration)
    last = None
    try:
        with open_camera(source) as camera:
            _say_mode(camera)
            for i, frame in enumerate(camera):
                last = frame
                vision.process(Frame(_gray(frame), frame.t_capture_ns, i))
                if i + 1 >= frames:
                    break
    except CameraError as err:
        raise CalibrateError(str(err)) from None
    if last is None:
        raise CalibrateError(f"{source}: no frame")
    fit = vision.fit
    if not vision.calibrated:
        found = ", ".join(map(str, sorted(fit.corners))) or "none"
        ids = ", ".join(map(str, CORNER_IDS))
        raise CalibrateError(
            f"calibration markers found: {found}; at least three of {ids} are needed "
            "(are they in view, uncovered, and printed from the arena's dictionary?)"
        )
    lines = []
    height = fit.camera_height()
    if height is not None:
        r, t = fit.pose
        foot = -(r.T @ t)
        axis = r[2]  # the optical axis in arena coordinates
        tilt = math.degrees(math.acos(min(1.0, abs(float(axis[2])))))
        lines.append(
            f"camera: {height:.3f} m above the floor, over arena ({foot[0]:.3f}, {foot[1]:.3f}) m, "
            f"tilted {tilt:.1f}° from vertical"
            + ("" if calibration else " (focal length estimated: no calibration given)")
        )
    lines.append(
        f"calibration markers: {len(fit.corners)} of {len(CORNER_IDS)} "
        f"(missing: {', '.join(str(m) for m in CORNER_IDS if m not in fit.corners) or 'none'})"
    )
    for marker, corners in sorted(fit.corners.items()):
        error = np.linalg.norm(
            fit.to_image(geometry.corner_points()[marker]) - fit.distort(corners), axis=1
        )
        lines.append(
            f"  marker {marker}: reprojection error {np.sqrt(np.mean(error**2)):.2f} px RMS, "
            f"{error.max():.2f} px max"
        )
    budgets = vision.budgets_at_cells()
    lines.append(
        f"lens misfit beyond corner noise: {1000 * fit.misfit_m:.1f} mm RMS"
        + (" (no calibration: a lens that distorts shows here)" if calibration is None else "")
    )
    lines.append(
        "accuracy budget per cell, mm (a car nearer a cell border than this is held, not guessed):"
    )
    lines += ["  " + " ".join(f"{1000 * b:4.0f}" for b in row) for row in budgets]
    usable = geometry.cell_m / 2 - budgets
    lines.append(
        f"worst cell: a car within {1000 * usable.min():.0f} mm of its cell centre is placed "
        f"with confidence (cell half-width {1000 * geometry.cell_m / 2:.0f} mm)"
    )
    if picture is not None:
        if not cv2.imwrite(str(picture), draw_arena(last.image, vision)):
            raise CalibrateError(f"--out {picture}: cannot write an image there")
        lines.append(f"picture of the detected arena: {picture}")
    return lines


def draw_arena(image: np.ndarray, vision: Vision) -> np.ndarray:
    """The frame with the grid as the vision's camera model puts it (green) and the calibration
    markers it fitted (red outlines)."""
    geometry = vision.geometry
    picture = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    steps = np.linspace(0.0, 1.0, 50)
    for i in range(geometry.cols + 1):
        x = i * geometry.cell_m
        line = np.stack([np.full_like(steps, x), steps * geometry.height_m], 1)
        _polyline(picture, vision.fit.to_image(line), (0, 200, 0))
    for j in range(geometry.rows + 1):
        y = j * geometry.cell_m
        line = np.stack([steps * geometry.width_m, np.full_like(steps, y)], 1)
        _polyline(picture, vision.fit.to_image(line), (0, 200, 0))
    for marker in vision.fit.corners:
        _polyline(picture, vision.fit.quads[marker], (0, 0, 255), closed=True)
    return picture


def _polyline(picture: np.ndarray, pts: np.ndarray, colour, closed: bool = False) -> None:
    cv2.polylines(picture, [np.round(pts).astype(np.int32)], closed, colour, 2, cv2.LINE_AA)


# -- command line -----------------------------------------------------------------------------
def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="udan-calibrate", description=__doc__.split("\n")[0].split(": ", 1)[1]
    )
    commands = parser.add_subparsers(dest="command", required=True)

    def board_options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--squares", default="7x5", help="squares across x down (default 7x5)")
        p.add_argument("--square-mm", type=float, default=30.0, help="square side (default 30)")
        p.add_argument("--marker-mm", type=float, default=22.0, help="marker side (default 22)")
        p.add_argument(
            "--dictionary",
            default="DICT_5X5_100",
            help="ArUco dictionary of the board's markers (default DICT_5X5_100: none of them "
            "can pass for an arena marker)",
        )

    board = commands.add_parser("board", help="a printable ChArUco board")
    board.add_argument("--out", required=True, type=Path, help="board.pdf (true size) or .png")
    board_options(board)

    camera = commands.add_parser("camera", help="calibrate a camera from views of the board")
    source = camera.add_mutually_exclusive_group(required=True)
    source.add_argument("--images", help="a folder of images of the board")
    source.add_argument(
        "--camera", help="a camera (as udan-edge --camera), at its current mode: move the board"
    )
    camera.add_argument("--out", required=True, type=Path, help="calibration YAML to write")
    camera.add_argument(
        "--views", type=int, default=20, help="views to take from --camera (default 20)"
    )
    board_options(camera)

    probe = commands.add_parser("probe", help="a camera's modes and controls, and its mode")
    probe.add_argument(
        "--camera", required=True, help="as udan-edge --camera, with the mode's ?options"
    )

    check = commands.add_parser("check", help="the arena as the vision sees it")
    check.add_argument("--camera", required=True, help="camera, video file or image folder")
    check.add_argument("--calibration", help="the camera's calibration YAML")
    check.add_argument(
        "--frames", type=int, default=48, help="frames to analyse (default 48: four sweeps)"
    )
    check.add_argument("--out", type=Path, help="picture of the detected arena (.png)")
    return parser


def run(args: argparse.Namespace) -> list[str]:
    """One subcommand; returns the lines to print."""
    if args.command == "board":
        return [f"{args.out}: {make_board(_board_spec(args), args.out)}"]
    if args.command == "camera":
        if args.views < MIN_VIEWS:
            raise CalibrateError(f"--views {args.views}: at least {MIN_VIEWS}")
        spec = _board_spec(args)
        source = args.images if args.images is not None else args.camera
        if args.images is not None and not Path(args.images).is_dir():
            raise CalibrateError(f"--images {args.images}: no such folder")
        views = collect_views(source, spec, args.views, live=args.camera is not None)
        calibration, rms = calibrate(views)
        save_calibration(args.out, calibration)
        k, d = calibration.camera_matrix, calibration.dist_coeffs
        lines = [
            f"{args.out}: {views.count} views, {views.size[0]}x{views.size[1]}, "
            f"RMS reprojection error {rms:.3f} px",
            f"  focal length {k[0, 0]:.1f} x {k[1, 1]:.1f} px, principal point "
            f"({k[0, 2]:.1f}, {k[1, 2]:.1f}), k1 {d[0]:+.4f} k2 {d[1]:+.4f}",
        ]
        if views.coverage < GOOD_COVERAGE:
            lines.append(
                f"  warning: the board covered {100 * views.coverage:.0f} % of the frame; "
                "views nearer its edges and corners make the lens model hold there too"
            )
        return lines
    if args.command == "probe":
        return probe_camera(args.camera)
    if args.frames < 1:
        raise CalibrateError(f"--frames {args.frames}: at least 1")
    return check_arena(args.camera, args.calibration, args.frames, args.out)


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        lines = run(args)
    except (CalibrateError, VisionError) as err:
        print(f"udan-calibrate: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"udan-calibrate: {err.filename or ''}: {err.strerror}", file=sys.stderr)
        return 2
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
