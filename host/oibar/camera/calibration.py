"""A camera's calibration (intrinsics and distortion) and the one remap that turns its frames into
the network's canonical camera.

Files read (:func:`load_calibration`):

- OpenCV's calibration YAML/XML/JSON (``cv2.FileStorage``; what ``oibar calibrate-camera`` and
  OpenCV's own calibration sample write): ``camera_matrix`` and ``distortion_coefficients`` as
  ``!!opencv-matrix``, ``image_width``, ``image_height``;
- ROS ``camera_info`` YAML, as ``camera_calibration_parsers`` writes it (``image_width``,
  ``image_height``, ``camera_matrix.data``, ``distortion_model``, ``distortion_coefficients.data``)
  or as a CameraInfo message is dumped (``width``, ``height``, ``K``/``k``, ``D``/``d``).
  Distortion ``plumb_bob`` (5 coefficients), ``rational_polynomial`` (8) or none; another model
  (``equidistant``, fisheye) is refused.

Both give the same :class:`CameraCalibration`: K in OpenCV's pixel convention (pixel centres on
integers, as OpenCV and ROS both write it), OpenCV's distortion vector, the image size.

:class:`CanonicalRemap` undistorts a frame of that camera and resamples it into the canonical
camera (the model's ``oibar.camera``: 744x480, f 583.33 px, principal point at the centre) with one
precomputed ``cv2.remap``. Canonical pixels the camera does not see (a narrower field of view) come
out black and are reported (``uncovered_fraction``, ``uncovered_border_px``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from oibar.geometry.camera import PinholeCamera, intrinsics_corner_to_centre

# ROS distortion models -> the number of OpenCV coefficients they carry.
ROS_DISTORTION_MODELS = {"plumb_bob": 5, "rational_polynomial": 8}
OPENCV_DIST_LENGTHS = (4, 5, 8, 12, 14)
# A canonical pixel counts as covered when its source lies inside the camera's image (OpenCV
# pixel centres, so -0.5 .. W-0.5) and where the lens model is still one-to-one.
_YAML_HEADER = "%YAML:1.0\n"


class CalibrationError(ValueError):
    """A calibration file that cannot be read or makes no sense; or a frame that does not match it."""


@dataclass(frozen=True)
class CameraCalibration:
    """Image size in pixels, K (3x3, OpenCV pixel convention: pixel centres on integers), OpenCV's
    distortion vector (k1, k2, p1, p2[, k3[, k4, k5, k6[, ...]]]) and where it came from."""

    width_px: int
    height_px: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    source: str = ""

    def __post_init__(self) -> None:
        K = np.asarray(self.K, float)
        dist = np.asarray(self.dist, float).ravel()
        where = f"{self.source}: " if self.source else ""
        if self.width_px <= 0 or self.height_px <= 0:
            raise CalibrationError(f"{where}image size must be > 0, got {self.width_px}x{self.height_px}")
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise CalibrationError(f"{where}the camera matrix must be 3x3 finite numbers")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1.0) > 1e-9 or np.any(K[2, :2] != 0):
            raise CalibrationError(f"{where}the camera matrix must have fx, fy > 0 and last row 0 0 1")
        if len(dist) == 0:
            dist = np.zeros(5)
        if len(dist) not in OPENCV_DIST_LENGTHS or not np.all(np.isfinite(dist)):
            raise CalibrationError(
                f"{where}need 0, 4, 5, 8, 12 or 14 finite distortion coefficients, got {len(dist)}"
            )
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)

    @property
    def size_wh(self) -> tuple[int, int]:
        return self.width_px, self.height_px

    def describe(self) -> str:
        d = ", ".join(f"{v:.4g}" for v in self.dist if v != 0) or "none"
        return (
            f"{self.width_px}x{self.height_px}, f {self.K[0, 0]:.1f}/{self.K[1, 1]:.1f} px, "
            f"c ({self.K[0, 2]:.1f}, {self.K[1, 2]:.1f}), distortion {d}"
        )


def _node_numbers(node: Any) -> np.ndarray:
    """A FileStorage node -> float array: an ``!!opencv-matrix``, a sequence, or a ROS matrix
    mapping (``rows``, ``cols``, ``data``)."""
    if node.isMap() and not node.getNode("data").empty() and node.getNode("dt").empty():
        node = node.getNode("data")
    if node.isSeq():
        return np.array([node.at(i).real() for i in range(node.size())], float)
    mat = node.mat()
    if mat is None:
        raise CalibrationError("not a matrix")
    return np.asarray(mat, float).ravel()


def _first(fs: Any, *names: str) -> tuple[str, Any] | None:
    for n in names:
        node = fs.getNode(n)
        if not node.empty():
            return n, node
    return None


def load_calibration(path: str | Path) -> CameraCalibration:
    """OpenCV calibration YAML/XML/JSON or ROS camera_info YAML -> :class:`CameraCalibration`;
    CalibrationError naming the file for anything else."""
    import cv2

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CalibrationError(f"calibration file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: cannot read the calibration file ({exc})") from None
    stripped = text.lstrip()
    if not stripped:
        raise CalibrationError(f"{path}: empty calibration file")
    # OpenCV's YAML parser wants its directive; ROS files have none
    if not stripped.startswith(("%YAML", "<", "{")):
        text = _YAML_HEADER + text
    elif stripped.startswith("%YAML") and not stripped.startswith("%YAML:1."):
        text = _YAML_HEADER + text.split("\n", 1)[1] if "\n" in text else text
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
        ok = fs.isOpened() and fs.root().isMap()
    except (cv2.error, SystemError) as exc:
        raise CalibrationError(
            f"{path}: not an OpenCV calibration or ROS camera_info file ({str(exc).strip().splitlines()[-1]})"
        ) from None
    if not ok:
        raise CalibrationError(f"{path}: not an OpenCV calibration or ROS camera_info file")
    try:
        return _parse(fs, str(path))
    except CalibrationError as exc:
        msg = str(exc)
        raise CalibrationError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    except (cv2.error, SystemError, TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: malformed calibration ({exc})") from None


def _parse(fs: Any, source: str) -> CameraCalibration:
    k = _first(fs, "camera_matrix", "K", "k")
    if k is None:
        raise CalibrationError("no camera_matrix (OpenCV) or camera_matrix/K (ROS camera_info) in it")
    K = _node_numbers(k[1])
    if K.size != 9:
        raise CalibrationError(f"{k[0]} must have 9 numbers, has {K.size}")
    size = [_first(fs, "image_width", "width"), _first(fs, "image_height", "height")]
    if size[0] is None or size[1] is None:
        raise CalibrationError("no image_width/image_height (or width/height): the image size is needed")
    w, h = (float(s[1].real()) for s in size if s is not None)
    if w != int(w) or h != int(h):
        raise CalibrationError(f"image size must be whole pixels, got {w}x{h}")
    model_node = fs.getNode("distortion_model")
    model = model_node.string().strip().lower() if not model_node.empty() else ""
    d = _first(fs, "distortion_coefficients", "D", "d")
    dist = _node_numbers(d[1]) if d is not None and not d[1].isNone() else np.zeros(0)
    if model and model not in ("none", *ROS_DISTORTION_MODELS):
        raise CalibrationError(
            f"distortion_model {model!r} is not supported (plumb_bob, rational_polynomial or none)"
        )
    if model in ROS_DISTORTION_MODELS and len(dist) and len(dist) != ROS_DISTORTION_MODELS[model]:
        raise CalibrationError(
            f"distortion_model {model} has {ROS_DISTORTION_MODELS[model]} coefficients, got {len(dist)}"
        )
    if model == "none" and np.any(dist != 0):
        raise CalibrationError("distortion_model none with non-zero distortion coefficients")
    return CameraCalibration(int(w), int(h), K.reshape(3, 3), dist, source)


def write_opencv_yaml(path: str | Path, calib: CameraCalibration, **extra: float | str) -> None:
    """OpenCV's calibration YAML (cv2.FileStorage): image_width, image_height, camera_matrix,
    distortion_coefficients, plus any extra scalars (e.g. the RMS reprojection error)."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
    if not fs.isOpened():
        raise CalibrationError(f"{path}: cannot write the calibration file")
    try:
        fs.write("image_width", int(calib.width_px))
        fs.write("image_height", int(calib.height_px))
        fs.write("camera_matrix", np.asarray(calib.K, np.float64))
        fs.write("distortion_coefficients", np.asarray(calib.dist, np.float64).reshape(1, -1))
        for key, value in extra.items():
            fs.write(key, value)
    finally:
        fs.release()


def write_camera_info_yaml(path: str | Path, calib: CameraCalibration, camera_name: str = "camera") -> None:
    """ROS camera_info YAML as camera_calibration_parsers writes it (plumb_bob for up to 5
    coefficients, rational_polynomial for 8)."""
    dist = list(calib.dist)
    if len(dist) in (4, 5):
        model, dist = "plumb_bob", (dist + [0.0])[:5]
    elif len(dist) == 8:
        model = "rational_polynomial"
    else:
        raise CalibrationError(f"ROS camera_info has no model for {len(dist)} coefficients")
    K = [float(v) for v in np.asarray(calib.K).ravel()]
    P = [K[0], K[1], K[2], 0.0, K[3], K[4], K[5], 0.0, 0.0, 0.0, 1.0, 0.0]

    def mat(rows: int, cols: int, data: list[float]) -> str:
        return f"  rows: {rows}\n  cols: {cols}\n  data: [{', '.join(repr(float(v)) for v in data)}]\n"

    Path(path).write_text(
        f"image_width: {calib.width_px}\nimage_height: {calib.height_px}\ncamera_name: {camera_name}\n"
        f"camera_matrix:\n{mat(3, 3, K)}distortion_model: {model}\n"
        f"distortion_coefficients:\n{mat(1, len(dist), dist)}"
        f"rectification_matrix:\n{mat(3, 3, [1, 0, 0, 0, 1, 0, 0, 0, 1])}"
        f"projection_matrix:\n{mat(3, 4, P)}",
        encoding="utf-8",
    )


def canonical_camera(meta: dict[str, Any] | None = None) -> tuple[np.ndarray, tuple[int, int]]:
    """The network's canonical camera: (K in the project's PIXEL_CORNER convention, (w, h)), from a
    model's ``oibar.camera`` metadata (K_frame, width_px, height_px), else PinholeCamera's."""
    cam = (meta or {}).get("camera") or {}
    if "K_frame" in cam and "width_px" in cam and "height_px" in cam:
        return np.array(cam["K_frame"], float), (int(cam["width_px"]), int(cam["height_px"]))
    pc = PinholeCamera()
    return pc.K, (pc.width_px, pc.height_px)


def _fold_radius(dist: np.ndarray, r_max: float) -> float:
    """The normalised radius up to which the radial distortion r -> r_d stays increasing (a lens
    model is one-to-one only there; beyond, a strong barrel folds back onto the image)."""
    d = np.zeros(14)
    d[: len(dist)] = dist
    k1, k2, _, _, k3, k4, k5, k6 = d[:8]
    r = np.linspace(0.0, max(r_max, 1e-6) * 1.01, 4001)
    r2 = r * r
    rd = r * (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    bad = np.flatnonzero(np.diff(rd) <= 0)
    return float(r[bad[0]]) if len(bad) else float("inf")


class CanonicalRemap:
    """One camera's frames -> the canonical camera's, by one precomputed ``cv2.remap``
    (``cv2.initUndistortRectifyMap`` to the canonical K: undistorted and resampled at once).

    ``apply(frame)`` raises a FrameError-compatible ValueError (:class:`CalibrationError`) for a
    frame that is not this camera's size: never a silent guess. ``uncovered`` marks the canonical
    pixels this camera does not see (black after the remap); ``uncovered_fraction`` and
    ``uncovered_border_px`` (left, top, right, bottom: the widest uncovered run from each edge along
    the centre lines) say how much; ``warning()`` is the line to print when there is any."""

    def __init__(
        self,
        calib: CameraCalibration,
        K_canonical_corner: np.ndarray,
        canonical_wh: tuple[int, int],
    ) -> None:
        import cv2

        self.calib = calib
        self.canonical_wh = (int(canonical_wh[0]), int(canonical_wh[1]))
        self.K_canonical = intrinsics_corner_to_centre(K_canonical_corner)  # cv2 wants pixel centres
        w, h = self.canonical_wh
        self.map_x, self.map_y = cv2.initUndistortRectifyMap(
            calib.K, calib.dist, None, self.K_canonical, (w, h), cv2.CV_32FC1
        )
        W, H = calib.size_wh
        inside = (
            (self.map_x >= -0.5) & (self.map_x <= W - 0.5) & (self.map_y >= -0.5) & (self.map_y <= H - 0.5)
        )
        # where the lens model folds back, the map points at pixels that see other rays
        u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        Kc = self.K_canonical
        r = np.hypot((u - Kc[0, 2]) / Kc[0, 0], (v - Kc[1, 2]) / Kc[1, 1])
        fold = _fold_radius(calib.dist, float(r.max()))
        self.uncovered: np.ndarray = ~(inside & (r < fold))
        # the fast fixed-point maps for the per-frame remap; uncovered pixels point outside the
        # frame, so the constant border fills them black
        mx = np.where(self.uncovered, -10.0, self.map_x).astype(np.float32)
        my = np.where(self.uncovered, -10.0, self.map_y).astype(np.float32)
        self._m1, self._m2 = cv2.convertMaps(mx, my, cv2.CV_16SC2)
        self.uncovered_fraction = float(self.uncovered.mean())
        cy, cx = h // 2, w // 2
        row, col = self.uncovered[cy], self.uncovered[:, cx]

        def run(a: np.ndarray) -> int:
            return int(np.argmin(a)) if not a.all() else len(a)

        self.uncovered_border_px = (run(row), run(col), run(row[::-1]), run(col[::-1]))

    def warning(self) -> str:
        """One line when the camera covers less than the canonical field of view, else ''."""
        if self.uncovered_fraction <= 0:
            return ""
        left, top, right, bottom = self.uncovered_border_px
        return (
            f"camera {self.calib.describe()} covers less than the network's "
            f"{self.canonical_wh[0]}x{self.canonical_wh[1]} canonical view: "
            f"{100 * self.uncovered_fraction:.1f} % of it is black (border left {left}, top {top}, "
            f"right {right}, bottom {bottom} px); the fixture is not seen there"
        )

    def check(self, image: Any) -> None:
        if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3:
            shape = getattr(image, "shape", type(image).__name__)
            raise CalibrationError(f"frame must be an (H, W, 3) RGB array, got {shape}")
        if image.dtype != np.uint8:
            raise CalibrationError(f"frame dtype must be uint8, got {image.dtype}")
        h, w = image.shape[:2]
        if (w, h) != self.calib.size_wh:
            W, H = self.calib.size_wh
            where = f" ({self.calib.source})" if self.calib.source else ""
            raise CalibrationError(
                f"frame {w}x{h} does not match the calibration's {W}x{H}{where}: "
                "wrong calibration file, or the camera's resolution changed"
            )

    def apply(self, image: np.ndarray) -> np.ndarray:
        """This camera's frame (H, W, 3) uint8 -> the canonical camera's (h, w, 3) uint8."""
        import cv2

        self.check(image)
        out: np.ndarray = cv2.remap(
            image, self._m1, self._m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )
        return out
