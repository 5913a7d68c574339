"""The navigation filter (issue 8, item 3): smooths the pose estimates, gates outliers and
coasts through missing frames, in the docking frame D that guidance steers in (frames.py).

Two decoupled constant-velocity Kalman filters share one clock:
  - position: the probe tip r_D_m and its velocity v_D_mps (6 states);
  - attitude: the attitude error att_rad (a rotation vector, body frame) and its rate w_rad_s
    (6 states). The docking corridor keeps the attitude error within a few degrees, so the
    rotation vector is treated as a vector (small angles): residuals are differences.
Measurement: ``docking_from_camera_pose(T_cam_target_m, R_cam_target)``. Its noise grows with
the camera-to-fixture distance (monocular: a pixel spans more metres further away), the
boresight (depth) axis noisier than the lateral ones; the attitude noise is constant, and also
moves the derived probe tip sideways by (attitude error) x (distance); both are inflated when
the estimator's confidence is low.

A measurement is gated (not used) when either block's normalised innovation squared exceeds
a chi-square threshold; after ``reinit_after`` consecutive gated measurements the filter
restarts from the latest one (a real jump, e.g. after a re-acquisition, must not be ignored
for ever). Without accepted measurements for ``max_coast_s`` the state is invalid, and the
next measurement starts the filter afresh.

Optional second sensor (``update_velocity``): the service vehicle's own relative-velocity
measurement in D (IMU/GNC odometry, oibar.nav.vehicle), a direct measurement of the velocity
states. The camera's velocity is a difference of positions whose error is a slowly varying,
range-dependent bias, so at 30 mm/s the closing speed it gives can be off by 10-20 mm/s; the
odometry pins it to a few mm/s. It has its own gate; after ``vel_reset_after`` consecutive
gated ones the velocity is re-seated on the odometry (the vehicle's velocity sensor is the
better judge of a real change, e.g. the contact). It never starts the filter nor keeps it valid:
position, and so validity, comes from the camera. Without odometry nothing here changes.

The odometry's own constant error is not in its reported sigma (a GNC states its white noise;
its bias per approach is a spec-sheet number). Fused as white, a 2 mm/s lateral bias walks the
tip estimate off the camera by the bias times the position's memory: 1-2.5 cm at 1-5 m in the rig
(docs/model_history.md, "where the closed loop's lateral error comes from"). The position block can
carry the odometry's lateral bias as three more states that are *considered*, never estimated
(a Schmidt-Kalman filter; ``odo_bias_sigma_lateral_mps``, their 1-sigma): the odometry reads
v + b with b zero-mean, and the covariance the odometry builds up in the position carries b's
share, so the camera keeps its weight. Estimating b was tried first and failed in the closed
loop: far out the camera's lateral error drifts with range (va007's look: -45 cm at 9 m to +5
cm at 5 m), which reads as an odometry bias and is then kept (docs/navigation.md). Not along the
docking axis (its sigma is zero): the closing speed that DOCK is checked against stays the
odometry's. On by default since OibarNet 0.15.3 (0.002 m/s, FilterParams); with 0.13.0's network
it traded the mean for the worst look and was off.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from oibar.geometry.docking import (
    GEOMETRY,
    R_D_CAM_ALIGNED,
    DockingGeometry,
    DockingState,
    camera_pose_from_docking,
    docking_from_camera_pose,
)
from oibar.geometry.rotations import matrix_to_quat, rotvec_to_matrix

CHI2_3DOF_P001 = 16.266  # chi-square, 3 degrees of freedom, upper tail 0.001


@dataclass(frozen=True)
class FilterParams:
    """Tuning of :class:`NavFilter`. Sigmas are 1-sigma. The defaults are sized for a model that
    meets the paper's requirement (5 % of range, 5 deg), not for the development model."""

    # Position measurement noise, camera axes, as a fraction of the camera-to-fixture distance:
    # the network's error scales with distance. Depth (boresight) comes from the fixture's
    # apparent size and is the weak axis of a monocular camera.
    pos_sigma_lateral_frac: float = 0.01
    pos_sigma_depth_frac: float = 0.03
    pos_sigma_floor_m: float = 0.005  # close in: pixel quantisation does not shrink to zero
    # Attitude measurement noise per axis: from the fixture's shape, not its size, so constant.
    # It also moves the probe tip in D by (attitude error) x (target-to-tip distance): the camera
    # sees the target's bearing, and the attitude turns that into where the probe is.
    att_sigma_deg: float = 1.5
    # Attitude noise that grows with the camera's range (deg per metre, added in quadrature):
    # PnP's tilt of a near-planar fixture is poorly observed far out (candidate 0.11.0's far
    # views tilted 3-6 deg beyond 6 m on va007's look while 0.3 deg at 2-4 m). Off (0): 0.5
    # deg/m was better on the 20 looks-study runs it was tried on (-0.33 cm paired) but tied on
    # 20 unflown ones (+0.04 cm; docs/navigation.md).
    att_sigma_per_m_deg: float = 0.0
    # Process noise: white acceleration. Docking thrust changes the relative velocity by
    # centimetres per second over seconds (closing-speed schedule 150/80/40/30 mm/s); the
    # attitude controller by tenths of deg/s. 1e-4 was the best of 1e-5/1e-4/1e-3 for the
    # closing speed on a training sequence (seq02) without lagging the schedule's steps.
    accel_psd_m2_s3: float = 1e-4  # sqrt(q * 1 s) = 1 cm/s of velocity random walk per second
    ang_accel_psd_rad2_s3: float = 1e-5  # about 0.2 deg/s per second
    # Position random walk (m^2/s) on the probe tip, beside the white acceleration. With the
    # vehicle's odometry pinning the velocity, the position block otherwise averages every
    # measurement since the start, and the camera's error is not white: it is range x the
    # attitude error of the fixture's view, a bias that shrinks as the range does. A random walk
    # gives the average a finite memory, so far-range bias fades as the vehicle closes in.
    # 1e-5 (about 10 s of memory at 4 m). Replaying 0.8.1's recorded filter inputs on the ten
    # validation looks, 3e-5 was best of eight values, but flown in the closed loop it tied; 1e-5
    # flown on the same 20 runs and then on 20 unflown ones (start 9 m) was better both times:
    # lateral p95 below 5 m paired -0.20 cm each time, worst run 8.09 -> 5.84 and 9.06 -> 4.50 cm,
    # capture 3.8 -> 3.0 and 3.2 -> 2.6 mm off the axis (docs/navigation.md).
    pos_rw_psd_m2_s: float = 1e-5
    # At first sight the rates are unknown: sigmas spanning what the approach can do
    # (closing speed <= 0.15 m/s, attitude rates well below 1 deg/s).
    init_vel_sigma_mps: float = 0.1
    init_rate_sigma_deg_s: float = 1.0
    gate_chi2: float = CHI2_3DOF_P001  # per block; a consistent measurement is gated ~1 in 1000
    reinit_after: int = 5  # consecutive gated measurements: 0.5 s at 10 Hz
    max_coast_s: float = 1.0  # at 0.15 m/s that is 0.15 m dead-reckoned; beyond, guidance must hold
    min_confidence: float = 0.05  # below: the frame is skipped (not an update, not an outlier)
    confidence_floor: float = 0.1  # noise is scaled by 1 / max(confidence, floor): at most 10x
    # Vehicle odometry (update_velocity): the sigma is the vehicle's own, per axis, never below
    # this floor (a sensor claiming 0 would freeze the velocity against everything else).
    vel_sigma_floor_mps: float = 0.001
    vel_gate_chi2: float = CHI2_3DOF_P001  # on the velocity innovation alone
    vel_reset_after: int = 5  # consecutive gated velocities: 0.5 s at 10 Hz
    # 1-sigma of the odometry's constant, unreported error per lateral D axis (x, y), carried as
    # consider states (0: off, the odometry fused as white). 0.002 is the rig vehicle's assumption
    # (VehicleParams.odometry_bias_mps); a real vehicle's GNC states its own. With 0.13.0 it lost
    # 2.3 cm on va007's look, where that camera leans, and stayed off; on with OibarNet 0.15.3
    # (its rule, docs/model_history.md): 64 paired runs, 55 better, the worst run 5.80 -> 4.78 cm.
    odo_bias_sigma_lateral_mps: float = 0.002

    def __post_init__(self) -> None:
        for name in (
            "pos_sigma_lateral_frac",
            "pos_sigma_depth_frac",
            "pos_sigma_floor_m",
            "att_sigma_deg",
            "accel_psd_m2_s3",
            "ang_accel_psd_rad2_s3",
            "init_vel_sigma_mps",
            "init_rate_sigma_deg_s",
            "gate_chi2",
            "max_coast_s",
            "confidence_floor",
            "vel_sigma_floor_mps",
            "vel_gate_chi2",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"FilterParams.{name} must be a finite positive number, got {v!r}")
        if not (np.isfinite(self.att_sigma_per_m_deg) and self.att_sigma_per_m_deg >= 0):
            raise ValueError(
                f"FilterParams.att_sigma_per_m_deg must be finite and >= 0, got {self.att_sigma_per_m_deg!r}"
            )
        if not (np.isfinite(self.odo_bias_sigma_lateral_mps) and self.odo_bias_sigma_lateral_mps >= 0):
            raise ValueError(
                "FilterParams.odo_bias_sigma_lateral_mps must be finite and >= 0, "
                f"got {self.odo_bias_sigma_lateral_mps!r}"
            )
        if not (np.isfinite(self.pos_rw_psd_m2_s) and self.pos_rw_psd_m2_s >= 0):
            raise ValueError(
                f"FilterParams.pos_rw_psd_m2_s must be finite and >= 0, got {self.pos_rw_psd_m2_s!r}"
            )
        for name in ("reinit_after", "vel_reset_after"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"FilterParams.{name} must be an integer >= 1, got {v!r}")
        if not 0.0 <= self.min_confidence < 1.0:
            raise ValueError(f"FilterParams.min_confidence must be in [0, 1), got {self.min_confidence!r}")
        if not self.confidence_floor <= 1.0:
            raise ValueError(f"FilterParams.confidence_floor must be <= 1, got {self.confidence_floor!r}")


@dataclass
class UpdateResult:
    accepted: bool  # the measurement changed the state (fused, initialised or re-initialised)
    gated: bool  # it failed the innovation gate
    nis_pos: float  # normalised innovation squared, position block (nan when not tested)
    nis_att: float  # same, attitude block
    reinitialised: bool  # the state was (re)started from this measurement
    reason: str  # initialised | fused | gated | reinitialised | low_confidence | non_finite


@dataclass
class VelocityUpdateResult:
    accepted: bool  # the velocity measurement changed the state (fused or reset)
    gated: bool  # it failed the velocity gate
    nis: float  # normalised innovation squared (nan when not tested)
    reason: str  # fused | gated | reset | not_initialised | non_finite (also malformed, sigma < 0)


@dataclass
class NavState:
    """The filter's answer at ``t_s``, all in D unless named otherwise."""

    t_s: float
    valid: bool  # initialised and an accepted measurement within max_coast_s
    r_D_m: np.ndarray  # probe tip
    v_D_mps: np.ndarray
    att_rad: np.ndarray  # attitude error, rotation vector, body frame
    w_rad_s: np.ndarray
    pos_sigma_m: np.ndarray  # (3,) 1-sigma per D axis
    vel_sigma_mps: np.ndarray  # (3,)
    att_sigma_deg: np.ndarray  # (3,) per body axis
    since_update_s: float  # since the last accepted measurement (inf before the first)
    range_m: float  # probe tip to contact (z of r_D; negative inside the drogue)
    shaft_distance_m: float  # shaft plane to berthing plane: NavUpdate.range_m
    closing_speed_mps: float  # -v_z: positive when closing
    lateral_m: float
    misalignment_deg: float  # boresight vs -z_D, roll excluded
    T_cam_target_m: np.ndarray  # the same state as the camera would see it (NavUpdate)
    q_cam_target: np.ndarray  # (w, x, y, z)


# Measurement matrices of a _CvBlock by its size (6: p, v; 9: p, v, b), built once, not per
# frame: the camera sees p; the rate sensor reads v, plus b where the bias is carried.
_H_POS = {n: np.hstack([np.eye(3), np.zeros((3, n - 3))]) for n in (6, 9)}
_H_RATE = {
    6: np.hstack([np.zeros((3, 3)), np.eye(3)]),
    9: np.hstack([np.zeros((3, 3)), np.eye(3), np.eye(3)]),
}


@dataclass
class _CvBlock:
    """Constant-velocity Kalman filter on a 3-vector: x = (p, v), P (6, 6); or, with bias states,
    x = (p, v, b), P (9, 9), where b is a constant, zero-mean error of the rate sensor (it reads
    v + b). b is a consider state: no measurement updates it (its gain is zero), but its
    covariance and its correlation with p and v are carried, so every gain allows for it."""

    x: np.ndarray = field(default_factory=lambda: np.zeros(6))
    P: np.ndarray = field(default_factory=lambda: np.eye(6))

    @property
    def has_bias(self) -> bool:
        return bool(self.x.shape[0] == 9)

    @staticmethod
    def transition(dt_s: float, psd: float, n: int = 6) -> tuple[np.ndarray, np.ndarray]:
        F = np.eye(n)
        F[:3, 3:6] = dt_s * np.eye(3)
        # Discrete white-noise acceleration (continuous PSD q integrated over dt); the bias is constant.
        Q = np.zeros((n, n))
        Q[:6, :6] = psd * np.block(
            [[dt_s**3 / 3 * np.eye(3), dt_s**2 / 2 * np.eye(3)], [dt_s**2 / 2 * np.eye(3), dt_s * np.eye(3)]]
        )
        return F, Q

    def predicted(self, dt_s: float, psd: float) -> _CvBlock:
        F, Q = self.transition(dt_s, psd, self.x.shape[0])
        return _CvBlock(F @ self.x, F @ self.P @ F.T + Q)

    def _innovation(
        self, H: np.ndarray, z: np.ndarray, Rm: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, float]:
        y = z - H @ self.x
        S = H @ self.P @ H.T + Rm
        return y, S, float(y @ np.linalg.solve(S, y))

    def _fuse(self, H: np.ndarray, y: np.ndarray, S: np.ndarray, Rm: np.ndarray) -> None:
        K = np.linalg.solve(S, H @ self.P).T  # P H^T S^-1 (S and P symmetric)
        if self.has_bias:
            K[6:9, :] = 0.0  # consider states: never updated; Joseph's form keeps P right for any gain
        self.x = self.x + K @ y
        I_KH = np.eye(self.x.shape[0]) - K @ H
        # Joseph form: stays symmetric positive definite however the gains round.
        self.P = I_KH @ self.P @ I_KH.T + K @ Rm @ K.T
        self.P = 0.5 * (self.P + self.P.T)

    def innovation(self, z: np.ndarray, Rm: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        return self._innovation(_H_POS[self.x.shape[0]], z, Rm)

    def fuse(self, y: np.ndarray, S: np.ndarray, Rm: np.ndarray) -> None:
        self._fuse(_H_POS[self.x.shape[0]], y, S, Rm)

    def rate_innovation(self, z: np.ndarray, Rm: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        return self._innovation(_H_RATE[self.x.shape[0]], z, Rm)

    def fuse_rate(self, y: np.ndarray, S: np.ndarray, Rm: np.ndarray) -> None:
        self._fuse(_H_RATE[self.x.shape[0]], y, S, Rm)

    def reseat_rate(self, z: np.ndarray, Rm: np.ndarray) -> None:
        """The rate becomes z with covariance Rm (plus the bias's: v = z - b); its correlation
        with p is dropped."""
        P = np.zeros_like(self.P)
        P[:3, :3] = self.P[:3, :3]
        P[3:6, 3:6] = Rm
        self.x = np.concatenate([self.x[:3], z, self.x[6:]])
        if self.has_bias:
            Pbb = self.P[6:9, 6:9]
            P[3:6, 3:6] += Pbb
            P[3:6, 6:9] = P[6:9, 3:6] = -Pbb
            P[6:9, 6:9] = Pbb
        self.P = P

    @staticmethod
    def started(
        z: np.ndarray,
        Rm: np.ndarray,
        rate_sigma: float,
        rate: np.ndarray | None = None,
        bias_cov: np.ndarray | None = None,
    ) -> _CvBlock:
        """At the measurement; rate zero, or ``rate`` (kept from before a jump) with the same
        initial uncertainty; ``bias_cov`` (3, 3) adds the (zero-mean) bias states."""
        n = 6 if bias_cov is None else 9
        P = np.zeros((n, n))
        P[:3, :3] = Rm
        P[3:6, 3:6] = rate_sigma**2 * np.eye(3)
        x = np.concatenate([z, np.zeros(3) if rate is None else rate])
        if bias_cov is not None:
            x = np.concatenate([x, np.zeros(3)])
            P[6:9, 6:9] = bias_cov
        return _CvBlock(x, P)


class NavFilter:
    """predict(t_s), update(t_s, T_cam_target_m, R_cam_target, confidence) -> UpdateResult,
    update_velocity(t_s, v_D_mps, sigma_mps) -> VelocityUpdateResult, state(t_s) -> NavState,
    reset(). Times in seconds on one monotonic clock (the frames' capture times); going
    backwards is a ValueError."""

    def __init__(self, params: FilterParams | None = None, geometry: DockingGeometry = GEOMETRY):
        self.params = params or FilterParams()
        self.geometry = geometry
        # Camera to probe tip in camera axes (fixed to the service vehicle).
        self._cam_to_tip_cam_m = geometry.R_s_cam.T @ (
            np.array([0.0, 0.0, geometry.probe_tip_s_m]) - np.asarray(geometry.p_s_cam_m, float)
        )
        self.reset()

    def reset(self) -> None:
        self._t_s: float | None = None  # time the blocks refer to
        self._pos: _CvBlock | None = None
        self._att: _CvBlock | None = None
        self._t_accepted_s: float | None = None
        self._gated_run = 0
        self.counts = {
            "initialised": 0,
            "fused": 0,
            "gated": 0,
            "reinitialised": 0,
            "low_confidence": 0,
            "non_finite": 0,
        }
        self._vel_gated_run = 0
        self.velocity_counts = {"fused": 0, "gated": 0, "reset": 0, "not_initialised": 0, "non_finite": 0}

    @property
    def initialised(self) -> bool:
        return self._pos is not None

    # ------------------------------------------------------------------ time
    def _check_time(self, t_s: float) -> float:
        t_s = float(t_s)
        if not np.isfinite(t_s):
            raise ValueError(f"time must be finite, got {t_s}")
        if self._t_s is not None and t_s < self._t_s:
            raise ValueError(f"time went backwards: {t_s:.6f} s after {self._t_s:.6f} s")
        return t_s

    def predict(self, t_s: float) -> None:
        """Propagate the state to t_s (covariance grows with the gap)."""
        t_s = self._check_time(t_s)
        if self._pos is not None and self._att is not None and self._t_s is not None and t_s > self._t_s:
            dt = t_s - self._t_s
            self._pos = self._pos.predicted(dt, self.params.accel_psd_m2_s3)
            if self.params.pos_rw_psd_m2_s > 0:
                self._pos.P[:3, :3] += self.params.pos_rw_psd_m2_s * dt * np.eye(3)
            self._att = self._att.predicted(dt, self.params.ang_accel_psd_rad2_s3)
        self._t_s = t_s

    def _blocks(self) -> tuple[_CvBlock, _CvBlock, float, float]:
        """(position block, attitude block, their time, last accepted time) of a started filter;
        callers check ``initialised`` first (the four are set together by ``_start``)."""
        assert self._pos is not None and self._att is not None
        assert self._t_s is not None and self._t_accepted_s is not None
        return self._pos, self._att, self._t_s, self._t_accepted_s

    def _coasted_too_long(self, t_s: float) -> bool:
        return self._t_accepted_s is None or t_s - self._t_accepted_s > self.params.max_coast_s

    # ------------------------------------------------------------------ measurement
    def measurement_noise(
        self, T_cam_target_m: np.ndarray, R_cam_target: np.ndarray, confidence: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(probe-tip covariance in D (3, 3) m^2, attitude covariance (3, 3) rad^2).

        The tip is r_D = R_D_cam u with u = (camera-to-tip - T_cam_target), camera axes, and
        R_D_cam = R_T_D R_cam_target^T. T's own error enters through R_D_cam; an attitude error
        phi (camera axes) adds R_D_cam [u]x phi, which grows with range. Its correlation with
        the attitude measurement is dropped (the two blocks are filtered separately)."""
        p = self.params
        scale = 1.0 / max(float(confidence), p.confidence_floor)
        T = np.asarray(T_cam_target_m, float)
        R_D_cam = R_D_CAM_ALIGNED @ np.asarray(R_cam_target, float).T
        cam_range_m = float(np.linalg.norm(T))
        sig_cam = (
            np.array([p.pos_sigma_lateral_frac, p.pos_sigma_lateral_frac, p.pos_sigma_depth_frac])
            * cam_range_m
        )
        att_var_rad2 = np.radians(p.att_sigma_deg) ** 2 + np.radians(p.att_sigma_per_m_deg * cam_range_m) ** 2
        u = self._cam_to_tip_cam_m - T
        J = R_D_cam @ np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
        R_pos = (
            R_D_cam @ np.diag(sig_cam**2) @ R_D_cam.T
            + att_var_rad2 * J @ J.T
            + p.pos_sigma_floor_m**2 * np.eye(3)
        )
        R_att = att_var_rad2 * np.eye(3)
        return R_pos * scale**2, R_att * scale**2

    def update(
        self, t_s: float, T_cam_target_m: ArrayLike, R_cam_target: ArrayLike, confidence: float = 1.0
    ) -> UpdateResult:
        """Fuse one pose estimate taken at t_s. Never raises for a bad measurement (it is skipped
        or gated, and the result says why); raises ValueError only for time going backwards."""
        p = self.params
        self.predict(t_s)
        T = np.asarray(T_cam_target_m, float).reshape(-1)
        R = np.asarray(R_cam_target, float)
        nan = float("nan")
        conf = float(confidence) if np.isfinite(confidence) else 0.0
        if T.shape != (3,) or R.shape != (3, 3) or not (np.all(np.isfinite(T)) and np.all(np.isfinite(R))):
            return self._count(UpdateResult(False, False, nan, nan, False, "non_finite"))
        if conf < p.min_confidence:
            return self._count(UpdateResult(False, False, nan, nan, False, "low_confidence"))
        meas = docking_from_camera_pose(T, R, self.geometry)
        R_pos, R_att = self.measurement_noise(T, R, conf)
        if not self.initialised or self._coasted_too_long(t_s):
            was = self.initialised
            self._start(meas, R_pos, R_att, t_s)
            return self._count(
                UpdateResult(True, False, nan, nan, True, "reinitialised" if was else "initialised")
            )
        pos, att, _, _ = self._blocks()
        y_p, S_p, nis_p = pos.innovation(meas.r_D_m, R_pos)
        y_a, S_a, nis_a = att.innovation(meas.att_rad, R_att)
        # One network pass gave both blocks: an inconsistent part condemns the whole frame.
        if nis_p > p.gate_chi2 or nis_a > p.gate_chi2:
            self._gated_run += 1
            if self._gated_run >= p.reinit_after:
                # The jump is in what we know of the position, not in the vehicles' motion: keep the rates.
                self._start(meas, R_pos, R_att, t_s, keep_rates=True)
                return self._count(UpdateResult(True, True, nis_p, nis_a, True, "reinitialised"))
            return self._count(UpdateResult(False, True, nis_p, nis_a, False, "gated"))
        pos.fuse(y_p, S_p, R_pos)
        att.fuse(y_a, S_a, R_att)
        self._gated_run = 0
        self._t_accepted_s = t_s
        return self._count(UpdateResult(True, False, nis_p, nis_a, False, "fused"))

    def update_velocity(self, t_s: float, v_D_mps: ArrayLike, sigma_mps: float) -> VelocityUpdateResult:
        """Fuse the vehicle's own relative velocity in D (m/s), 1-sigma ``sigma_mps`` per axis,
        measured at t_s. Skipped before the camera has started the filter or after it expired
        (nothing to correct: the next frame restarts it); never raises for a bad measurement,
        only ValueError for time going backwards."""
        p = self.params
        self.predict(t_s)
        nan = float("nan")
        try:
            v = np.asarray(v_D_mps, float).reshape(-1)
            sigma = float(sigma_mps)
        except (TypeError, ValueError):
            v, sigma = np.full(1, nan), nan
        if v.shape != (3,) or not (np.all(np.isfinite(v)) and np.isfinite(sigma) and sigma >= 0.0):
            return self._count_vel(VelocityUpdateResult(False, False, nan, "non_finite"))
        if not self.initialised or self._coasted_too_long(t_s):
            return self._count_vel(VelocityUpdateResult(False, False, nan, "not_initialised"))
        Rm = max(sigma, p.vel_sigma_floor_mps) ** 2 * np.eye(3)
        pos, _, _, _ = self._blocks()
        y, S, nis = pos.rate_innovation(v, Rm)
        if nis > p.vel_gate_chi2:
            self._vel_gated_run += 1
            if self._vel_gated_run >= p.vel_reset_after:
                pos.reseat_rate(v, Rm)
                self._vel_gated_run = 0
                return self._count_vel(VelocityUpdateResult(True, True, nis, "reset"))
            return self._count_vel(VelocityUpdateResult(False, True, nis, "gated"))
        pos.fuse_rate(y, S, Rm)
        self._vel_gated_run = 0
        return self._count_vel(VelocityUpdateResult(True, False, nis, "fused"))

    def _count_vel(self, r: VelocityUpdateResult) -> VelocityUpdateResult:
        self.velocity_counts[r.reason] += 1
        return r

    def _start(
        self, meas: DockingState, R_pos: np.ndarray, R_att: np.ndarray, t_s: float, keep_rates: bool = False
    ) -> None:
        p = self.params
        v = w = None
        if keep_rates:
            pos, att, _, _ = self._blocks()
            v, w = pos.x[3:6], att.x[3:6]
        s2 = p.odo_bias_sigma_lateral_mps**2
        bias_cov = np.diag([s2, s2, 0.0]) if s2 > 0 else None
        self._pos = _CvBlock.started(meas.r_D_m, R_pos, p.init_vel_sigma_mps, v, bias_cov)
        self._att = _CvBlock.started(meas.att_rad, R_att, np.radians(p.init_rate_sigma_deg_s), w)
        self._t_s = t_s
        self._t_accepted_s = t_s
        self._gated_run = 0

    def _count(self, r: UpdateResult) -> UpdateResult:
        self.counts[r.reason] += 1
        return r

    # ------------------------------------------------------------------ output
    def state(self, t_s: float) -> NavState:
        """The state extrapolated to t_s (the filter itself is not advanced). Before the first
        measurement: a zero state with valid False and infinite sigmas."""
        t_s = self._check_time(t_s)
        if not self.initialised:
            zero, inf3 = np.zeros(3), np.full(3, np.inf)
            T, R = camera_pose_from_docking(zero, zero, self.geometry)
            return NavState(
                t_s,
                False,
                zero,
                zero.copy(),
                zero.copy(),
                zero.copy(),
                inf3,
                inf3.copy(),
                inf3.copy(),
                float("inf"),
                0.0,
                self.geometry.shaft_distance_m(0.0),
                0.0,
                0.0,
                0.0,
                T,
                matrix_to_quat(R),
            )
        pos0, att0, blocks_t_s, accepted_t_s = self._blocks()
        dt = t_s - blocks_t_s
        pos = pos0.predicted(dt, self.params.accel_psd_m2_s3)
        att = att0.predicted(dt, self.params.ang_accel_psd_rad2_s3)
        r, v, a, w = pos.x[:3], pos.x[3:6], att.x[:3], att.x[3:6]
        R_D_cam = R_D_CAM_ALIGNED @ rotvec_to_matrix(a) @ self.geometry.R_s_cam
        ds = DockingState(r_D_m=r, att_rad=a, R_D_cam=R_D_cam)
        T, R = camera_pose_from_docking(r, a, self.geometry)
        since = t_s - accepted_t_s
        return NavState(
            t_s=t_s,
            valid=not self._coasted_too_long(t_s),
            r_D_m=r,
            v_D_mps=v,
            att_rad=a,
            w_rad_s=w,
            pos_sigma_m=np.sqrt(np.diag(pos.P)[:3]),
            vel_sigma_mps=np.sqrt(np.diag(pos.P)[3:6]),
            att_sigma_deg=np.degrees(np.sqrt(np.diag(att.P)[:3])),
            since_update_s=since,
            range_m=ds.range_m,
            shaft_distance_m=self.geometry.shaft_distance_m(ds.range_m),
            closing_speed_mps=float(-v[2]),
            lateral_m=ds.lateral_m,
            misalignment_deg=ds.misalignment_deg,
            T_cam_target_m=T,
            q_cam_target=matrix_to_quat(R),
        )
