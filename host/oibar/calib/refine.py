"""Least-squares refinement of the two static transforms (and of the time offset).

Model (handeye.py): A[i] X = Z B[i]. The per-pose residual is the transform between the mocap
measurement B[i] and its prediction inv(Z) A[i] X, as (translation m, rotation vector rad) in
the target-marker frame. Every term is whitened by its first-order covariance, built from:

- mocap noise on each rigid body, in the body frame: T_meas = T @ Exp(d), d ~ N(0, diag(s_t^2,
  s_r^2)) per axis. The housing's rotation noise moves the target-marker origin by
  (lever arm x angle), i.e. several mm at a metre: this is why plain unweighted residuals do
  poorly and why the covariance is propagated with the adjoint;
- the PnP covariance of A[i] from its Jacobian (pnp.py).

So the cost is a Mahalanobis distance (chi-square with 6 dof per pose when the noise figures
are right): `chi2_per_dof` near 1 says the stated noise matches the data.
The time offset enters through B[i](offset). With the mocap fitted locally around each frame
(timing.smooth) B is a smooth function of the offset, so the offset is a 13th parameter of the
same least squares, fitted jointly with X and Z (its derivative by finite differences of B),
and its variance comes out of the same covariance. Without smoothing (interpolation between
samples, piecewise linear in the offset) pass an `offset_window_s` of None and a fixed offset.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.stats import chi2

from oibar.geometry.transforms import T_from_vec, adjoint, inv_T, log_T

from .errors import CalibError

OUTLIER_P = 0.999


@dataclass
class MocapNoise:
    sigma_t_m: float = 0.2e-3
    sigma_r_rad: float = np.radians(0.5)

    def cov(self) -> np.ndarray:
        return np.diag([self.sigma_t_m**2] * 3 + [self.sigma_r_rad**2] * 3)


@dataclass
class RefineResult:
    X: np.ndarray  # T_pattern_tmarkers
    Z: np.ndarray  # T_cam_housing
    offset_s: float
    cov_X: np.ndarray  # 6x6, right perturbation of X (m, rad)
    cov_Z: np.ndarray
    sigma_offset_s: float
    inliers: np.ndarray  # bool mask over the poses given
    d2: np.ndarray  # Mahalanobis distance^2 of each pose
    residuals: np.ndarray  # (N, 6) unwhitened residual (m, rad) of each pose
    chi2_per_dof: float
    offset_profile: list = field(default_factory=list)


def _whitening(
    A_cov: np.ndarray,
    B: np.ndarray,
    X: np.ndarray,
    noise_h: MocapNoise,
    noise_m: MocapNoise,
    k_h: np.ndarray,
    k_m: np.ndarray,
) -> np.ndarray:
    """Per-pose W with W.T @ W = inverse covariance of the residual log(inv(B_hat) @ B);
    k_h, k_m scale the mocap variances for interpolation (timing.interpolate)."""
    Ad_Xi = adjoint(inv_T(X))
    S_h, S_m = noise_h.cov(), noise_m.cov()
    W = np.empty((len(B), 6, 6))
    for i in range(len(B)):
        Ad_Bi = adjoint(inv_T(B[i]))
        S = Ad_Xi @ A_cov[i] @ Ad_Xi.T + k_h[i] * (Ad_Bi @ S_h @ Ad_Bi.T) + k_m[i] * S_m
        W[i] = np.linalg.cholesky(np.linalg.inv(S)).T
    return W


def _residuals(A_inv, B, X, Z):
    """log(inv(inv(Z) A X) @ B) = log(inv(X) inv(A) Z B), shape (N, 6)."""
    return log_T(inv_T(X) @ A_inv @ (Z @ B))


def _solve(A_inv, B, W, X0, Z0):
    def fun(x):
        Z = Z0 @ T_from_vec(x[:6])
        X = X0 @ T_from_vec(x[6:])
        return np.einsum("nij,nj->ni", W, _residuals(A_inv, B, X, Z)).ravel()

    sol = least_squares(fun, np.zeros(12), method="lm", x_scale="jac")
    return X0 @ T_from_vec(sol.x[6:]), Z0 @ T_from_vec(sol.x[:6]), float(2 * sol.cost), sol.jac


def _solve_joint(A_inv, B_of, W, X0, Z0, off0_s, off_lo_s, off_hi_s):
    """X, Z and the offset together: B_of(offset) gives the mocap poses (smooth in the offset
    when the mocap is fitted locally, timing.smooth). The offset is a parameter in ms, bounded
    to [off_lo_s, off_hi_s]; its derivative is taken by finite differences of the smooth B."""

    def fun(x):
        Z = Z0 @ T_from_vec(x[:6])
        X = X0 @ T_from_vec(x[6:12])
        return np.einsum("nij,nj->ni", W, _residuals(A_inv, B_of(off0_s + 1e-3 * x[12]), X, Z)).ravel()

    sol = least_squares(fun, np.zeros(13), method="lm", x_scale="jac", diff_step=1e-7)
    off = off0_s + 1e-3 * float(sol.x[12])
    if not off_lo_s <= off <= off_hi_s:
        raise CalibError(
            f"the time offset left its search window ({off * 1e3:.1f} ms, window "
            f"{off_lo_s * 1e3:.1f} to {off_hi_s * 1e3:.1f} ms); check the time columns or pass --offset-s"
        )
    J = sol.jac.copy()
    J[:, 12] *= 1e3  # d residual / d offset in s
    return (
        X0 @ T_from_vec(sol.x[6:12]),
        Z0 @ T_from_vec(sol.x[:6]),
        off0_s + 1e-3 * float(sol.x[12]),
        float(2 * sol.cost),
        J,
    )


def refine(
    A: np.ndarray,
    A_cov: np.ndarray,
    B_at: Callable[[float], tuple],
    X0: np.ndarray,
    Z0: np.ndarray,
    offset0_s: float,
    noise_housing: MocapNoise,
    noise_tmarkers: MocapNoise,
    offset_window_s: float | None = None,
    min_poses: int = 10,
) -> RefineResult:
    """Refine X, Z (and the offset within offset0_s +- offset_window_s when given).
    `B_at(offset_s)` returns T_housing_tmarkers for every pose, a validity mask and the
    variance factors of both bodies (timing.relative_at(..., with_variance=True)); for the
    joint fit of the offset it must be smooth in the offset (timing.smooth)."""
    idx = _covered_poses(B_at, len(A), offset0_s, offset_window_s, min_poses)
    poses = _Poses(A, A_cov, B_at, idx, noise_housing, noise_tmarkers)
    fit = _Fit(poses, X0, Z0, offset0_s, offset_window_s)
    inl = fit.reject_outliers(min_poses)
    W = poses.W(fit.offset, fit.X)
    cost_val, J = fit.solve(W, inl, joint=True)
    return _result(fit, W, inl, cost_val, J, len(A))


def _covered_poses(
    B_at: Callable[[float], tuple], n: int, offset0_s: float, offset_window_s: float | None, min_poses: int
) -> np.ndarray:
    """Indices of the poses with mocap coverage at every offset the fit may try."""
    # Keep the same poses for every trial offset, or the costs would not be comparable.
    keep = np.ones(n, bool)
    probes = (
        [offset0_s]
        if not offset_window_s
        else np.linspace(offset0_s - offset_window_s, offset0_s + offset_window_s, 5)
    )
    for off in probes:
        keep &= B_at(off)[1]
    if keep.sum() < min_poses:
        raise CalibError(
            f"too few poses with mocap coverage: {int(keep.sum())} (need {min_poses}); "
            "missing frames or mocap gaps?"
        )
    return np.flatnonzero(keep)


class _Poses:
    """The poses kept (``idx``): A inverted, and the mocap B with its weights at a trial offset,
    cached (``B_at`` interpolates every body at every call)."""

    def __init__(self, A, A_cov, B_at, idx, noise_housing: MocapNoise, noise_tmarkers: MocapNoise):
        self.idx = idx
        self.A_inv, self.A_cov = inv_T(A[idx]), A_cov[idx]
        self._B_at = B_at
        self._noise = (noise_housing, noise_tmarkers)
        self._cache: dict = {}

    def _full(self, off):
        key = float(off)
        if key not in self._cache:
            if len(self._cache) > 64:
                self._cache.clear()
            B, _, k_h, k_m = self._B_at(key)
            self._cache[key] = (B[self.idx], k_h[self.idx], k_m[self.idx])
        return self._cache[key]

    def B(self, off):
        return self._full(off)[0]

    def W(self, off, X):
        # Weights follow the offset (variance factors), with X fixed per pass.
        B, k_h, k_m = self._full(off)
        return _whitening(self.A_cov, B, X, *self._noise, k_h, k_m)


class _Fit:
    """X, Z and the offset as the passes refine them, and the joint fit's cost profile."""

    def __init__(self, poses: _Poses, X0, Z0, offset0_s: float, offset_window_s: float | None):
        self.poses = poses
        self.X, self.Z, self.offset = X0, Z0, offset0_s
        self.window_s = offset_window_s
        self.lo_s = offset0_s - (offset_window_s or 0.0)
        self.hi_s = offset0_s + (offset_window_s or 0.0)
        self.profile: list = []

    def solve(self, W, mask, joint):
        p = self.poses
        if self.window_s and joint:
            self.X, self.Z, self.offset, cost, J = _solve_joint(
                p.A_inv[mask],
                lambda o: p.B(o)[mask],
                W[mask],
                self.X,
                self.Z,
                self.offset,
                self.lo_s,
                self.hi_s,
            )
            self.profile.append((round(self.offset, 7), cost))
        else:
            self.X, self.Z, cost, J = _solve(p.A_inv[mask], p.B(self.offset)[mask], W[mask], self.X, self.Z)
        return cost, J

    def reject_outliers(self, min_poses: int) -> np.ndarray:
        """Three passes; the inlier mask over the poses kept."""
        p = self.poses
        inl = np.ones(len(p.idx), bool)
        # Pass 0 gets X, Z close with weights from the closed form (offset fixed); passes 1 and 2
        # fit the offset too, with the weights re-made from the better X, and reject outliers.
        for it in range(3):
            W = p.W(self.offset, self.X)
            self.solve(W, inl, joint=it > 0)
            wr = np.einsum("nij,nj->ni", W, _residuals(p.A_inv, p.B(self.offset), self.X, self.Z))
            d2 = np.sum(wr**2, axis=1)
            if it == 0:
                continue
            # Outliers: far beyond chi-square(6), scaled by the median so that a wrong noise figure
            # does not reject everything.
            scale = max(1.0, float(np.median(d2[inl])) / chi2.median(6))
            inl = d2 <= scale * chi2.ppf(OUTLIER_P, 6)
            if inl.sum() < min_poses:
                raise CalibError(
                    f"only {int(inl.sum())} poses agree with the model; check the body names, "
                    "the pattern file and the time columns"
                )
        return inl


def _result(fit: _Fit, W, inl, cost_val: float, J, n: int) -> RefineResult:
    """The final fit's covariances (from its Jacobian) and per-pose figures over all ``n`` poses."""
    p, idx = fit.poses, fit.poses.idx
    n_par = J.shape[1]
    dof = max(6 * int(inl.sum()) - n_par, 1)
    chi2_dof = cost_val / dof
    cov = np.linalg.pinv(J.T @ J) * max(1.0, chi2_dof)  # inflate when the data are noisier than stated
    sigma_offset = float(np.sqrt(cov[12, 12])) if n_par == 13 else float("nan")
    r = _residuals(p.A_inv, p.B(fit.offset), fit.X, fit.Z)
    wr = np.einsum("nij,nj->ni", W, r)
    inliers = np.zeros(n, bool)
    inliers[idx[inl]] = True
    d2_all = np.full(n, np.nan)
    d2_all[idx] = np.sum(wr**2, axis=1)
    res_all = np.full((n, 6), np.nan)
    res_all[idx] = r
    return RefineResult(
        X=fit.X,
        Z=fit.Z,
        offset_s=fit.offset,
        cov_X=cov[6:12, 6:12],
        cov_Z=cov[:6, :6],
        sigma_offset_s=sigma_offset,
        inliers=inliers,
        d2=d2_all,
        residuals=res_all,
        chi2_per_dof=float(chi2_dof),
        offset_profile=fit.profile,
    )
