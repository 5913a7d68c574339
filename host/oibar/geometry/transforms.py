"""Rigid transforms as 4x4 homogeneous matrices, and the small-perturbation algebra the
calibration refinement needs.

Naming: ``T_a_b`` maps points in frame b into frame a (``p_a = T_a_b @ p_b``); translations are
metres; quaternions ``(w, x, y, z)``, scalar first, ``w >= 0`` (oibar.geometry.rotations).

Perturbations are applied on the right, in the body frame: ``T_noisy = T @ Exp(delta)`` with
``delta = (rho_m (3), phi_rad (3))``. To first order ``Exp(delta) = [I + [phi]x, rho]``; the
(translation, rotation vector) pair of a transform is used as its "log".
"""

from __future__ import annotations

import numpy as np

from ._types import ArrayLike, FloatArray
from .rotations import matrix_to_rotvec, quat_to_matrix, rotation_angle_deg, rotvec_to_matrix, skew


def make_T(R: ArrayLike, t_m: ArrayLike) -> FloatArray:
    """(3, 3) rotation and (3,) translation in metres -> (4, 4)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t_m
    return T


def inv_T(T: ArrayLike) -> FloatArray:
    """Inverse of one (4, 4) or a stack (N, 4, 4) of rigid transforms."""
    M = np.asarray(T, dtype=float)
    R = np.swapaxes(M[..., :3, :3], -1, -2)
    out = np.zeros_like(M)
    out[..., :3, :3] = R
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R, M[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def T_from_pose(t_m: ArrayLike, q_wxyz: ArrayLike) -> FloatArray:
    """Translation(s) ``(..., 3)`` m and quaternion(s) ``(..., 4)`` -> transform(s) ``(..., 4, 4)``."""
    t = np.asarray(t_m, dtype=float)
    T = np.zeros(t.shape[:-1] + (4, 4))
    T[..., :3, :3] = quat_to_matrix(q_wxyz)
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def T_from_vec(x: ArrayLike) -> FloatArray:
    """6-vector (translation m (3), rotation vector rad (3)) -> (4, 4)."""
    v = np.asarray(x, dtype=float)
    return make_T(rotvec_to_matrix(v[3:6]), v[0:3])


def log_T(T: ArrayLike) -> FloatArray:
    """``(..., 6)`` = (translation m, rotation vector rad) of one or a stack of transforms: the
    first-order log of near-identity transforms, and the inverse of :func:`T_from_vec`."""
    M = np.asarray(T, dtype=float)
    return np.concatenate([M[..., :3, 3], matrix_to_rotvec(M[..., :3, :3])], axis=-1)


def adjoint(T: ArrayLike) -> FloatArray:
    """6x6 adjoint for ``delta = (rho, phi)``: ``T @ Exp(delta) = Exp(adjoint(T) @ delta) @ T``."""
    M = np.asarray(T, dtype=float)
    R, t = M[:3, :3], M[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[:3, 3:] = skew(t) @ R
    Ad[3:, 3:] = R
    return Ad


def transform_points(points_b: ArrayLike, R_a_b: ArrayLike, t_a_b_m: ArrayLike) -> FloatArray:
    """Points ``(N, 3)`` in frame b -> frame a: ``p_a = R_a_b p_b + t_a_b`` (metres). With
    ``(R_cam_target, T_cam_target)`` this puts fixture points into the camera frame."""
    out: FloatArray = np.asarray(points_b, float) @ np.asarray(R_a_b, float).T + np.asarray(t_a_b_m, float)
    return out


def pose_error(T_est: ArrayLike, T_true: ArrayLike) -> tuple[float, float]:
    """(translation error m, rotation error deg) between two (4, 4) transforms."""
    A, B = np.asarray(T_est, dtype=float), np.asarray(T_true, dtype=float)
    dR = A[:3, :3].T @ B[:3, :3]
    return float(np.linalg.norm(A[:3, 3] - B[:3, 3])), rotation_angle_deg(dR)
