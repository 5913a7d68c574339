"""Relative-pose composition: chaser trajectory + port + camera mount -> camera pose in LVLH
and the label T_cam_target / q_cam_target.

Label convention (used by the CNN and the navigation):
  T_cam_target  position of the berthing-fixture frame origin F_t expressed in the camera
                frame (OpenCV axes: +X right, +Y down, +Z forward), metres;
  q_cam_target  unit quaternion (w, x, y, z), w >= 0, of R_cam_target, the rotation that maps
                vectors in F_t to the camera frame: p_cam = R_cam_target @ p_t + T_cam_target.
When the chaser is aligned, R_cam_target = I (q = 1, 0, 0, 0) and T_cam_target = (0, 0.12, d+0.30)
for a shaft-plane distance d, because of the camera mount
(oibar.geometry.docking.MOUNT).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oibar.geometry.docking import MOUNT, CameraMount
from oibar.geometry.rotations import matrix_to_quat

from .ports import Port
from .trajectory import Trajectory

# The camera mount (oibar.geometry.docking.MOUNT: 0.12 m above the probe axis, 0.30 m behind the
# shaft plane, boresight parallel to the docking axis) is the one navigation and the rig use.


@dataclass
class CameraPoses:
    T_cam_target: np.ndarray  # (N, 3) m
    R_cam_target: np.ndarray  # (N, 3, 3)
    q_cam_target: np.ndarray  # (N, 4) w, x, y, z
    R_lvlh_cam: np.ndarray  # (N, 3, 3)
    p_lvlh_cam: np.ndarray  # (N, 3) m

    @property
    def range_m(self) -> np.ndarray:
        return np.linalg.norm(self.T_cam_target, axis=1)


def camera_poses(traj: Trajectory, port: Port, mount: CameraMount = MOUNT) -> CameraPoses:
    R_s_cam = np.asarray(mount.R_s_cam, dtype=float)
    p_s_cam = np.asarray(mount.p_s_cam_m, dtype=float)
    R_t_cam = traj.R_t_s @ R_s_cam  # (N,3,3)
    p_t_cam = traj.p_t_s + np.einsum("nij,j->ni", traj.R_t_s, p_s_cam)
    R_cam_t = np.transpose(R_t_cam, (0, 2, 1))
    T_cam_t = -np.einsum("nij,nj->ni", R_cam_t, p_t_cam)
    q = np.stack([matrix_to_quat(R) for R in R_cam_t])
    R_lvlh_cam = np.einsum("ij,njk->nik", port.R_lvlh_t, R_t_cam)
    p_lvlh_cam = port.p_lvlh_t[None, :] + p_t_cam @ port.R_lvlh_t.T
    return CameraPoses(T_cam_t, R_cam_t, q, R_lvlh_cam, p_lvlh_cam)
