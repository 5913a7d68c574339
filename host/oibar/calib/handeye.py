"""Closed-form start: OpenCV's robot-world/hand-eye calibration, and the motion checks it needs.

The chain, per calibration pose i (all transforms rigid, `T_a_b` maps b into a):

    T_cam_pattern[i] @ T_pattern_tmarkers = T_cam_housing @ T_housing_tmarkers[i]
        A[i]                X                     Z                 B[i]

A comes from PnP on the pattern, B = inv(T_mocap_housing) @ T_mocap_tmarkers from the mocap
(the two rigid bodies: camera housing and target markers). X and Z are the static unknowns.
This is OpenCV's A X = Z B with world = pattern, base = target markers, gripper = housing.
Using the *relative* mocap pose B lets both bodies move during the recording.
"""

from __future__ import annotations

import cv2
import numpy as np

from oibar.geometry.rotations import rotation_angles_deg as rotation_angle_deg
from oibar.geometry.transforms import inv_T, make_T

from .errors import CalibError

MIN_POSES = 10
MIN_ROTATION_SPREAD_DEG = 10.0  # largest rotation between two poses
MIN_AXIS_SPREAD = 0.15  # RMS angle about the 2nd axis / about the main axis


def motion_spread(T_cam_pattern: np.ndarray) -> dict:
    """How well the relative rotations between poses excite the hand-eye problem.

    The rotation part is only observable from rotations about at least two non-parallel axes
    (one axis leaves the translation along it and the rotation about it free). We take the
    rotation vectors between every pose and a spread of reference poses and look at the
    eigenvalues of their scatter: `axis_spread` = sqrt(l2 / l1)."""
    R = T_cam_pattern[:, :3, :3]
    n = len(R)
    refs = np.unique(np.linspace(0, n - 1, min(n, 12)).astype(int))
    vecs = []
    for r in refs:
        rel = np.einsum("ji,njk->nik", R[r], R)  # R_r^T R_j
        ang = np.radians(rotation_angle_deg(rel))
        w = np.stack(
            [rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], 1
        )
        s = np.linalg.norm(w, axis=1)
        ok = s > 1e-9
        vecs.append(w[ok] / s[ok, None] * ang[ok, None])
    v = np.concatenate(vecs) if vecs else np.zeros((0, 3))
    max_deg = float(np.degrees(np.linalg.norm(v, axis=1).max())) if len(v) else 0.0
    ev = np.sort(np.linalg.eigvalsh(v.T @ v / max(len(v), 1)))[::-1] if len(v) else np.zeros(3)
    spread = float(np.sqrt(max(ev[1], 0.0) / ev[0])) if ev[0] > 0 else 0.0
    return {"max_rotation_deg": max_deg, "axis_spread": spread}


def check_motion(T_cam_pattern: np.ndarray, min_poses: int = MIN_POSES) -> dict:
    n = len(T_cam_pattern)
    if n < min_poses:
        raise CalibError(
            f"too few calibration poses: {n} usable, need at least {min_poses} "
            "(50-200 well-spread poses for sub-0.1-deg results)"
        )
    spread = motion_spread(T_cam_pattern)
    if spread["max_rotation_deg"] < MIN_ROTATION_SPREAD_DEG:
        raise CalibError(
            f"degenerate motion: the camera rotates at most {spread['max_rotation_deg']:.1f} deg relative "
            f"to the pattern (pure translation?); tilt and roll it by 20-40 deg about several axes"
        )
    if spread["axis_spread"] < MIN_AXIS_SPREAD:
        raise CalibError(
            f"degenerate motion: the rotations are (almost) all about one axis (spread "
            f"{spread['axis_spread']:.2f} < {MIN_AXIS_SPREAD}); rotate about at least two different axes"
        )
    return spread


def rotation_residual_rms(A, B, X, Z) -> float:
    """RMS over poses of the rotation (deg) between A X and Z B: picks the better closed form."""
    D = np.einsum("nij,jk->nik", A, X)
    E = np.einsum("ij,njk->nik", Z, B)
    dR = np.einsum("nji,njk->nik", D[:, :3, :3], E[:, :3, :3])
    return float(np.sqrt(np.mean(rotation_angle_deg(dR) ** 2)))


def closed_form(
    T_cam_pattern: np.ndarray, T_housing_tmarkers: np.ndarray, fast: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """(T_pattern_tmarkers, T_cam_housing) from cv2.calibrateRobotWorldHandEye; of the two
    methods, the one with the smaller rotation residual (`fast`: Shah's method only)."""
    A, B = T_cam_pattern, T_housing_tmarkers
    args = ([a[:3, :3] for a in A], [a[:3, 3] for a in A], [b[:3, :3] for b in B], [b[:3, 3] for b in B])
    best = None
    methods = (cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH, cv2.CALIB_ROBOT_WORLD_HAND_EYE_LI)
    for method in methods[:1] if fast else methods:
        try:
            R_bw, t_bw, R_gc, t_gc = cv2.calibrateRobotWorldHandEye(*args, method=method)
        except cv2.error:
            continue
        X = make_T(R_bw, np.ravel(t_bw))
        Z = make_T(R_gc, np.ravel(t_gc))
        if not (np.all(np.isfinite(X)) and np.all(np.isfinite(Z))):
            continue
        # Re-orthonormalise: the closed forms can return slightly non-orthogonal matrices.
        for T in (X, Z):
            U, _, Vt = np.linalg.svd(T[:3, :3])
            T[:3, :3] = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
        rms = rotation_residual_rms(A, B, X, Z)
        if best is None or rms < best[0]:
            best = (rms, X, Z)
    if best is None:
        raise CalibError("OpenCV's hand-eye calibration found no solution (degenerate motion?)")
    return best[1], best[2]


def relative_mocap(T_mocap_housing: np.ndarray, T_mocap_tmarkers: np.ndarray) -> np.ndarray:
    return np.einsum("nij,njk->nik", inv_T(T_mocap_housing), T_mocap_tmarkers)
