"""Time alignment between the mocap clock and the camera's frame timestamps.

Convention: the mocap pose that belongs to frame k is the one at mocap time
`time_s[k] + offset_s` (offset_s > 0: the mocap clock runs ahead of the frame clock).

The coarse estimate needs no calibration: the angle of the rotation between two instants is
the same whether it is seen by the camera (relative to the pattern) or by the mocap (housing
relative to target markers), because the two differ by fixed rotations on either side. So the
angular speed of the camera from PnP and of the housing from the mocap must match once shifted
by the right offset. The fine estimate is done by the refinement (refine.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .errors import CalibError
from .transforms import rotation_angle_deg


@dataclass
class Track:
    """One rigid body's poses in the mocap frame, sorted by time (occluded samples removed)."""
    name: str
    t_s: np.ndarray             # (N,)
    T_mocap_body: np.ndarray    # (N, 4, 4)

    @property
    def period_s(self) -> float:
        return float(np.median(np.diff(self.t_s))) if len(self.t_s) > 1 else float("nan")


def interpolate(track: Track, t_query_s: np.ndarray, max_gap_s: float | None = None,
                with_variance: bool = False):
    """Poses at `t_query_s` (linear in position, slerp in rotation) and a validity mask: a query
    is invalid outside the track or inside a gap longer than `max_gap_s` (default: 2.5 sample
    periods, i.e. one dropped sample is bridged, an occlusion is not)."""
    t = track.t_s
    tq = np.asarray(t_query_s, dtype=float)
    if max_gap_s is None:
        max_gap_s = 2.5 * track.period_s
    i1 = np.clip(np.searchsorted(t, tq, side="right"), 1, len(t) - 1)
    i0 = i1 - 1
    dt = t[i1] - t[i0]
    valid = (tq >= t[0]) & (tq <= t[-1]) & (dt <= max_gap_s + 1e-12)
    alpha = np.clip((tq - t[i0]) / np.where(dt > 0, dt, 1.0), 0.0, 1.0)
    T0, T1 = track.T_mocap_body[i0], track.T_mocap_body[i1]
    R0 = Rotation.from_matrix(T0[:, :3, :3])
    rel = (R0.inv() * Rotation.from_matrix(T1[:, :3, :3])).as_rotvec()
    R = (R0 * Rotation.from_rotvec(rel * alpha[:, None])).as_matrix()
    out = np.zeros((len(tq), 4, 4))
    out[:, :3, :3] = R
    out[:, :3, 3] = (1 - alpha)[:, None] * T0[:, :3, 3] + alpha[:, None] * T1[:, :3, 3]
    out[:, 3, 3] = 1.0
    if with_variance:
        return out, valid, (1 - alpha) ** 2 + alpha ** 2
    return out, valid


def relative_at(housing: Track, tmarkers: Track, t_query_s: np.ndarray,
                max_gap_s: float | None = None, with_variance: bool = False):
    """T_housing_tmarkers at the query times and where both bodies were seen (and, with
    `with_variance`, the interpolation variance factors of the housing and of the target)."""
    from .handeye import relative_mocap

    H, vh, kh = interpolate(housing, t_query_s, max_gap_s, with_variance=True)
    M, vm, km = interpolate(tmarkers, t_query_s, max_gap_s, with_variance=True)
    if with_variance:
        return relative_mocap(H, M), vh & vm, kh, km
    return relative_mocap(H, M), vh & vm


def _speeds(R: np.ndarray, t_s: np.ndarray, lag: int) -> np.ndarray:
    rel = np.einsum("nji,njk->nik", R[:-lag], R[lag:])
    return np.radians(rotation_angle_deg(rel)) / (t_s[lag:] - t_s[:-lag])


def offset_by_speed(frame_t_s: np.ndarray, R_cam_pattern: np.ndarray, housing: Track, tmarkers: Track,
                  search_s: float, step_s: float | None = None, baseline_s: float = 0.2) -> float:
    """Offset (s) within +-search_s that best matches the angular speeds of the two sensors.

    Speeds are taken over a baseline of >= `baseline_s` so that mocap noise (fractions of a
    degree per sample) stays small against the motion."""
    if len(frame_t_s) < 3:
        raise CalibError("too few frames to estimate the time offset")
    period = float(np.median(np.diff(frame_t_s)))
    lag = max(1, int(round(baseline_s / period)))
    lag = min(lag, len(frame_t_s) - 1)
    w_cam = _speeds(R_cam_pattern, frame_t_s, lag)
    step_s = step_s or max(min(housing.period_s / 2, period / 10), 1e-4)
    offsets = np.arange(-search_s, search_s + step_s / 2, step_s)
    costs = np.full(len(offsets), np.inf)
    for j, off in enumerate(offsets):
        B, valid = relative_at(housing, tmarkers, frame_t_s + off)
        ok = valid[lag:] & valid[:-lag]
        if ok.sum() < max(5, 0.5 * len(ok)):
            continue
        w_moc = _speeds(B[:, :3, :3], frame_t_s, lag)
        costs[j] = np.mean((w_moc[ok] - w_cam[ok]) ** 2)
    if not np.isfinite(costs).any():
        raise CalibError("the mocap does not cover the frames for any time offset in the search window; "
                         "check the time columns or widen --offset-search-s")
    j = int(np.argmin(costs))
    if 0 < j < len(costs) - 1 and np.all(np.isfinite(costs[j - 1:j + 2])):
        # Parabola through the best grid point and its neighbours.
        c0, c1, c2 = costs[j - 1:j + 2]
        den = c0 - 2 * c1 + c2
        if den > 0:
            return float(offsets[j] + 0.5 * step_s * (c0 - c2) / den)
    return float(offsets[j])


def offset_by_handeye(frame_t_s: np.ndarray, T_cam_pattern: np.ndarray, housing: Track, tmarkers: Track,
                      center_s: float, half_width_s: float = 0.1, step_s: float = 0.005) -> float:
    """Second stage: the offset whose mocap poses fit the closed-form hand-eye solution best
    (smallest rotation residual). Much sharper than the speed match, whose noise is large
    against the small change of speed over a few tens of milliseconds."""
    from .handeye import closed_form, rotation_residual_rms

    offsets = np.arange(center_s - half_width_s, center_s + half_width_s + step_s / 2, step_s)
    costs = np.full(len(offsets), np.inf)
    for j, off in enumerate(offsets):
        B, valid = relative_at(housing, tmarkers, frame_t_s + off)
        if valid.sum() < 10:
            continue
        X, Z = closed_form(T_cam_pattern[valid], B[valid], fast=True)
        costs[j] = rotation_residual_rms(T_cam_pattern[valid], B[valid], X, Z)
    if not np.isfinite(costs).any():
        return center_s
    j = int(np.argmin(costs))
    if 0 < j < len(costs) - 1 and np.all(np.isfinite(costs[j - 1:j + 2])):
        c0, c1, c2 = costs[j - 1:j + 2]
        den = c0 - 2 * c1 + c2
        if den > 0:
            return float(offsets[j] + 0.5 * step_s * (c0 - c2) / den)
    return float(offsets[j])
