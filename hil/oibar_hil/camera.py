"""The renderer's side of the camera model: OpenGL's clip matrix and axes for
oibar.geometry.camera.PinholeCamera (the one pinhole model of the project; its docstring gives
the pixel conventions and the numbers).
"""

from __future__ import annotations

import numpy as np

from oibar.geometry.camera import PinholeCamera


def gl_projection(cam: PinholeCamera) -> np.ndarray:
    """OpenGL clip matrix (row-major, column vectors) for GL eye coordinates (x right, y up,
    z backwards) that reproduces ``cam.project`` (pixel-corner convention) after the image is
    read back and flipped so row 0 is the top."""
    W, H, n, f = cam.width_px, cam.height_px, cam.near_m, cam.far_m
    return np.array(
        [
            [2 * cam.fx_px / W, 0.0, 1.0 - 2 * cam.cx_px / W, 0.0],
            [0.0, 2 * cam.fy_px / H, -(1.0 - 2 * cam.cy_px / H), 0.0],
            [0.0, 0.0, -(f + n) / (f - n), -2 * f * n / (f - n)],
            [0.0, 0.0, -1.0, 0.0],
        ]
    )


# OpenCV camera axes -> OpenGL eye axes (flip Y and Z).
R_GL_CV = np.diag([1.0, -1.0, -1.0])
