"""Reprojection overlay for visual checks: the target model (the berthing fixture's outline,
oibar.geometry.fixture.fixture_wireframe_t) and its axes drawn from a camera-to-target pose, and
optionally the pattern corners predicted through the calibrated mocap chain (circles) next to
the detected ones (crosses). Hidden edges are drawn too: it is a wireframe.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from oibar.geometry.fixture import fixture_wireframe_t

from .pnp import Intrinsics, project

AXIS_LENGTH_M = 0.15


@lru_cache(maxsize=1)
def model_edges_target() -> np.ndarray:
    """(E, 2, 3) segments in F_t, metres: the fixture's outline (rim, drogue, pin guides,
    couplings, connector)."""
    return fixture_wireframe_t()


def _pt(uv) -> tuple[int, int]:
    # cv2 drawing with 4 fractional bits: sub-pixel positions, OpenCV pixel convention.
    return int(round(uv[0] * 16)), int(round(uv[1] * 16))


def draw_model(
    image_bgr: np.ndarray, T_cam_target: np.ndarray, intr: Intrinsics, color=(0, 255, 0)
) -> np.ndarray:
    img = image_bgr.copy()
    segs = model_edges_target()
    uv = project(segs.reshape(-1, 3), T_cam_target, intr).reshape(-1, 2, 2)
    for a, b in uv:
        if np.all(np.isfinite(a)) and np.all(np.isfinite(b)):
            cv2.line(img, _pt(a), _pt(b), color, 1, cv2.LINE_AA, shift=4)
    axes = project(np.vstack([np.zeros(3), np.eye(3) * AXIS_LENGTH_M]), T_cam_target, intr)
    if np.all(np.isfinite(axes)):
        for tip, col in zip(
            axes[1:], ((0, 0, 255), (0, 255, 0), (255, 96, 0)), strict=True
        ):  # X red, Y green, Z blue
            cv2.line(img, _pt(axes[0]), _pt(tip), col, 2, cv2.LINE_AA, shift=4)
    return img


def draw_corners(
    image_bgr: np.ndarray, uv_detected: np.ndarray | None, uv_predicted: np.ndarray | None
) -> np.ndarray:
    img = image_bgr.copy()
    if uv_detected is not None:
        for p in uv_detected:
            cv2.drawMarker(img, (int(round(p[0])), int(round(p[1]))), (255, 255, 0), cv2.MARKER_CROSS, 7, 1)
    if uv_predicted is not None:
        for p in uv_predicted:
            if np.all(np.isfinite(p)):
                cv2.circle(img, _pt(p), 4 * 16, (0, 0, 255), 1, cv2.LINE_AA, shift=4)
    return img


def caption(image_bgr: np.ndarray, text: str) -> np.ndarray:
    img = image_bgr.copy()
    cv2.putText(img, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return img
