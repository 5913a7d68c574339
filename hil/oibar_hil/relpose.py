"""Relative-pose composition: chaser trajectory + port + camera mount -> camera pose in LVLH
and the label T_cam_target / q_cam_target.

Label convention (used by the CNN and the navigation):
  T_cam_target  position of the berthing-fixture frame origin F_t expressed in the camera
                frame (OpenCV axes: +X right, +Y down, +Z forward), metres;
  q_cam_target  unit quaternion (w, x, y, z), w >= 0, of R_cam_target, the rotation that maps
                vectors in F_t to the camera frame: p_cam = R_cam_target @ p_t + T_cam_target.
When the chaser is aligned, R_cam_target = I (q = 1, 0, 0, 0) and T_cam_target = (0, 0.12, d+0.30)
for a shaft-plane distance d, because of the camera mount below.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oibar.nav.frames import GEOMETRY

from .ports import Port
from .rotations import matrix_to_quat
from .trajectory import Trajectory


@dataclass(frozen=True)
class CameraMount:
    """Camera pose in the chaser docking frame F_s (assumption): 0.12 m above the probe axis
    (-Y_s) and 0.30 m behind the shaft plane, boresight parallel to the docking axis, so the
    fixture stays in view down to soft-dock. The numbers come from oibar.nav.frames.GEOMETRY,
    the one source shared with guidance and the HIL rig's rendered camera (plain tuples here so
    the dataset manifest stays JSON)."""

    p_s_cam_m: tuple = tuple(float(x) for x in GEOMETRY.p_s_cam_m)
    R_s_cam: tuple = tuple(tuple(float(x) for x in row) for row in np.asarray(GEOMETRY.R_s_cam))


MOUNT = CameraMount()


@dataclass
class CameraPoses:
    T_cam_target: np.ndarray   # (N, 3) m
    R_cam_target: np.ndarray   # (N, 3, 3)
    q_cam_target: np.ndarray   # (N, 4) w, x, y, z
    R_lvlh_cam: np.ndarray     # (N, 3, 3)
    p_lvlh_cam: np.ndarray     # (N, 3) m

    @property
    def range_m(self) -> np.ndarray:
        return np.linalg.norm(self.T_cam_target, axis=1)


def camera_poses(traj: Trajectory, port: Port, mount: CameraMount = MOUNT) -> CameraPoses:
    R_s_cam = np.asarray(mount.R_s_cam, dtype=float)
    p_s_cam = np.asarray(mount.p_s_cam_m, dtype=float)
    R_t_cam = traj.R_t_s @ R_s_cam                                   # (N,3,3)
    p_t_cam = traj.p_t_s + np.einsum("nij,j->ni", traj.R_t_s, p_s_cam)
    R_cam_t = np.transpose(R_t_cam, (0, 2, 1))
    T_cam_t = -np.einsum("nij,nj->ni", R_cam_t, p_t_cam)
    q = np.stack([matrix_to_quat(R) for R in R_cam_t])
    R_lvlh_cam = np.einsum("ij,njk->nik", port.R_lvlh_t, R_t_cam)
    p_lvlh_cam = port.p_lvlh_t[None, :] + p_t_cam @ port.R_lvlh_t.T
    return CameraPoses(T_cam_t, R_cam_t, q, R_lvlh_cam, p_lvlh_cam)


def target_points_in_camera(points_t: np.ndarray, T_cam_target: np.ndarray, R_cam_target: np.ndarray) -> np.ndarray:
    return np.asarray(points_t, float) @ np.asarray(R_cam_target, float).T + np.asarray(T_cam_target, float)
