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
The time offset enters through B[i](offset); it is found by a bounded 1-D search over the
profile cost (solve X, Z for each trial offset), since slerp between mocap samples makes the
cost only piecewise smooth in the offset.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.optimize import least_squares, minimize_scalar
from scipy.stats import chi2

from .errors import CalibError
from .transforms import T_from_vec, adjoint, inv_T, log_T

OUTLIER_P = 0.999


@dataclass
class MocapNoise:
    sigma_t_m: float = 0.2e-3
    sigma_r_rad: float = np.radians(0.5)

    def cov(self) -> np.ndarray:
        return np.diag([self.sigma_t_m ** 2] * 3 + [self.sigma_r_rad ** 2] * 3)


@dataclass
class RefineResult:
    X: np.ndarray               # T_pattern_tmarkers
    Z: np.ndarray               # T_cam_housing
    offset_s: float
    cov_X: np.ndarray           # 6x6, right perturbation of X (m, rad)
    cov_Z: np.ndarray
    sigma_offset_s: float
    inliers: np.ndarray         # bool mask over the poses given
    d2: np.ndarray              # Mahalanobis distance^2 of each pose
    residuals: np.ndarray       # (N, 6) unwhitened residual (m, rad) of each pose
    chi2_per_dof: float
    offset_profile: list = field(default_factory=list)


def _whitening(A_cov: np.ndarray, B: np.ndarray, X: np.ndarray, noise_h: MocapNoise, noise_m: MocapNoise,
               k_h: np.ndarray, k_m: np.ndarray) -> np.ndarray:
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


def refine(A: np.ndarray, A_cov: np.ndarray, B_at: Callable[[float], tuple],
           X0: np.ndarray, Z0: np.ndarray, offset0_s: float, noise_housing: MocapNoise,
           noise_tmarkers: MocapNoise, offset_window_s: float | None = None,
           min_poses: int = 10) -> RefineResult:
    """Refine X, Z (and the offset within offset0_s +- offset_window_s when given).
    `B_at(offset_s)` returns T_housing_tmarkers for every pose, a validity mask and the
    interpolation variance factors of both bodies (timing.relative_at(..., with_variance=True))."""
    n = len(A)
    # Keep the same poses for every trial offset, or the costs would not be comparable.
    keep = np.ones(n, bool)
    probes = [offset0_s] if not offset_window_s else np.linspace(offset0_s - offset_window_s,
                                                                 offset0_s + offset_window_s, 5)
    for off in probes:
        keep &= B_at(off)[1]
    if keep.sum() < min_poses:
        raise CalibError(f"too few poses with mocap coverage: {int(keep.sum())} (need {min_poses}); "
                         "missing frames or mocap gaps?")
    idx = np.flatnonzero(keep)
    A_inv, Acov_k = inv_T(A[idx]), A_cov[idx]
    B_cache: dict = {}

    def B_k(off):
        key = round(float(off), 9)
        if key not in B_cache:
            B, _, k_h, k_m = B_at(off)
            B_cache[key] = (B[idx], k_h[idx], k_m[idx])
        return B_cache[key][0]

    def W_k(off, X):
        # Weights follow the trial offset (interpolation variance), with X fixed per pass.
        B_k(off)
        _, k_h, k_m = B_cache[round(float(off), 9)]
        return _whitening(Acov_k, B_k(off), X, noise_housing, noise_tmarkers, k_h, k_m)

    X, Z, offset = X0, Z0, offset0_s
    inl = np.ones(len(idx), bool)
    profile: dict = {}

    def search_offset(lo, hi, n_grid):
        def cost(off):
            key = round(float(off), 7)
            if key not in profile:
                W = W_k(off, X)
                profile[key] = _solve(A_inv[inl], B_k(off)[inl], W[inl], X, Z)[2]
            return profile[key]

        grid = np.linspace(lo, hi, n_grid)
        j = int(np.argmin([cost(o) for o in grid]))
        a, b = grid[max(j - 1, 0)], grid[min(j + 1, n_grid - 1)]
        return float(minimize_scalar(cost, bounds=(a, b), method="bounded", options={"xatol": 2e-5}).x)

    # Pass 0 gets X, Z close with weights from the closed form; pass 1 searches the offset
    # with the weights re-made from the better X and rejects outliers; pass 2 settles.
    for it in range(3):
        if offset_window_s and it == 1:
            offset = search_offset(offset - offset_window_s, offset + offset_window_s, 11)
        elif offset_window_s and it == 2:
            step = 2 * offset_window_s / 10
            offset = search_offset(offset - step, offset + step, 3)
        W = W_k(offset, X)
        X, Z, _, _ = _solve(A_inv[inl], B_k(offset)[inl], W[inl], X, Z)
        wr = np.einsum("nij,nj->ni", W, _residuals(A_inv, B_k(offset), X, Z))
        d2 = np.sum(wr ** 2, axis=1)
        if it == 0:
            continue
        # Outliers: far beyond chi-square(6), scaled by the median so that a wrong noise figure
        # does not reject everything.
        scale = max(1.0, float(np.median(d2[inl])) / chi2.median(6))
        inl = d2 <= scale * chi2.ppf(OUTLIER_P, 6)
        if inl.sum() < min_poses:
            raise CalibError(f"only {int(inl.sum())} poses agree with the model; check the body names, "
                             "the pattern file and the time columns")

    X, Z, cost_val, J = _solve(A_inv[inl], B_k(offset)[inl], W[inl], X, Z)
    dof = max(6 * int(inl.sum()) - 12 - (1 if offset_window_s else 0), 1)
    chi2_dof = cost_val / dof
    cov = np.linalg.pinv(J.T @ J) * max(1.0, chi2_dof)   # inflate when the data are noisier than stated
    sigma_offset = float("nan")
    if offset_window_s:
        # Curvature of the profile cost around the optimum: var(offset) = 2 / cost''.
        h = 2e-3
        c = [_solve(A_inv[inl], B_k(offset + k * h)[inl], W_k(offset + k * h, X)[inl], X, Z)[2]
             for k in (-1, 0, 1)]
        curv = (c[0] - 2 * c[1] + c[2]) / h ** 2
        if curv > 0:
            sigma_offset = float(np.sqrt(2.0 / curv * max(1.0, chi2_dof)))
    r = _residuals(A_inv, B_k(offset), X, Z)
    wr = np.einsum("nij,nj->ni", W, r)
    inliers = np.zeros(n, bool)
    inliers[idx[inl]] = True
    d2_all = np.full(n, np.nan)
    d2_all[idx] = np.sum(wr ** 2, axis=1)
    res_all = np.full((n, 6), np.nan)
    res_all[idx] = r
    return RefineResult(X=X, Z=Z, offset_s=offset, cov_X=cov[6:, 6:], cov_Z=cov[:6, :6],
                        sigma_offset_s=sigma_offset, inliers=inliers, d2=d2_all, residuals=res_all,
                        chi2_per_dof=float(chi2_dof), offset_profile=sorted(profile.items()))
