"""Frames of the docking geometry, and the conversion between what the camera sees and what
guidance steers on.

Camera frame C (OpenCV: +x right, +y down, +z forward). The network reports the berthing
fixture frame F_t in C: ``T_cam_target`` (m) and ``R_cam_target`` (p_C = R_cam_target p_t +
T_cam_target). F_t: origin at the centre of the berthing plane (the drogue's lip is flush with
it), +z_t into the port, so when the vehicles are aligned F_t is parallel to C.

Docking frame D (what guidance and the HIL world use): origin at the drogue entrance (= F_t's
origin), +z_D out of the drogue towards the approaching service vehicle, x_D = x_t, so
``R_t_D = diag(1, -1, -1)``. Guidance steers the probe tip ``r_D_m``; its z is the range to
contact (negative once the probe is inside the drogue). ``att_rad`` is the service vehicle's
attitude error: a rotation vector in the camera/body frame from the aligned attitude.

Service vehicle frame F_s: origin at the end-effector shaft plane centre, axes parallel to C.
The probe tip is ``probe_tip_s_m`` ahead of the shaft plane, and the camera sits at
``p_s_cam_m`` (above the probe axis and behind the shaft plane: it keeps the fixture in view down
to soft-dock). These are assumptions shared with the synthetic world (oibar_hil.relpose) and the
rig's camera; a real vehicle puts its own numbers in :class:`DockingGeometry`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from oibar.rotations import matrix_to_rotvec, rotvec_to_matrix

R_T_D = np.diag([1.0, -1.0, -1.0])          # F_t axes <-> D axes (its own inverse)
R_D_CAM_ALIGNED = R_T_D                      # the camera's axes in D when aligned (C parallel to F_t)


@dataclass(frozen=True)
class DockingGeometry:
    probe_tip_s_m: float = 0.27                                   # probe tip ahead of the shaft plane
    p_s_cam_m: tuple = (0.0, -0.12, -0.30)                        # camera in F_s
    R_s_cam: np.ndarray = field(default_factory=lambda: np.eye(3))  # camera axes in F_s

    def shaft_distance_m(self, range_m: float) -> float:
        """Shaft-plane to berthing-plane distance (the paper's d) for a probe-tip range."""
        return range_m + self.probe_tip_s_m


GEOMETRY = DockingGeometry()


@dataclass
class DockingState:
    """Guidance's view of the relative pose, all in D."""

    r_D_m: np.ndarray           # probe tip position
    att_rad: np.ndarray         # attitude error, rotation vector in the body frame
    R_D_cam: np.ndarray

    @property
    def range_m(self) -> float:
        return float(self.r_D_m[2])

    @property
    def lateral_m(self) -> float:
        return float(np.hypot(self.r_D_m[0], self.r_D_m[1]))

    @property
    def misalignment_deg(self) -> float:
        """Combined yaw/pitch: angle between the boresight and -z_D (roll excluded)."""
        return float(np.degrees(np.arccos(np.clip(-self.R_D_cam[2, 2], -1.0, 1.0))))


def camera_pose_from_docking(r_D_m: np.ndarray, att_rad: np.ndarray,
                             geom: DockingGeometry = GEOMETRY) -> tuple[np.ndarray, np.ndarray]:
    """(probe tip in D, attitude error) -> (T_cam_target_m, R_cam_target): what the camera sees."""
    R_D_s = R_D_CAM_ALIGNED @ rotvec_to_matrix(att_rad)          # body axes = camera axes
    R_t_s = R_T_D @ R_D_s
    p_t_tip = R_T_D @ np.asarray(r_D_m, dtype=float)
    p_t_s = p_t_tip - R_t_s @ np.array([0.0, 0.0, geom.probe_tip_s_m])
    p_t_cam = p_t_s + R_t_s @ np.asarray(geom.p_s_cam_m, dtype=float)
    R_t_cam = R_t_s @ geom.R_s_cam
    R_cam_t = R_t_cam.T
    return -R_cam_t @ p_t_cam, R_cam_t


def docking_from_camera_pose(T_cam_target_m: np.ndarray, R_cam_target: np.ndarray,
                             geom: DockingGeometry = GEOMETRY) -> DockingState:
    """Inverse of camera_pose_from_docking: the network's estimate -> guidance's state."""
    R_t_cam = np.asarray(R_cam_target, dtype=float).T
    p_t_cam = -R_t_cam @ np.asarray(T_cam_target_m, dtype=float)
    R_t_s = R_t_cam @ geom.R_s_cam.T
    p_t_s = p_t_cam - R_t_s @ np.asarray(geom.p_s_cam_m, dtype=float)
    p_t_tip = p_t_s + R_t_s @ np.array([0.0, 0.0, geom.probe_tip_s_m])
    R_D_s = R_T_D @ R_t_s
    att = matrix_to_rotvec(R_D_CAM_ALIGNED.T @ R_D_s)
    return DockingState(r_D_m=R_T_D @ p_t_tip, att_rad=att, R_D_cam=R_D_s @ geom.R_s_cam)
