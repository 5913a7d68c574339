"""Pinhole model of the paper's camera (DFK 22BUC03, MT9V024 sensor, 3.5 mm lens).

Camera frame (OpenCV): +X right, +Y down, +Z along the optical axis (forward).

Pixel coordinates are continuous with the origin at the top-left *corner* of the top-left
pixel, so pixel (col i, row j) covers [i, i+1) x [j, j+1) and its centre is (i+0.5, j+0.5).
In that convention the image centre is exactly (W/2, H/2) = (372, 240), which is where we put
the principal point. OpenCV puts pixel centres on integers: use `K_opencv()` (cx-0.5, cy-0.5)
with cv2 functions.

The paper quotes HFOV 65.6 deg and VFOV 44.7 deg, which disagree by ~1 % for square pixels.
We take the lens and the sensor as authoritative: f = 3.5 mm / 6.0 um = 583.33 px, square
pixels, which gives HFOV = 2 atan(372/583.33) = 65.1 deg and VFOV = 2 atan(240/583.33) = 44.7 deg.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

FOCAL_LENGTH_MM = 3.5
PIXEL_PITCH_UM = 6.0


@dataclass(frozen=True)
class PinholeCamera:
    width_px: int = 744
    height_px: int = 480
    fx_px: float = FOCAL_LENGTH_MM / (PIXEL_PITCH_UM * 1e-3)
    fy_px: float = FOCAL_LENGTH_MM / (PIXEL_PITCH_UM * 1e-3)
    cx_px: float = 372.0
    cy_px: float = 240.0
    near_m: float = 0.05
    far_m: float = 400.0

    @property
    def K(self) -> np.ndarray:
        """Intrinsics in the pixel-corner convention documented above."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    def K_opencv(self) -> np.ndarray:
        """Intrinsics in OpenCV's pixel-centre convention (principal point 371.5, 239.5)."""
        K = self.K.copy()
        K[0, 2] -= 0.5
        K[1, 2] -= 0.5
        return K

    @property
    def hfov_deg(self) -> float:
        return float(np.degrees(2.0 * np.arctan(self.width_px / 2.0 / self.fx_px)))

    @property
    def vfov_deg(self) -> float:
        return float(np.degrees(2.0 * np.arctan(self.height_px / 2.0 / self.fy_px)))

    def project(self, p_cam_m: np.ndarray) -> np.ndarray:
        """Points (N,3) in the camera frame, metres -> (N,2) pixel coordinates (u right, v down).
        Points at or behind the camera give NaN."""
        p = np.atleast_2d(np.asarray(p_cam_m, dtype=float))
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(z > 0, self.fx_px * p[:, 0] / z + self.cx_px, np.nan)
            v = np.where(z > 0, self.fy_px * p[:, 1] / z + self.cy_px, np.nan)
        return np.stack([u, v], axis=1)

    def gl_projection(self) -> np.ndarray:
        """OpenGL clip matrix (row-major, column vectors) for GL eye coordinates
        (x right, y up, z backwards) that reproduces `project` after the image is read back
        and flipped so row 0 is the top."""
        W, H, n, f = self.width_px, self.height_px, self.near_m, self.far_m
        return np.array([
            [2 * self.fx_px / W, 0.0, 1.0 - 2 * self.cx_px / W, 0.0],
            [0.0, 2 * self.fy_px / H, -(1.0 - 2 * self.cy_px / H), 0.0],
            [0.0, 0.0, -(f + n) / (f - n), -2 * f * n / (f - n)],
            [0.0, 0.0, -1.0, 0.0],
        ])

    def as_dict(self) -> dict:
        d = asdict(self)
        d.update(hfov_deg=round(self.hfov_deg, 3), vfov_deg=round(self.vfov_deg, 3))
        return d


# OpenCV camera axes -> OpenGL eye axes (flip Y and Z).
R_GL_CV = np.diag([1.0, -1.0, -1.0])
