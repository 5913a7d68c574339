"""What the estimator answers for one frame."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class PoseEstimate:
    """One frame's answer. T/q/R: the target's pose in the camera frame (p_C = R p_t + T)."""

    T_cam_target_m: np.ndarray  # (3,) metres, camera frame (OpenCV axes)
    q_cam_target: np.ndarray  # (4,) (w, x, y, z), w >= 0
    R_cam_target: np.ndarray  # (3, 3)
    t_s: float  # capture time of the frame, as given by the caller
    latency_ms: float  # resize + inference, this call
    confidence: float  # 0..1 plausibility (not a calibrated probability)
    camera_range_m: float  # ||T_cam_target||: camera-to-fixture distance
    ortho_defect: float  # ||rot6d - its Gram-Schmidt projection||; 0 for a valid rotation
    flags: tuple[str, ...] = field(default_factory=tuple)  # why confidence was lowered, if it was
    # What a filter should fuse, when it differs from the pose above: the same keypoints solved
    # without the attitude prior. The prior (the crop's attitude head) makes each frame's pose
    # better on its own but pulls the tilt toward "aligned" on every frame alike, an error a
    # filter cannot average away; PnP alone is noisier and unbiased (docs/model_history.md).
    T_meas_cam_target_m: np.ndarray | None = None
    R_meas_cam_target: np.ndarray | None = None
    crops: int = 0  # crop windows read through a keypoint network for this frame (its latency's driver)

    @property
    def finite(self) -> bool:
        return bool(np.all(np.isfinite(self.T_cam_target_m)) and np.all(np.isfinite(self.R_cam_target)))

    def measurement(self) -> tuple[np.ndarray, np.ndarray]:
        """(T_cam_target_m, R_cam_target) for a filter: the prior-free pose when there is one,
        else the pose itself."""
        if self.T_meas_cam_target_m is not None and self.R_meas_cam_target is not None:
            return self.T_meas_cam_target_m, self.R_meas_cam_target
        return self.T_cam_target_m, self.R_cam_target


def no_answer(t_s: float, latency_ms: float, flag: str) -> PoseEstimate:
    """A frame with nothing to read (NaN pose, confidence 0), flagged why."""
    nan = np.full(3, np.nan)
    return PoseEstimate(
        nan,
        np.full(4, np.nan),
        np.full((3, 3), np.nan),
        float(t_s),
        latency_ms,
        0.0,
        float("nan"),
        0.0,
        (flag,),
    )
