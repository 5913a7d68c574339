"""The camera's attitude checked against the vehicle's own (an integrity check of the navigator).

The service vehicle holds its attitude from its own sensors (star tracker, gyros) and knows the
target's (the station holds its local-vertical attitude and says so), so its GNC knows the relative
attitude to about a degree (``VehicleInterface.relative_attitude``). The camera's position comes
out of the pose through the attitude: the probe tip in D is the fixture's bearing turned by the
relative attitude, so an attitude misread by 15 deg at 7 m puts the tip 1.8 m off. Campaign cnn_300's
mission 71 did that: at confidence 0.92-0.98 the network misread the fixture's tilt by 4-17 deg from
9 m to 2 m, and guidance followed the reading 1.87 m off the docking axis (docs/campaign.md).

The check: the angle between the camera's relative attitude and the vehicle's. Within
``limit_deg`` plus ``k_sigma`` times the vehicle's own 1-sigma, the camera's pose is used as it
is. Beyond it the camera's attitude is out of its specification (the paper's 5 deg) and
disagrees with an independent sensor: the navigator keeps the camera's translation (the fixture's
bearing and range, which the image fixes) and takes the vehicle's attitude. The cycle does not
hold: the vehicle's attitude is the better one there, and holding for the minutes a lighting
lasts would only abort the approach. Without a vehicle attitude nothing changes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from oibar.geometry.docking import R_D_cam_from_attitude, camera_pose_from_docking, docking_from_camera_pose
from oibar.nav.vehicle import RelativeAttitude


@dataclass(frozen=True)
class AttitudeCheckParams:
    limit_deg: float = 5.0  # the attitude bound the estimator is held to (the paper's 5 deg)
    k_sigma: float = 3.0  # the vehicle's own error widens the bound by this many of its sigmas


@dataclass(frozen=True)
class AttitudeCheck:
    """The verdict on one frame: the angle between the two attitudes, the bound it was held to,
    and whether the vehicle's attitude replaced the camera's."""

    disagreement_deg: float
    limit_deg: float
    replaced: bool


def valid_reference(ref: Any) -> RelativeAttitude | None:
    """``ref`` as a :class:`RelativeAttitude`, or None when it is not one (wrong shape, not
    finite, a sigma not above zero): a bad vehicle sensor reading turns the check off, never on."""
    try:
        t_s = float(ref[0])
        att = np.asarray(ref[1], dtype=float)
        sigma = float(ref[2])
    except (TypeError, ValueError, IndexError):
        return None
    if att.shape != (3,) or not np.all(np.isfinite(att)) or not np.isfinite(t_s):
        return None
    if not (np.isfinite(sigma) and sigma > 0.0):
        return None
    return RelativeAttitude(t_s, att, sigma)


def disagreement_deg(R_cam_target: np.ndarray, att_ref_rad: np.ndarray) -> float:
    """The angle between the camera's relative attitude (from ``R_cam_target``) and the
    vehicle's (``att_ref_rad``), deg."""
    att_cam = docking_from_camera_pose(np.zeros(3), R_cam_target).att_rad
    R_rel = R_D_cam_from_attitude(att_cam).T @ R_D_cam_from_attitude(att_ref_rad)
    return float(np.degrees(np.arccos(np.clip((np.trace(R_rel) - 1.0) / 2.0, -1.0, 1.0))))


def check_attitude(
    T_cam_target_m: np.ndarray,
    R_cam_target: np.ndarray,
    ref: RelativeAttitude,
    params: AttitudeCheckParams | None = None,
) -> tuple[np.ndarray, np.ndarray, AttitudeCheck]:
    """The pose to fuse, ``(T_cam_target_m, R_cam_target)``, and the verdict: the camera's own
    pose when the attitudes agree, else its translation with the vehicle's attitude."""
    params = params or AttitudeCheckParams()
    d = disagreement_deg(R_cam_target, ref.att_rad)
    limit = params.limit_deg + params.k_sigma * float(np.degrees(ref.sigma_rad))
    if d <= limit:
        return T_cam_target_m, R_cam_target, AttitudeCheck(d, limit, False)
    R_ref = camera_pose_from_docking(np.zeros(3), ref.att_rad)[1]
    return T_cam_target_m, R_ref, AttitudeCheck(d, limit, True)
