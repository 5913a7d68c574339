"""The paper's metrics (SPEC section 7), per frame and per sequence.

  dt    = ||t_hat - t||                          position error, m
  dt_pct = 100 dt / ||t||                        range-normalised position error, %
  dq    = 2 acos(|(q_hat^-1 (x) q)_scalar|)      attitude error, deg
Requirements: dt_pct <= 5 % and dq <= 5 deg; compliance = share of frames meeting each.
"""

from __future__ import annotations

import numpy as np

POS_REQ_PCT = 5.0
ATT_REQ_DEG = 5.0


def position_error_m(T_hat_m: np.ndarray, T_m: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.asarray(T_hat_m, float) - np.asarray(T_m, float), axis=-1)


def position_error_pct(T_hat_m: np.ndarray, T_m: np.ndarray) -> np.ndarray:
    return 100.0 * position_error_m(T_hat_m, T_m) / np.linalg.norm(np.asarray(T_m, float), axis=-1)


def attitude_error_deg(q_hat: np.ndarray, q: np.ndarray) -> np.ndarray:
    """For unit quaternions the scalar part of q_hat^-1 (x) q is their dot product; |.| makes q
    and -q (the same rotation) agree."""
    q_hat = np.asarray(q_hat, float)
    q = np.asarray(q, float)
    q_hat = q_hat / np.linalg.norm(q_hat, axis=-1, keepdims=True)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    d = np.clip(np.abs(np.sum(q_hat * q, axis=-1)), 0.0, 1.0)
    return np.degrees(2.0 * np.arccos(d))


def summarize(T_hat_m, q_hat, T_m, q) -> dict:
    dt = position_error_m(T_hat_m, T_m)
    dt_pct = position_error_pct(T_hat_m, T_m)
    dq = attitude_error_deg(q_hat, q)
    return {
        "frames": int(len(dt)),
        "dt_mean_m": float(dt.mean()), "dt_median_m": float(np.median(dt)),
        "dt_mean_pct": float(dt_pct.mean()), "dt_median_pct": float(np.median(dt_pct)),
        "dq_mean_deg": float(dq.mean()), "dq_median_deg": float(np.median(dq)),
        "compliance_pos_pct": float(100.0 * np.mean(dt_pct <= POS_REQ_PCT)),
        "compliance_att_pct": float(100.0 * np.mean(dq <= ATT_REQ_DEG)),
    }


def score(summary: dict) -> float:
    """One number for model selection on validation: mean range-normalised position error (as a
    fraction) plus mean attitude error (rad), in the spirit of the SPEED score."""
    return summary["dt_mean_pct"] / 100.0 + np.radians(summary["dq_mean_deg"])


def mean_pose(T_m: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The trivial baseline's prediction: the mean position, and the mean attitude as the
    principal eigenvector of sum(q q^T) (sign-invariant average of quaternions)."""
    T_m = np.asarray(T_m, float)
    q = np.asarray(q, float)
    M = q.T @ q
    w, v = np.linalg.eigh(M)
    q_mean = v[:, -1]
    if q_mean[0] < 0:
        q_mean = -q_mean
    return T_m.mean(0), q_mean / np.linalg.norm(q_mean)


TABLE_COLUMNS = [
    ("frames", "frames", "{:d}"),
    ("dt_mean_m", "dt mean (m)", "{:.3f}"), ("dt_median_m", "dt median (m)", "{:.3f}"),
    ("dt_mean_pct", "dt mean (%)", "{:.2f}"), ("dt_median_pct", "dt median (%)", "{:.2f}"),
    ("dq_mean_deg", "dq mean (deg)", "{:.2f}"), ("dq_median_deg", "dq median (deg)", "{:.2f}"),
    ("compliance_pos_pct", "pos <= 5 % (%)", "{:.2f}"), ("compliance_att_pct", "att <= 5 deg (%)", "{:.2f}"),
]


def markdown_table(rows: list[tuple[str, str, dict]]) -> str:
    """rows: (sequence, model, summary) -> a markdown table as in the paper's per-sequence tables."""
    head = "| sequence | model | " + " | ".join(c[1] for c in TABLE_COLUMNS) + " |"
    sep = "| --- | --- | " + " | ".join("---:" for _ in TABLE_COLUMNS) + " |"
    lines = [head, sep]
    for seq, model, s in rows:
        lines.append(f"| {seq} | {model} | " + " | ".join(fmt.format(s[k]) for k, _, fmt in TABLE_COLUMNS) + " |")
    return "\n".join(lines)
