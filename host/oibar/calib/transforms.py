"""Rigid transforms as 4x4 matrices, and the small-perturbation algebra the refinement needs.

Naming: `T_a_b` maps points in frame b into frame a (p_a = T_a_b @ p_b); quaternions are
(w, x, y, z), scalar first, w >= 0 (the dataset's convention, docs/synthetic.md).

Perturbations are applied on the right, in the body frame: T_noisy = T @ Exp(delta) with
delta = (rho_m (3), phi_rad (3)). To first order Exp(delta) = [I + [phi]x, rho], which is all the
noise model needs; we use (translation, rotation vector) of a transform as its "log".
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def make_T(R: np.ndarray, t_m: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t_m
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of one (4,4) or a stack (N,4,4) of rigid transforms."""
    T = np.asarray(T, dtype=float)
    R = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = R
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def quat_wxyz_to_R(q_wxyz) -> np.ndarray:
    q = np.asarray(q_wxyz, dtype=float)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]]).as_matrix()


def R_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    q = Rotation.from_matrix(R).as_quat()[..., [3, 0, 1, 2]]
    return np.where(q[..., :1] < 0, -q, q)   # one sign per rotation, as in the dataset


def T_from_pose(t_m, q_wxyz) -> np.ndarray:
    t = np.asarray(t_m, dtype=float)
    T = np.zeros(t.shape[:-1] + (4, 4))
    T[..., :3, :3] = quat_wxyz_to_R(q_wxyz)
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def T_from_vec(x: np.ndarray) -> np.ndarray:
    """6-vector (t_m (3), rotation vector rad (3)) -> (4,4)."""
    return make_T(Rotation.from_rotvec(x[3:6]).as_matrix(), x[0:3])


def vec_from_T(T: np.ndarray) -> np.ndarray:
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])


def log_T(T: np.ndarray) -> np.ndarray:
    """(..., 6) = (translation m, rotation vector rad): first-order log of near-identity transforms."""
    T = np.asarray(T, dtype=float)
    return np.concatenate([T[..., :3, 3], Rotation.from_matrix(T[..., :3, :3]).as_rotvec()], axis=-1)


def skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint for delta = (rho, phi): T @ Exp(delta) = Exp(adjoint(T) @ delta) @ T."""
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[:3, 3:] = skew(t) @ R
    Ad[3:, 3:] = R
    return Ad


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error deg) between two transforms."""
    dR = T_est[:3, :3].T @ T_true[:3, :3]
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])), float(rotation_angle_deg(dR))
