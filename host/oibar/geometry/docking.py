"""Frames of the docking geometry, the camera mount, and the conversion between what the camera
sees and what guidance steers on.

Camera frame C (OpenCV: +x right, +y down, +z forward). The pose estimator reports the berthing
fixture frame F_t in C: ``T_cam_target`` (m) and ``R_cam_target`` (``p_C = R_cam_target p_t +
T_cam_target``). F_t: origin at the centre of the berthing plane (the drogue's lip is flush with
it), +z_t into the port, so when the vehicles are aligned F_t is parallel to C.

Docking frame D (what guidance and the HIL world use): origin at the drogue entrance (= F_t's
origin), +z_D out of the drogue towards the approaching service vehicle, x_D = x_t, so
``R_t_D = diag(1, -1, -1)``. Guidance steers the probe tip ``r_D_m``; its z is the range to
contact (negative once the probe is inside the drogue). ``att_rad`` is the service vehicle's
attitude error: a rotation vector in the camera/body frame from the aligned attitude.

Service vehicle frame F_s: origin at the end-effector shaft plane centre, axes parallel to C.
The probe tip is ``probe_tip_s_m`` ahead of the shaft plane, and the camera sits at
``p_s_cam_m`` (above the probe axis and behind the shaft plane: it keeps the fixture in view down
to soft-dock). These are assumptions shared by navigation, the synthetic world and the rig's
camera; a real vehicle puts its own numbers in :class:`DockingGeometry`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._types import ArrayLike, FloatArray
from .rotations import matrix_to_rotvec, rotvec_to_matrix

R_T_D: FloatArray = np.diag([1.0, -1.0, -1.0])
"""F_t axes <-> D axes (its own inverse)."""
R_D_CAM_ALIGNED: FloatArray = R_T_D
"""The camera's axes in D when the vehicles are aligned (C parallel to F_t)."""


def _eye3() -> FloatArray:
    return np.eye(3)


@dataclass(frozen=True)
class DockingGeometry:
    """The service vehicle's docking geometry, in F_s: the probe tip ``probe_tip_s_m`` (m) ahead
    of the shaft plane along +z_s, the camera's position ``p_s_cam_m`` (m) and its axes
    ``R_s_cam`` (maps C vectors into F_s)."""

    probe_tip_s_m: float = 0.27
    p_s_cam_m: tuple[float, float, float] = (0.0, -0.12, -0.30)
    R_s_cam: FloatArray = field(default_factory=_eye3)

    def shaft_distance_m(self, range_m: float) -> float:
        """Shaft-plane to berthing-plane distance (the paper's d) for a probe-tip range, m."""
        return range_m + self.probe_tip_s_m


GEOMETRY = DockingGeometry()


@dataclass(frozen=True)
class CameraMount:
    """The camera's pose in F_s as plain tuples (so that the data set's manifest stays JSON):
    position ``p_s_cam_m`` (m) and axes ``R_s_cam`` (rows). Built from a :class:`DockingGeometry`,
    which holds the numbers."""

    p_s_cam_m: tuple[float, ...]
    R_s_cam: tuple[tuple[float, ...], ...]

    @classmethod
    def from_geometry(cls, geom: DockingGeometry) -> CameraMount:
        return cls(
            tuple(float(x) for x in geom.p_s_cam_m),
            tuple(tuple(float(x) for x in row) for row in np.asarray(geom.R_s_cam)),
        )

    def T_s_cam(self) -> FloatArray:
        """(4, 4) camera pose in F_s (maps C points into F_s), metres."""
        T = np.eye(4)
        T[:3, :3] = np.asarray(self.R_s_cam, float)
        T[:3, 3] = np.asarray(self.p_s_cam_m, float)
        return T


MOUNT = CameraMount.from_geometry(GEOMETRY)


def lateral_offset_m(r_D_m: ArrayLike) -> float:
    """Distance of the probe tip from the docking axis (the hypotenuse of x_D, y_D), m."""
    r = np.asarray(r_D_m, dtype=float)
    return float(np.hypot(r[0], r[1]))


def misalignment_deg(R_D_cam: ArrayLike) -> float:
    """Combined yaw/pitch: the angle between the camera boresight and -z_D (roll excluded), deg."""
    R = np.asarray(R_D_cam, dtype=float)
    return float(np.degrees(np.arccos(np.clip(-R[2, 2], -1.0, 1.0))))


def R_D_cam_from_attitude(att_rad: ArrayLike) -> FloatArray:
    """The camera's axes in D for an attitude error (rotation vector, body frame, rad)."""
    out: FloatArray = R_D_CAM_ALIGNED @ rotvec_to_matrix(att_rad)
    return out


@dataclass
class DockingState:
    """Guidance's view of the relative pose, all in D: probe tip ``r_D_m`` (m), attitude error
    ``att_rad`` (rotation vector in the body frame), camera axes ``R_D_cam``."""

    r_D_m: FloatArray
    att_rad: FloatArray
    R_D_cam: FloatArray

    @property
    def range_m(self) -> float:
        """Probe tip to the drogue entrance along the docking axis (negative once inside), m."""
        return float(self.r_D_m[2])

    @property
    def lateral_m(self) -> float:
        return lateral_offset_m(self.r_D_m)

    @property
    def misalignment_deg(self) -> float:
        """Combined yaw/pitch: angle between the boresight and -z_D (roll excluded), deg."""
        return misalignment_deg(self.R_D_cam)


def camera_pose_from_docking(
    r_D_m: ArrayLike, att_rad: ArrayLike, geom: DockingGeometry = GEOMETRY
) -> tuple[FloatArray, FloatArray]:
    """(probe tip in D, m; attitude error, rad) -> (T_cam_target_m, R_cam_target): what the
    camera sees."""
    R_D_s = R_D_CAM_ALIGNED @ rotvec_to_matrix(att_rad)  # body axes = camera axes
    R_t_s = R_T_D @ R_D_s
    p_t_tip = R_T_D @ np.asarray(r_D_m, dtype=float)
    p_t_s = p_t_tip - R_t_s @ np.array([0.0, 0.0, geom.probe_tip_s_m])
    p_t_cam = p_t_s + R_t_s @ np.asarray(geom.p_s_cam_m, dtype=float)
    R_t_cam = R_t_s @ geom.R_s_cam
    R_cam_t = R_t_cam.T
    return -R_cam_t @ p_t_cam, R_cam_t


def docking_from_camera_pose(
    T_cam_target_m: ArrayLike, R_cam_target: ArrayLike, geom: DockingGeometry = GEOMETRY
) -> DockingState:
    """Inverse of :func:`camera_pose_from_docking`: the pose estimate -> guidance's state."""
    R_t_cam = np.asarray(R_cam_target, dtype=float).T
    p_t_cam = -R_t_cam @ np.asarray(T_cam_target_m, dtype=float)
    R_t_s = R_t_cam @ geom.R_s_cam.T
    p_t_s = p_t_cam - R_t_s @ np.asarray(geom.p_s_cam_m, dtype=float)
    p_t_tip = p_t_s + R_t_s @ np.array([0.0, 0.0, geom.probe_tip_s_m])
    R_D_s = R_T_D @ R_t_s
    att = matrix_to_rotvec(R_D_CAM_ALIGNED.T @ R_D_s)
    return DockingState(r_D_m=R_T_D @ p_t_tip, att_rad=att, R_D_cam=R_D_s @ geom.R_s_cam)


def R_cam_target_aligned(geom: DockingGeometry = GEOMETRY) -> FloatArray:
    """The attitude the camera sees when the vehicles are aligned (no attitude error): the
    reference the keypoint model's attitude head is measured from."""
    return camera_pose_from_docking(np.zeros(3), np.zeros(3), geom)[1]


def tilt_scaled(R_cam_target: ArrayLike, factor: float, geom: DockingGeometry = GEOMETRY) -> FloatArray:
    """`R_cam_target` turned about "aligned" so that its tilt (the attitude error about the
    camera's x and y) is `factor` times as large; the roll about the boresight is kept. How an
    attitude reading shrunk toward "aligned" is given back its size (oibar.nav.error_models.HeadGainModel)."""
    att = docking_from_camera_pose(np.zeros(3), R_cam_target, geom).att_rad
    att[:2] *= float(factor)
    return camera_pose_from_docking(np.zeros(3), att, geom)[1]
