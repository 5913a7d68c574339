"""Rotations: elementary matrices, rotation vectors, quaternions and angles.

Conventions (the whole project's, docs/synthetic.md):
  - quaternions are scalar-first ``(w, x, y, z)``, Hamilton, unit, and returned with ``w >= 0``
    (one sign per rotation);
  - ``R_a_b`` maps vectors expressed in frame b into frame a: ``v_a = R_a_b @ v_b``;
  - angles are radians unless the name ends in ``_deg``.

Functions take one rotation (``(3, 3)``, ``(4,)``, ``(3,)``) unless their docstring says they take
a stack (``(..., 3, 3)``). For one rotation the arithmetic is exactly that of the functions these
replaced (host ``oibar.rotations``), so recorded numbers do not move.
"""

from __future__ import annotations

import numpy as np

from ._types import ArrayLike, FloatArray


def rot_x(angle_rad: float) -> FloatArray:
    """Rotation by ``angle_rad`` about +X (right-handed)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> FloatArray:
    """Rotation by ``angle_rad`` about +Y (right-handed)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> FloatArray:
    """Rotation by ``angle_rad`` about +Z (right-handed)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def skew(v: ArrayLike) -> FloatArray:
    """The cross-product matrix: ``skew(v) @ u == cross(v, u)``."""
    x, y, z = np.asarray(v, dtype=float)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rotvec_to_matrix(rotvec_rad: ArrayLike) -> FloatArray:
    """Rodrigues: the rotation of ``|v|`` radians about ``v/|v|`` (one rotation vector, (3,))."""
    v = np.asarray(rotvec_rad, dtype=float)
    angle = float(np.linalg.norm(v))
    if angle < 1e-15:
        return np.eye(3)
    k = v / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    out: FloatArray = np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)
    return out


def _matrix_to_quat_one(R: FloatArray) -> FloatArray:
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    # Shepperd's method: pick the largest diagonal term to stay well conditioned.
    if tr > max(R[0, 0], R[1, 1], R[2, 2]):
        s = 2.0 * np.sqrt(1.0 + tr)
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array([(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s])
    elif R[1, 1] >= R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array([(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array([(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    out: FloatArray = -q if q[0] < 0 else q
    return out


def matrix_to_quat(R: ArrayLike) -> FloatArray:
    """Rotation matrix ``(3, 3)`` or stack ``(..., 3, 3)`` -> unit quaternion(s) ``(..., 4)``
    ``(w, x, y, z)`` with ``w >= 0`` (Shepperd's method, well conditioned for every rotation)."""
    M = np.asarray(R, dtype=float)
    if M.ndim == 2:
        return _matrix_to_quat_one(M)
    flat = M.reshape(-1, 3, 3)
    q = np.stack([_matrix_to_quat_one(m) for m in flat]) if len(flat) else np.zeros((0, 4))
    return q.reshape(M.shape[:-2] + (4,))


def quat_to_matrix(q: ArrayLike) -> FloatArray:
    """Quaternion ``(4,)`` or stack ``(..., 4)`` ``(w, x, y, z)`` -> rotation matrix ``(..., 3, 3)``.
    The quaternion is normalised first; ``q`` and ``-q`` give the same matrix."""
    a = np.asarray(q, dtype=float)
    if a.ndim == 1:
        w, x, y, z = a / np.linalg.norm(q)
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    w, x, y, z = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_rotvec(R: ArrayLike) -> FloatArray:
    """Inverse of :func:`rotvec_to_matrix` (angle in 0..pi), via the quaternion for stability near
    0. Takes ``(3, 3)`` -> ``(3,)`` or a stack ``(..., 3, 3)`` -> ``(..., 3)``; radians."""
    M = np.asarray(R, dtype=float)
    if M.ndim > 2:
        flat = M.reshape(-1, 3, 3)
        v = np.stack([matrix_to_rotvec(m) for m in flat]) if len(flat) else np.zeros((0, 3))
        return v.reshape(M.shape[:-2] + (3,))
    q = matrix_to_quat(M)
    s = float(np.linalg.norm(q[1:]))
    if s < 1e-12:
        return np.zeros(3)
    angle = 2.0 * np.arctan2(s, q[0])
    out: FloatArray = q[1:] / s * angle
    return out


def rotation_angle_deg(R: ArrayLike) -> float:
    """Angle of one rotation matrix ``(3, 3)``, degrees (0..180)."""
    c = (np.trace(np.asarray(R, dtype=float)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def rotation_angles_deg(R: ArrayLike) -> FloatArray:
    """Angles of a stack of rotation matrices ``(..., 3, 3)`` -> ``(...)``, degrees (0..180)."""
    c = (np.trace(np.asarray(R, dtype=float), axis1=-2, axis2=-1) - 1.0) / 2.0
    out: FloatArray = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
    return out


def angle_between_quats_deg(q_a: ArrayLike, q_b: ArrayLike) -> float:
    """Angle of the rotation taking attitude ``q_b`` to ``q_a`` (one pair), degrees (0..180),
    computed through the matrices (``angle(R_a R_b^T)``)."""
    return rotation_angle_deg(quat_to_matrix(np.asarray(q_a)) @ quat_to_matrix(np.asarray(q_b)).T)


def mean_quat(q: ArrayLike) -> FloatArray:
    """The mean attitude of unit quaternions ``(N, 4)`` (w, x, y, z): the principal eigenvector of
    sum(q q^T), blind to each one's sign (q and -q are one attitude), returned with ``w >= 0``."""
    qa = np.asarray(q, dtype=float)
    _, v = np.linalg.eigh(qa.T @ qa)
    out: FloatArray = v[:, -1] / np.linalg.norm(v[:, -1])
    return -out if out[0] < 0 else out
