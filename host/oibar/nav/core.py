"""One navigation cycle, independent of where frames and time come from: frame -> pose
estimate -> checks -> filter -> navigation solution. The real-time daemon (oibar.nav.daemon)
and the HIL rig (oibar_hil.rig) both run this same code; only the clock and the camera differ.

A cycle never raises for bad input: a missing or stale frame, a malformed frame, a low
confidence or a gated outlier each give a solution with ``hold_reason`` set, and guidance holds.

``odometry``: the vehicle's own relative velocity in D, ``(t_s, v_D_mps, sigma_mps)``
(oibar.nav.vehicle.RelativeVelocity) or None, fused into the filter's velocity after the frame
(before it when older). It sharpens the closing speed the MCU checks the capture against; it
does not make the solution trustworthy without a frame, and a bad or gated one does not hold.

``attitude_ref``: the vehicle's own relative attitude, ``(t_s, att_rad, sigma_rad)``
(oibar.nav.vehicle.RelativeAttitude) or None. A frame whose attitude disagrees with it beyond
the check's bound is fused with the vehicle's attitude in place of its own (oibar.nav.integrity);
the verdict is in ``NavStep.attitude_check``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from oibar.geometry.rotations import quat_to_matrix
from oibar.nav.filter import NavFilter
from oibar.nav.guidance import NavSolution
from oibar.nav.integrity import AttitudeCheck, AttitudeCheckParams, check_attitude, valid_reference
from oibar.nav.pose import FrameError, PoseEstimate, PoseEstimator


@dataclass
class NavigatorParams:
    confidence_min: float = 0.5  # below: do not act on the estimate (the filter coasts)
    max_frame_age_s: float = 0.25  # an older frame is stale: 2.5 cycles at 10 Hz
    attitude_check: AttitudeCheckParams = field(default_factory=AttitudeCheckParams)


@dataclass
class NavStep:
    """Everything one cycle produced, for the log and the replay."""

    t_s: float
    solution: NavSolution
    frame_seq: int | None = None
    frame_t_s: float | None = None
    estimate: PoseEstimate | None = None
    update: Any = None  # the filter's UpdateResult, None when nothing was fed
    hold_reason: str = ""
    timings_ms: dict[str, float] = field(default_factory=dict)
    velocity_update: Any = None  # the filter's VelocityUpdateResult, None without odometry
    attitude_check: AttitudeCheck | None = None  # None: no vehicle attitude, or no frame fused


class Navigator:
    def __init__(
        self,
        estimator: PoseEstimator,
        nav_filter: NavFilter | None = None,
        params: NavigatorParams | None = None,
    ) -> None:
        self.estimator = estimator
        self.filter = nav_filter or NavFilter()
        self.p = params or NavigatorParams()

    def step(
        self,
        t_s: float,
        frame: Any | None,
        frame_t_s: float | None = None,
        frame_seq: int | None = None,
        odometry: Any = None,
        attitude_ref: Any = None,
    ) -> NavStep:
        """``frame``: an RGB uint8 image, or None when no new frame arrived this cycle.
        ``frame_t_s``: its capture time on the same clock as ``t_s`` (default: now).
        ``odometry``: ``(t_s, v_D_mps, sigma_mps)`` on the same clock, or None.
        ``attitude_ref``: ``(t_s, att_rad, sigma_rad)``, or None."""
        timings: dict[str, float] = {}
        reason = ""
        est = None
        upd = None
        vel_upd = None
        att_check = None
        odo_t_s = None
        if odometry is not None:
            try:
                odo_t_s = min(float(odometry[0]), t_s)
            except (TypeError, ValueError, IndexError):
                odo_t_s = float("nan")
            if not np.isfinite(odo_t_s):
                odo_t_s, odometry = None, None
            # older than the frame: fuse it first, so the filter's clock only goes forward
            elif frame is not None and odo_t_s < (t_s if frame_t_s is None else min(frame_t_s, t_s)):
                vel_upd = self._fuse_velocity(odo_t_s, odometry)
                odometry = None
        if frame is None:
            reason = "no new frame"
        else:
            # a frame captured between the cycle's start and the poll is "now", not the future
            ft = t_s if frame_t_s is None else min(frame_t_s, t_s)
            if t_s - ft > self.p.max_frame_age_s:
                reason = f"stale frame ({t_s - ft:.2f} s old)"
            else:
                t0 = time.perf_counter()
                try:
                    prior = self._predicted_pose(ft)
                    if prior is not None:
                        est = self.estimator.estimate(frame, t_s=ft, prior=prior)
                    else:
                        est = self.estimator.estimate(frame, t_s=ft)
                except FrameError as exc:
                    reason = f"malformed frame: {exc}"
                timings["estimate_ms"] = (time.perf_counter() - t0) * 1e3
                if est is not None:
                    if not est.confidence >= self.p.confidence_min:  # NaN-safe
                        reason = f"low confidence {est.confidence:.2f}"
                    else:
                        upd, att_check, reason = self._fuse_frame(ft, est, attitude_ref, timings)
        if odometry is not None and odo_t_s is not None:  # (odometry kept: its time is finite)
            vel_upd = self._fuse_velocity(odo_t_s, odometry)
        st = self.filter.state(t_s)
        if not st.valid and not reason:
            reason = "filter not initialised"
        sol = NavSolution(
            valid=bool(st.valid),
            r_D_m=np.asarray(st.r_D_m, dtype=float).copy(),
            v_D_mps=np.asarray(st.v_D_mps, dtype=float).copy(),
            att_rad=np.asarray(st.att_rad, dtype=float).copy(),
            misalignment_deg=float(st.misalignment_deg),
            t_cam_target_m=np.asarray(st.T_cam_target_m, dtype=float),
            q_cam_target=np.asarray(st.q_cam_target, dtype=float),
            confidence=float(est.confidence) if est is not None else 0.0,
            hold_reason=reason,
        )
        return NavStep(
            t_s, sol, frame_seq, frame_t_s, est, upd, reason, timings, vel_upd, attitude_check=att_check
        )

    def _fuse_frame(
        self, ft: float, est: PoseEstimate, attitude_ref: Any, timings: dict[str, float]
    ) -> tuple[Any, AttitudeCheck | None, str]:
        """The frame's pose into the filter, checked against the vehicle's attitude first:
        (the filter's verdict, the check's, why to hold or "")."""
        t0 = time.perf_counter()
        upd, att_check, reason = None, None, ""
        try:
            T_m, R_m = est.measurement()  # prior-free where it differs (PoseEstimate)
            if (ref := valid_reference(attitude_ref)) is not None:
                T_m, R_m, att_check = check_attitude(T_m, R_m, ref, self.p.attitude_check)
            upd = self.filter.update(ft, T_m, R_m, est.confidence)
        except ValueError as exc:  # a frame older than the last one fused
            reason = f"frame out of order ({exc})"
        timings["filter_ms"] = (time.perf_counter() - t0) * 1e3
        if upd is not None and upd.gated:
            reason = "gated outlier"
        return upd, att_check, reason

    def _predicted_pose(self, t_s: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The filter's pose for the frame's time, for an estimator that looks where the target
        should be (a keypoint model's crop); None while the filter has no valid track."""
        if not getattr(self.estimator, "uses_prior", False) or not self.filter.initialised:
            return None
        try:
            st = self.filter.state(t_s)
        except ValueError:  # a frame older than the filter's clock
            return None
        if not st.valid:
            return None
        return quat_to_matrix(np.asarray(st.q_cam_target, float)), np.asarray(st.T_cam_target_m, float)

    def _fuse_velocity(self, t_s: float, odometry: Any) -> Any:
        try:
            return self.filter.update_velocity(t_s, odometry[1], odometry[2])
        except (ValueError, TypeError, IndexError):  # older than the last fused frame, or malformed
            return None

    def reset(self) -> None:
        self.filter.reset()
