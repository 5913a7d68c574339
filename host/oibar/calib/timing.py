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

from oibar.geometry.rotations import rotation_angles_deg as rotation_angle_deg

from .errors import CalibError


@dataclass
class Track:
    """One rigid body's poses in the mocap frame, sorted by time (occluded samples removed)."""

    name: str
    t_s: np.ndarray  # (N,)
    T_mocap_body: np.ndarray  # (N, 4, 4)

    @property
    def rotations(self) -> Rotation:
        """The sample rotations as one scipy Rotation (made once; the local fits index it)."""
        rot = self.__dict__.get("_rotations")
        if rot is None or len(rot) != len(self.t_s):
            rot = Rotation.from_matrix(self.T_mocap_body[:, :3, :3])
            self.__dict__["_rotations"] = rot
        return rot

    @property
    def period_s(self) -> float:
        return float(np.median(np.diff(self.t_s))) if len(self.t_s) > 1 else float("nan")


def interpolate(
    track: Track, t_query_s: np.ndarray, max_gap_s: float | None = None, with_variance: bool = False
):
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
        return out, valid, (1 - alpha) ** 2 + alpha**2
    return out, valid


SMOOTH_HALF_WIDTH_S = 0.10  # local-quadratic mocap fit: +-100 ms, 19 samples with weight at 100 Hz
SMOOTH_DEGREE = 2


def smooth(
    track: Track,
    t_query_s: np.ndarray,
    half_width_s: float = SMOOTH_HALF_WIDTH_S,
    max_gap_s: float | None = None,
    with_variance: bool = False,
    ref_t_s: np.ndarray | None = None,
    degree: int = SMOOTH_DEGREE,
):
    """Poses at `t_query_s` from a local polynomial fit (degree 2) of the mocap samples within
    +-`half_width_s`: position in the mocap frame, rotation in the tangent space of a reference
    sample (R = R_ref Exp(phi), phi(t) fitted), weights (1 - (dt/h)^2)^2.

    Why not interpolate between the two neighbouring samples: the interpolated pose carries the
    noise of one or two samples, and how much depends on where the query falls between them
    (variance factor 0.5 halfway, 1 on a sample). When the frame clock ticks (nearly) in step
    with the mocap's, every frame sits at about the same fraction of a sample period, and a
    shift of the trial offset changes the noise of all poses together: the offset fit is pulled
    towards shifts that make the noise look smaller, and the estimate of X and Z follows the
    offset error. The local fit (+-0.1 s at 100 Hz: 19 weighted samples) has a variance factor
    of ~0.14 that hardly depends on where the query falls, and it is a smooth function of the
    query time, so the offset can be fitted jointly with X and Z. The motion must be smooth over
    the window (a quadratic in time over +-0.1 s: true for the documented calibration motion,
    whose fastest component has a period of ~3 s; the fit is within 0.02 mm / 0.001 deg of it).

    `ref_t_s` picks the reference sample of each query (default: the query itself); keeping it
    fixed while the query times shift keeps the result smooth in the shift. Returns the poses,
    a validity mask (inside the track, no gap longer than `max_gap_s` around the query, and
    enough samples in the window) and, with `with_variance`, the variance factor sum(h_i^2)
    of each fitted pose relative to one sample."""
    t = track.t_s
    tq = np.atleast_1d(np.asarray(t_query_s, dtype=float))
    n = len(tq)
    if max_gap_s is None:
        max_gap_s = 2.5 * track.period_s
    h = float(half_width_s)
    lo = np.searchsorted(t, tq - h, side="right")
    hi = np.searchsorted(t, tq + h, side="left")
    m = max(int((hi - lo).max()) if n else 1, 1)
    idx = lo[:, None] + np.arange(m)[None, :]
    inwin = idx < hi[:, None]
    idx = np.clip(idx, 0, len(t) - 1)
    u = (t[idx] - tq[:, None]) / h
    w = np.where(inwin, np.clip(1.0 - u**2, 0.0, None) ** 2, 0.0)
    V = np.stack([u**d for d in range(degree + 1)], axis=2)  # (n, m, d+1)
    VtW = np.swapaxes(V * w[..., None], 1, 2)  # (n, d+1, m)
    G = VtW @ V
    enough = np.sum(w > 1e-6, axis=1) >= degree + 2
    G[~enough] = np.eye(degree + 1)
    # Row 0 of inv(G) @ V^T W: the weights that give the fitted value at the query.
    hat = np.linalg.solve(G, VtW)[:, 0, :]  # (n, m)
    # Reference sample: nearest to ref_t_s.
    tr = tq if ref_t_s is None else np.broadcast_to(np.asarray(ref_t_s, float), tq.shape)
    j1 = np.clip(np.searchsorted(t, tr), 1, len(t) - 1)
    iref = np.where(np.abs(t[j1 - 1] - tr) <= np.abs(t[j1] - tr), j1 - 1, j1)
    rot = track.rotations
    R_ref = rot[iref]
    phi = (rot[np.repeat(iref, m)].inv() * rot[idx.ravel()]).as_rotvec().reshape(n, m, 3)
    out = np.zeros((n, 4, 4))
    out[:, :3, :3] = (R_ref * Rotation.from_rotvec(np.einsum("nm,nmk->nk", hat, phi))).as_matrix()
    out[:, :3, 3] = np.einsum("nm,nmk->nk", hat, track.T_mocap_body[idx, :3, 3])
    out[:, 3, 3] = 1.0
    # Validity as for interpolation (inside the track, no long gap at the query) plus a window
    # that holds enough samples on both sides.
    i1 = np.clip(np.searchsorted(t, tq, side="right"), 1, len(t) - 1)
    gap = t[i1] - t[i1 - 1]
    both = np.any((u < 0) & (w > 1e-6), axis=1) & np.any((u > 0) & (w > 1e-6), axis=1)
    valid = (tq >= t[0]) & (tq <= t[-1]) & (gap <= max_gap_s + 1e-12) & enough & both
    if with_variance:
        return out, valid, np.sum(hat**2, axis=1)
    return out, valid


def relative_at(
    housing: Track,
    tmarkers: Track,
    t_query_s: np.ndarray,
    max_gap_s: float | None = None,
    with_variance: bool = False,
    smooth_half_width_s: float | None = None,
    ref_t_s: np.ndarray | None = None,
):
    """T_housing_tmarkers at the query times and where both bodies were seen (and, with
    `with_variance`, the variance factors of the housing and of the target poses).
    `smooth_half_width_s`: local polynomial fit of the mocap (`smooth`) instead of
    interpolation between neighbouring samples."""
    from .handeye import relative_mocap

    if smooth_half_width_s:
        H, vh, kh = smooth(housing, t_query_s, smooth_half_width_s, max_gap_s, True, ref_t_s)
        M, vm, km = smooth(tmarkers, t_query_s, smooth_half_width_s, max_gap_s, True, ref_t_s)
    else:
        H, vh, kh = interpolate(housing, t_query_s, max_gap_s, with_variance=True)
        M, vm, km = interpolate(tmarkers, t_query_s, max_gap_s, with_variance=True)
    if with_variance:
        return relative_mocap(H, M), vh & vm, kh, km
    return relative_mocap(H, M), vh & vm


def _speeds(R: np.ndarray, t_s: np.ndarray, lag: int) -> np.ndarray:
    rel = np.einsum("nji,njk->nik", R[:-lag], R[lag:])
    return np.radians(rotation_angle_deg(rel)) / (t_s[lag:] - t_s[:-lag])


def offset_by_speed(
    frame_t_s: np.ndarray,
    R_cam_pattern: np.ndarray,
    housing: Track,
    tmarkers: Track,
    search_s: float,
    step_s: float | None = None,
    baseline_s: float = 0.2,
) -> float:
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
        raise CalibError(
            "the mocap does not cover the frames for any time offset in the search window; "
            "check the time columns or widen --offset-search-s"
        )
    j = int(np.argmin(costs))
    if 0 < j < len(costs) - 1 and np.all(np.isfinite(costs[j - 1 : j + 2])):
        # Parabola through the best grid point and its neighbours.
        c0, c1, c2 = costs[j - 1 : j + 2]
        den = c0 - 2 * c1 + c2
        if den > 0:
            return float(offsets[j] + 0.5 * step_s * (c0 - c2) / den)
    return float(offsets[j])


def offset_by_handeye(
    frame_t_s: np.ndarray,
    T_cam_pattern: np.ndarray,
    housing: Track,
    tmarkers: Track,
    center_s: float,
    half_width_s: float = 0.1,
    step_s: float = 0.01,
    smooth_half_width_s: float | None = None,
) -> float:
    """Second stage: the offset whose mocap poses fit the closed-form hand-eye solution best
    (smallest rotation residual). Much sharper than the speed match, whose noise is large
    against the small change of speed over a few tens of milliseconds."""
    from .handeye import closed_form, rotation_residual_rms

    offsets = np.arange(center_s - half_width_s, center_s + half_width_s + step_s / 2, step_s)
    costs = np.full(len(offsets), np.inf)
    for j, off in enumerate(offsets):
        B, valid = relative_at(housing, tmarkers, frame_t_s + off, smooth_half_width_s=smooth_half_width_s)
        if valid.sum() < 10:
            continue
        X, Z = closed_form(T_cam_pattern[valid], B[valid], fast=True)
        costs[j] = rotation_residual_rms(T_cam_pattern[valid], B[valid], X, Z)
    if not np.isfinite(costs).any():
        return center_s
    j = int(np.argmin(costs))
    if 0 < j < len(costs) - 1 and np.all(np.isfinite(costs[j - 1 : j + 2])):
        c0, c1, c2 = costs[j - 1 : j + 2]
        den = c0 - 2 * c1 + c2
        if den > 0:
            return float(offsets[j] + 0.5 * step_s * (c0 - c2) / den)
    return float(offsets[j])
