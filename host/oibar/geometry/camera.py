"""Pinhole model of the paper's camera (DFK 22BUC03, MT9V024 sensor, 3.5 mm lens), and the two
pixel conventions the project meets.

Camera frame C (OpenCV axes): +X right, +Y down, +Z along the optical axis (forward); metres.

Pixel conventions (u right, v down, in pixels):

``PIXEL_CORNER`` (the project's): continuous coordinates with the origin at the top-left *corner*
    of the top-left pixel, so pixel (col i, row j) covers [i, i+1) x [j, j+1) and its centre is
    (i + 0.5, j + 0.5). The image centre is exactly (W/2, H/2) = (372, 240), where the principal
    point sits. The data set's labels, the renderer, the networks and ``PinholeCamera.K`` use
    it; resizing an image by (sx, sy) scales these coordinates exactly (:func:`scale_intrinsics`).
``PIXEL_CENTRE`` (OpenCV's): pixel centres on integers, so the same point has coordinates
    half a pixel smaller on both axes. cv2 functions (PnP, warps, drawing) want it:
    :func:`corner_to_centre_px` and :meth:`PinholeCamera.K_centre` convert.

The paper quotes HFOV 65.6 deg and VFOV 44.7 deg, which disagree by ~1 % for square pixels. The
lens and the sensor are taken as authoritative: f = 3.5 mm / 6.0 um = 583.33 px, square pixels,
which gives HFOV = 2 atan(372/583.33) = 65.1 deg and VFOV = 2 atan(240/583.33) = 44.7 deg.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ._types import ArrayLike, FloatArray

FOCAL_LENGTH_MM = 3.5
PIXEL_PITCH_UM = 6.0

PIXEL_CORNER = "corner"
"""Name of the project's pixel convention: origin at the top-left pixel's corner."""
PIXEL_CENTRE = "centre"
"""Name of OpenCV's pixel convention: origin at the top-left pixel's centre."""
CENTRE_MINUS_CORNER_PX = -0.5
"""A point's coordinate in ``PIXEL_CENTRE`` minus its coordinate in ``PIXEL_CORNER``, pixels,
on both axes."""


def corner_to_centre_px(uv_corner_px: ArrayLike) -> FloatArray:
    """Pixel coordinates (..., 2), ``PIXEL_CORNER`` -> ``PIXEL_CENTRE`` (OpenCV)."""
    out: FloatArray = np.asarray(uv_corner_px, dtype=float) + CENTRE_MINUS_CORNER_PX
    return out


def centre_to_corner_px(uv_centre_px: ArrayLike) -> FloatArray:
    """Pixel coordinates (..., 2), ``PIXEL_CENTRE`` (OpenCV) -> ``PIXEL_CORNER``."""
    out: FloatArray = np.asarray(uv_centre_px, dtype=float) - CENTRE_MINUS_CORNER_PX
    return out


def intrinsics(fx_px: float, fy_px: float, cx_px: float, cy_px: float) -> FloatArray:
    """3x3 intrinsics; the principal point is in whatever convention the caller uses."""
    return np.array([[fx_px, 0, cx_px], [0, fy_px, cy_px], [0, 0, 1]], dtype=np.float64)


def intrinsics_corner_to_centre(K_corner: ArrayLike) -> FloatArray:
    """Intrinsics in ``PIXEL_CORNER`` -> the same camera in ``PIXEL_CENTRE`` (principal point
    moved by -0.5 px on both axes)."""
    K = np.array(K_corner, dtype=float)
    K[0, 2] += CENTRE_MINUS_CORNER_PX
    K[1, 2] += CENTRE_MINUS_CORNER_PX
    return K


def scale_intrinsics(K: ArrayLike, sx: float, sy: float) -> FloatArray:
    """Intrinsics after resizing the image by (sx, sy). Exact in ``PIXEL_CORNER`` only."""
    out: FloatArray = np.diag([sx, sy, 1.0]) @ np.asarray(K, dtype=float)
    return out


def project_camera_points(K: ArrayLike, p_cam_m: ArrayLike) -> FloatArray:
    """Points (N, 3) in C, metres -> (N, 2) pixels in K's convention. No check for points
    behind the camera (see :func:`project_target_points`)."""
    p = np.atleast_2d(p_cam_m) @ np.asarray(K).T
    out: FloatArray = p[:, :2] / p[:, 2:3]
    return out


def project_target_points(K: ArrayLike, points_m: ArrayLike, R: ArrayLike, T: ArrayLike) -> FloatArray:
    """Target points (N, 3), metres in the target frame, seen with ``R = R_cam_target`` and
    ``T = T_cam_target_m`` -> pixels (N, 2) in K's convention. Points at or behind the camera
    (z <= 0) give NaN."""
    p = np.asarray(points_m, float) @ np.asarray(R, float).T + np.asarray(T, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv: FloatArray = (p @ np.asarray(K, float).T)[:, :2] / p[:, 2:3]
    uv[p[:, 2] <= 0] = np.nan
    return uv


def rotation_homography(K: ArrayLike, R_new_old: ArrayLike) -> FloatArray:
    """Pixel map old -> new of a pure camera rotation ``R_new_old``: exact for any scene depth
    (which is why the pose augmentations use it: new labels T' = R T, R_cam_target' = R R_cam_target)."""
    Km = np.asarray(K, dtype=float)
    out: FloatArray = Km @ np.asarray(R_new_old) @ np.linalg.inv(Km)
    return out


@dataclass(frozen=True)
class PinholeCamera:
    """The flight camera: size in pixels, focal lengths and principal point in pixels
    (``PIXEL_CORNER``), and the near/far clip distances (metres) the renderer draws between."""

    width_px: int = 744
    height_px: int = 480
    fx_px: float = FOCAL_LENGTH_MM / (PIXEL_PITCH_UM * 1e-3)
    fy_px: float = FOCAL_LENGTH_MM / (PIXEL_PITCH_UM * 1e-3)
    cx_px: float = 372.0
    cy_px: float = 240.0
    near_m: float = 0.05
    far_m: float = 400.0

    @property
    def K(self) -> FloatArray:
        """Intrinsics in ``PIXEL_CORNER``."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    def K_centre(self) -> FloatArray:
        """Intrinsics in ``PIXEL_CENTRE`` (OpenCV; principal point 371.5, 239.5)."""
        return intrinsics_corner_to_centre(self.K)

    K_opencv = K_centre

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view, degrees."""
        return float(np.degrees(2.0 * np.arctan(self.width_px / 2.0 / self.fx_px)))

    @property
    def vfov_deg(self) -> float:
        """Vertical field of view, degrees."""
        return float(np.degrees(2.0 * np.arctan(self.height_px / 2.0 / self.fy_px)))

    def project(self, p_cam_m: ArrayLike) -> FloatArray:
        """Points (N, 3) in C, metres -> (N, 2) pixels (``PIXEL_CORNER``, u right, v down).
        Points at or behind the camera give NaN."""
        p = np.atleast_2d(np.asarray(p_cam_m, dtype=float))
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(z > 0, self.fx_px * p[:, 0] / z + self.cx_px, np.nan)
            v = np.where(z > 0, self.fy_px * p[:, 1] / z + self.cy_px, np.nan)
        return np.stack([u, v], axis=1)

    def as_dict(self) -> dict[str, Any]:
        """The fields plus the fields of view (3 decimals), as the data set's manifest stores them."""
        d = asdict(self)
        d.update(hfov_deg=round(self.hfov_deg, 3), vfov_deg=round(self.vfov_deg, 3))
        return d
