"""The paper's pose-error metrics (SPEC section 7), per frame and per sequence.

  dt     = ||t_hat - t||                          position error, m
  dt_pct = 100 dt / ||t||                        range-normalised position error, %
  dq     = 2 acos(|(q_hat^-1 (x) q)_scalar|)     attitude error, deg
Requirements: dt_pct <= 5 % and dq <= 5 deg; compliance = the share of frames meeting each.
Positions are T_cam_target (camera frame, m); attitudes q_cam_target (w, x, y, z).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ._types import ArrayLike, FloatArray
from .rotations import mean_quat

POS_REQ_PCT = 5.0
"""Position requirement: range-normalised error, percent."""
ATT_REQ_DEG = 5.0
"""Attitude requirement, degrees."""


def position_error_m(T_hat_m: ArrayLike, T_m: ArrayLike) -> FloatArray:
    """dt: Euclidean distance between estimated and true positions (..., 3) -> (...), m."""
    out: FloatArray = np.linalg.norm(np.asarray(T_hat_m, float) - np.asarray(T_m, float), axis=-1)
    return out


def position_error_pct(T_hat_m: ArrayLike, T_m: ArrayLike) -> FloatArray:
    """dt_pct: dt divided by the true range, percent."""
    out: FloatArray = 100.0 * position_error_m(T_hat_m, T_m) / np.linalg.norm(np.asarray(T_m, float), axis=-1)
    return out


def attitude_error_deg(q_hat: ArrayLike, q: ArrayLike) -> FloatArray:
    """dq, degrees. For unit quaternions the scalar part of q_hat^-1 (x) q is their dot product;
    |.| makes q and -q (the same rotation) agree."""
    a = np.asarray(q_hat, float)
    b = np.asarray(q, float)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    d = np.clip(np.abs(np.sum(a * b, axis=-1)), 0.0, 1.0)
    out: FloatArray = np.degrees(2.0 * np.arccos(d))
    return out


def summarize(T_hat_m: ArrayLike, q_hat: ArrayLike, T_m: ArrayLike, q: ArrayLike) -> dict[str, Any]:
    """Means, medians and compliance over a sequence of frames (the paper's table columns)."""
    dt = position_error_m(T_hat_m, T_m)
    dt_pct = position_error_pct(T_hat_m, T_m)
    dq = attitude_error_deg(q_hat, q)
    return {
        "frames": int(len(dt)),
        "dt_mean_m": float(dt.mean()),
        "dt_median_m": float(np.median(dt)),
        "dt_mean_pct": float(dt_pct.mean()),
        "dt_median_pct": float(np.median(dt_pct)),
        "dq_mean_deg": float(dq.mean()),
        "dq_median_deg": float(np.median(dq)),
        "compliance_pos_pct": float(100.0 * np.mean(dt_pct <= POS_REQ_PCT)),
        "compliance_att_pct": float(100.0 * np.mean(dq <= ATT_REQ_DEG)),
    }


def score(summary: dict[str, Any]) -> float:
    """One number for model selection on validation: mean range-normalised position error (as a
    fraction) plus mean attitude error (rad), in the spirit of the SPEED score."""
    return float(summary["dt_mean_pct"] / 100.0 + np.radians(summary["dq_mean_deg"]))


def mean_pose(T_m: ArrayLike, q: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """The trivial baseline's prediction: the mean position (m), and the mean attitude
    (rotations.mean_quat: sign-invariant average of quaternions)."""
    mean_T: FloatArray = np.asarray(T_m, float).mean(0)
    return mean_T, mean_quat(q)
