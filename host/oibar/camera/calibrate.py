"""``oibar calibrate-camera``: a camera's intrinsics and distortion from images of a chessboard or
a ChArUco board (OpenCV: findChessboardCorners + cornerSubPix, or cv2.aruco's CharucoDetector;
then calibrateCamera), written as OpenCV's calibration YAML that ``--calibration`` reads.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from oibar import argtypes
from oibar.camera.calibration import (
    CalibrationError,
    CameraCalibration,
    write_camera_info_yaml,
    write_opencv_yaml,
)

EXIT_OK = 0
EXIT_ERROR = 2
MIN_VIEWS = 3
MIN_CHARUCO_CORNERS = 6
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
_SUBPIX_CRITERIA = (3, 50, 1e-3)  # cv2.TERM_CRITERIA_EPS + COUNT, 50 iterations, 1e-3 px


@dataclass(frozen=True)
class Board:
    """A chessboard (``inner_wh``: its inner corners across and down) or a ChArUco board
    (``charuco``: ``inner_wh`` is then its squares across and down), square side in metres."""

    inner_wh: tuple[int, int]
    square_m: float
    charuco: bool = False
    marker_m: float = 0.0
    dictionary: str = "DICT_4X4_50"

    def object_points(self) -> np.ndarray:
        """(N, 3) corners in the board's plane (z = 0), metres, in detection order (chessboard)
        or by ChArUco id."""
        if self.charuco:
            return np.asarray(self.charuco_board().getChessboardCorners(), np.float32)
        cols, rows = self.inner_wh
        grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2)
        return np.hstack([grid * self.square_m, np.zeros((len(grid), 1))]).astype(np.float32)

    def charuco_board(self) -> Any:
        import cv2

        if not hasattr(cv2, "aruco"):
            raise CalibrationError(
                "this OpenCV build has no cv2.aruco module: use a chessboard (--chessboard)"
            )
        try:
            d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        except AttributeError:
            raise CalibrationError(
                f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_4X4_50)"
            ) from None
        return cv2.aruco.CharucoBoard(self.inner_wh, self.square_m, self.marker_m, d)


@dataclass
class CalibrationResult:
    calibration: CameraCalibration
    rms_px: float
    views_used: list[str] = field(default_factory=list)
    views_skipped: list[str] = field(default_factory=list)
    per_view_rms_px: list[float] = field(default_factory=list)


def _subpix(gray: np.ndarray, uv: np.ndarray, half: int) -> np.ndarray:
    import cv2

    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, *_SUBPIX_CRITERIA[1:])
    out: np.ndarray = cv2.cornerSubPix(
        gray, uv.reshape(-1, 1, 2).astype(np.float32), (half, half), (-1, -1), criteria
    )
    return out.reshape(-1, 2)


def _half_window(uv: np.ndarray) -> int:
    d = np.linalg.norm(uv[:, None] - uv[None], axis=2)
    d[d == 0] = np.inf
    spacing = float(d.min()) if np.isfinite(d).any() else 10.0
    return int(np.clip(spacing * 0.3, 2, 11))


def detect(gray: np.ndarray, board: Board) -> tuple[np.ndarray, np.ndarray] | None:
    """The board's corners in one grey image: (object points (N, 3), image points (N, 2),
    OpenCV pixel convention), or None where the board is not found."""
    import cv2

    if board.charuco:
        detector = cv2.aruco.CharucoDetector(board.charuco_board())
        corners, ids, _, _ = detector.detectBoard(gray)
        if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
            return None
        uv = corners.reshape(-1, 2)
        # CharucoDetector up to OpenCV 4.13 returns its corners +0.5 px off (opencv issue #25539):
        # cornerSubPix again converges to the saddle point whatever the start
        uv = _subpix(gray, uv, _half_window(uv))
        return board.object_points()[ids.ravel()], uv
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH + cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, board.inner_wh, flags=flags)
    if not found:
        return None
    uv = corners.reshape(-1, 2)
    return board.object_points(), _subpix(gray, uv, _half_window(uv))


def calibrate(
    images: list[tuple[str, np.ndarray]], board: Board, rational: bool = False
) -> CalibrationResult:
    """Named grey (or BGR) images of the board -> the calibration; CalibrationError when the
    images differ in size or too few show the board."""
    import cv2

    if not images:
        raise CalibrationError("no images")
    sizes = {(im.shape[1], im.shape[0]) for _, im in images}
    if len(sizes) > 1:
        raise CalibrationError(f"the images differ in size ({sorted(sizes)}): one camera, one resolution")
    (w, h) = sizes.pop()
    obj, img, used, skipped = [], [], [], []
    for name, im in images:
        gray = im if im.ndim == 2 else cv2.cvtColor(im, cv2.COLOR_BGR2GRAY)
        det = detect(gray, board)
        if det is None:
            skipped.append(name)
            continue
        obj.append(det[0].astype(np.float32))
        img.append(det[1].astype(np.float32).reshape(-1, 1, 2))
        used.append(name)
    if len(used) < MIN_VIEWS:
        raise CalibrationError(
            f"the board was found in {len(used)} of {len(images)} image(s); at least {MIN_VIEWS} "
            "views are needed (check --chessboard/--charuco: inner corners for a chessboard, squares for ChArUco)"
        )
    flags = cv2.CALIB_RATIONAL_MODEL if rational else 0
    # the matrices passed in are only filled (no CALIB_USE_INTRINSIC_GUESS): OpenCV starts from its own
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        obj, img, (w, h), np.eye(3), np.zeros(8 if rational else 5), flags=flags
    )
    per_view = []
    for o, i, r, t in zip(obj, img, rvecs, tvecs, strict=True):
        proj = cv2.projectPoints(o, r, t, K, dist)[0].reshape(-1, 2)
        per_view.append(float(np.sqrt(np.mean(np.sum((proj - i.reshape(-1, 2)) ** 2, axis=1)))))
    dist = np.asarray(dist, float).ravel()[: 8 if rational else 5]
    return CalibrationResult(
        CameraCalibration(w, h, np.asarray(K, float), dist), float(rms), used, skipped, per_view
    )


def _wh(text: str) -> tuple[int, int]:
    try:
        a, b = (int(v, 10) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not COLSxROWS (e.g. 9x6)") from None
    if a < 2 or b < 2:
        raise argparse.ArgumentTypeError(f"{text!r}: at least 2x2")
    return a, b


_EPILOG = """\
boards:
  --chessboard 9x6 --square-mm 25       a chessboard with 9x6 inner corners (10x7 squares)
  --charuco 7x5 --square-mm 30 --marker-mm 22 [--dictionary DICT_4X4_50]
                                        a ChArUco board of 7x5 squares (cv2.aruco: available in
                                        the opencv-python-headless oibar installs; partial views work)

Take 10-30 images at the camera's working resolution, the board filling different parts of
the frame, tilted up to ~45 deg. Write the result with -o camera.yaml and pass it to
`oibar nav/pose/replay --calibration camera.yaml` (or `oibar calib ... --intrinsics`).

exit status: 0 written; 2 bad argument, unreadable image, images of different sizes, or the
board found in fewer than 3 images (one line on stderr, never a traceback).
"""


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "calibrate-camera",
        help="calibrate a camera from chessboard or ChArUco images (OpenCV YAML out)",
        description="Estimate a camera's intrinsics and lens distortion from images of a "
        "chessboard or ChArUco board (OpenCV calibrateCamera) and write OpenCV's calibration "
        "YAML (camera_matrix, distortion_coefficients, image_width, image_height).",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("images", nargs="+", type=Path, metavar="IMAGE", help="board images, or folders of them")
    kind = p.add_mutually_exclusive_group(required=True)
    kind.add_argument(
        "--chessboard", type=_wh, metavar="COLSxROWS", help="chessboard inner corners, e.g. 9x6"
    )
    kind.add_argument("--charuco", type=_wh, metavar="COLSxROWS", help="ChArUco board squares, e.g. 7x5")
    p.add_argument(
        "--square-mm", type=argtypes.positive(), required=True, metavar="MM", help="square side, mm (> 0)"
    )
    p.add_argument(
        "--marker-mm", type=argtypes.positive(), default=None, metavar="MM", help="ChArUco marker side, mm"
    )
    p.add_argument(
        "--dictionary", default="DICT_4X4_50", help="ChArUco ArUco dictionary (default DICT_4X4_50)"
    )
    p.add_argument(
        "--rational", action="store_true", help="8-coefficient rational distortion model (wide-angle lenses)"
    )
    p.add_argument(
        "-o", "--out", type=Path, required=True, metavar="YAML", help="OpenCV calibration YAML to write"
    )
    p.add_argument(
        "--camera-info", type=Path, default=None, metavar="YAML", help="also write a ROS camera_info YAML"
    )
    p.set_defaults(handler=cmd_calibrate_camera, run=run)


def run(args: argparse.Namespace) -> int:
    try:
        return int(args.handler(args))
    except (CalibrationError, OSError) as exc:
        print(f"oibar: error: {exc}", file=sys.stderr, flush=True)
        return EXIT_ERROR


def _image_files(paths: list[Path]) -> list[Path]:
    out: list[Path] = []
    for p in paths:
        if p.is_dir():
            out += sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
        else:
            out.append(p)
    return out


def cmd_calibrate_camera(a: argparse.Namespace) -> int:
    import cv2

    if a.charuco is not None:
        if a.marker_mm is None or not a.marker_mm < a.square_mm:
            raise CalibrationError("--charuco needs --marker-mm smaller than --square-mm")
        board = Board(a.charuco, a.square_mm / 1e3, True, a.marker_mm / 1e3, a.dictionary)
        board.charuco_board()  # an unknown dictionary or no cv2.aruco: one line now
    else:
        board = Board(a.chessboard, a.square_mm / 1e3)
    files = _image_files(a.images)
    if not files:
        raise CalibrationError("no images (folders are searched for " + ", ".join(IMAGE_SUFFIXES) + ")")
    images = []
    for f in files:
        im = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) if f.is_file() else None
        if im is None:
            raise CalibrationError(f"{f}: cannot read the image")
        images.append((str(f), im))
    res = calibrate(images, board, rational=a.rational)
    c = res.calibration
    write_opencv_yaml(a.out, c, rms_reprojection_px=res.rms_px, views=len(res.views_used))
    if a.camera_info is not None:
        write_camera_info_yaml(a.camera_info, c)
    print(f"board found in {len(res.views_used)} of {len(images)} images")
    for name in res.views_skipped:
        print(f"  no board: {name}")
    print(f"camera {c.describe()}")
    print(f"RMS reprojection {res.rms_px:.3f} px (worst view {max(res.per_view_rms_px):.3f} px)")
    print(f"wrote {a.out}" + (f" and {a.camera_info}" if a.camera_info else ""))
    return EXIT_OK
