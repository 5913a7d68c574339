"""The calibration pattern on the target: detection, PnP pose and its covariance.

The pattern is a ChArUco board (a chessboard with ArUco markers in the white squares): every
corner carries an id, so partial views work and there is no 180-degree ordering ambiguity as
with a plain chessboard. Pattern frame: origin at the board's outer top-left corner, +X along
the squares' columns, +Y along the rows, +Z into the board (OpenCV's board convention).
`T_target_pattern` places it on the target (from the fixture drawing / how it is clamped).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from oibar.geometry.camera import PinholeCamera
from oibar.geometry.transforms import make_T

from .errors import CalibError

MIN_CORNERS = 8


@dataclass
class Pattern:
    squares_x: int
    squares_y: int
    square_m: float
    marker_m: float
    dictionary: str = "DICT_4X4_50"
    T_target_pattern: np.ndarray = field(default_factory=lambda: np.eye(4))

    def board(self):
        try:
            d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        except AttributeError:
            raise CalibError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_4X4_50)") from None
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m, d)

    @property
    def size_m(self) -> tuple[float, float]:
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    def corners_pattern_m(self) -> np.ndarray:
        """(K, 3) chessboard corners in the pattern frame, indexed by ChArUco corner id."""
        return np.asarray(self.board().getChessboardCorners(), dtype=float)


@dataclass
class Intrinsics:
    """Pinhole + OpenCV distortion, OpenCV pixel convention (pixel centres on integers)."""

    width_px: int
    height_px: int
    K: np.ndarray
    dist: np.ndarray

    @classmethod
    def oibar_default(cls) -> Intrinsics:
        cam = PinholeCamera()
        return cls(cam.width_px, cam.height_px, cam.K_centre(), np.zeros(5))


@dataclass
class Observation:
    ids: np.ndarray  # (K,) ChArUco corner ids
    uv_px: np.ndarray  # (K, 2) detected corners
    T_cam_pattern: np.ndarray  # (4, 4)
    cov: np.ndarray  # (6, 6) right perturbation (m, rad) of T_cam_pattern, per px^2 of corner noise
    rms_px: float  # PnP reprojection RMS


class Detector:
    def __init__(self, pattern: Pattern, intr: Intrinsics):
        self.pattern, self.intr = pattern, intr
        self.board = pattern.board()
        self.obj_m = pattern.corners_pattern_m()
        self.detector = cv2.aruco.CharucoDetector(self.board)

    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        corners, ids, _, _ = self.detector.detectBoard(gray)
        if ids is None or len(ids) < MIN_CORNERS:
            return None
        # CharucoDetector in OpenCV 4.x up to 4.13 returns its corners +0.5 px off (opencv
        # issue #25539, fixed upstream in PR #28380): refine them again ourselves, which
        # converges to the saddle point whatever the start and whatever the OpenCV version.
        uv = corners.reshape(-1, 1, 2).astype(np.float32)
        ids = ids.ravel().astype(int)
        spacing = _min_spacing_px(uv.reshape(-1, 2))
        half = int(np.clip(spacing * 0.3, 2, 7))
        refined = cv2.cornerSubPix(
            gray, uv, (half, half), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
        )
        return ids, refined.reshape(-1, 2).astype(float)

    def observe(self, image: np.ndarray) -> Observation | None:
        """Pattern pose in the camera, or None when too few corners are seen."""
        det = self.detect(image)
        if det is None:
            return None
        ids, uv = det
        obj = self.obj_m[ids]
        K, dist = self.intr.K, self.intr.dist
        ok, rvec, tvec = cv2.solvePnP(obj, uv, K, dist, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            return None
        rvec, tvec = cv2.solvePnPRefineLM(obj, uv, K, dist, rvec, tvec)
        T = make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
        proj = cv2.projectPoints(obj, rvec, tvec, K, dist)[0].reshape(-1, 2)
        rms = float(np.sqrt(np.mean(np.sum((proj - uv) ** 2, axis=1))))
        return Observation(ids, uv, T, pose_covariance(T, obj, K, 1.0), rms)


def _min_spacing_px(uv: np.ndarray) -> float:
    d = np.linalg.norm(uv[:, None] - uv[None], axis=2)
    d[d == 0] = np.inf
    return float(d.min()) if np.isfinite(d).any() else 10.0


def pose_covariance(
    T_cam_pattern: np.ndarray, obj_m: np.ndarray, K: np.ndarray, sigma_px: float
) -> np.ndarray:
    """Gauss-Newton covariance of the PnP pose for isotropic corner noise sigma_px, in the
    right-perturbation convention T @ Exp(d): d p_cam / d d = R [I, -[P]x]."""
    R, t = T_cam_pattern[:3, :3], T_cam_pattern[:3, 3]
    J = np.zeros((2 * len(obj_m), 6))
    fx, fy = K[0, 0], K[1, 1]
    for k, P in enumerate(obj_m):
        x, y, z = R @ P + t
        d_uv_d_p = np.array([[fx / z, 0.0, -fx * x / z**2], [0.0, fy / z, -fy * y / z**2]])
        Px = np.array([[0.0, -P[2], P[1]], [P[2], 0.0, -P[0]], [-P[1], P[0], 0.0]])
        J[2 * k : 2 * k + 2] = d_uv_d_p @ R @ np.hstack([np.eye(3), -Px])
    return sigma_px**2 * np.linalg.pinv(J.T @ J)


def project(points_m: np.ndarray, T_cam_frame: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Points in some frame -> pixels (OpenCV convention), distortion included; NaN behind."""
    rvec = cv2.Rodrigues(T_cam_frame[:3, :3])[0]
    uv = cv2.projectPoints(
        np.asarray(points_m, float).reshape(-1, 1, 3), rvec, T_cam_frame[:3, 3], intr.K, intr.dist
    )[0].reshape(-1, 2)
    z = np.asarray(points_m, float) @ T_cam_frame[:3, :3].T[:, 2] + T_cam_frame[2, 3]
    uv[z <= 1e-6] = np.nan
    return uv
