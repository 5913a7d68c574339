"""Relative 6-DOF motion of the service vehicle (SV) with respect to the target's drogue.

Frame D (docking frame, fixed to the target vehicle's drogue): origin at the drogue
entrance, +z out of the drogue towards the approaching SV, x/y lateral. The state is the
SV probe tip position ``r_D_m`` and velocity ``v_D_mps`` in D, and the SV attitude error
``att_rad`` (small rotation vector from the aligned attitude, in the SV camera/body frame)
with its rate ``w_rad_s``. The camera looks along the probe (camera +z towards the target).

The SV's own GNC (not ours: the "vehicle interface" of SPEC section 5) tracks the relative
velocity and angular-rate setpoints that guidance sends, with a first-order response,
thrust limits and actuator noise. Orbital (Clohessy-Wiltshire) terms are left out: over the
last 10 m and a few minutes they are millimetres, far below the guidance corrections.
All numbers here are assumptions (docs/hil.md, "Plant parameters").

The SV's GNC also knows its own relative velocity (IMU and its navigation) and reports it to
ours (oibar.nav.vehicle ``relative_velocity``): here the true one plus a constant error per
approach (calibration, not reported) and white noise (reported as its sigma), from a generator
spawned off the rig's seeded one (the world's own noise stream is unchanged).

It knows the relative attitude too (``relative_attitude``: its star tracker and gyros against the
target's known attitude): the true one plus a constant error per approach (the target's attitude
knowledge) and white noise, reported with their combined sigma, from a second spawned generator.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from oibar.geometry.docking import R_D_cam_from_attitude, lateral_offset_m, misalignment_deg
from oibar.nav.vehicle import RelativeAttitude, RelativeVelocity


@dataclass
class VehicleParams:
    mass_kg: float = 150.0  # assumption: effective relative mass of the SV
    thrust_max_n: float = 20.0  # assumption: translation thrust per axis
    velocity_tau_s: float = 1.0  # assumption: SV GNC velocity loop time constant
    rate_tau_s: float = 0.5  # assumption: attitude-rate loop time constant
    ang_accel_max_rad_s2: float = 0.02
    accel_noise_mps2: float = 4e-4  # actuator noise (1 sigma), thruster quantisation
    ang_noise_rad_s2: float = 2e-4
    noise_period_s: float = 0.1  # noise is held for one thruster cycle
    odometry: bool = True  # the SV's GNC reports its relative velocity to ours
    odometry_sigma_mps: float = 0.005  # assumption: white, per axis, reported as its 1-sigma
    odometry_bias_mps: float = (
        0.002  # assumption: 1-sigma per axis of a constant error per approach, unreported
    )
    attitude_ref: bool = True  # the SV's GNC reports its relative attitude to ours
    attitude_ref_bias_deg: float = 1.0  # assumption: 1-sigma per axis, constant per approach
    attitude_ref_noise_deg: float = 0.05  # assumption: white, per axis (star tracker and gyros)
    # A constant unmodelled acceleration in D (thruster misalignment, plume impingement), which
    # the velocity loop must fight; zero in the scenarios (issue 62 disperses it)
    accel_bias_mps2: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass
class WorldState:
    r_D_m: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 10.0]))
    v_D_mps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    att_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    w_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))


class World:
    """Integrates the SV's relative motion; the mechanism adds axial forces and limits."""

    def __init__(self, params: VehicleParams, state: WorldState, rng: np.random.Generator) -> None:
        self.p = params
        self.s = state
        self.rng = rng
        self.v_sp_mps = np.zeros(3)
        self.w_sp_rad_s = np.zeros(3)
        self.thrust_n = np.zeros(3)
        self._noise_a = np.zeros(3)
        self._noise_w = np.zeros(3)
        self._noise_left_s = 0.0
        if params.odometry:
            self._odo_rng = rng.spawn(1)[0]
            self._odo_bias_mps = self._odo_rng.normal(0.0, params.odometry_bias_mps, 3)
        if params.attitude_ref:  # spawned after the odometry's: that stream stays as it was
            self._att_rng = rng.spawn(1)[0]
            self._att_bias_rad = self._att_rng.normal(0.0, np.radians(params.attitude_ref_bias_deg), 3)

    def relative_velocity(self, t_s: float) -> RelativeVelocity | None:
        """What the SV's GNC reports of its relative velocity at t_s (VehicleInterface's odometry)."""
        p = self.p
        if not p.odometry:
            return None
        v = self.s.v_D_mps + self._odo_bias_mps + self._odo_rng.normal(0.0, p.odometry_sigma_mps, 3)
        return RelativeVelocity(float(t_s), v, p.odometry_sigma_mps)

    def relative_attitude(self, t_s: float) -> RelativeAttitude | None:
        """What the SV's GNC reports of the relative attitude at t_s (VehicleInterface's)."""
        p = self.p
        if not p.attitude_ref:
            return None
        noise_rad = np.radians(p.attitude_ref_noise_deg)
        att = self.s.att_rad + self._att_bias_rad + self._att_rng.normal(0.0, noise_rad, 3)
        sigma_rad = float(np.hypot(np.radians(p.attitude_ref_bias_deg), noise_rad))
        return RelativeAttitude(float(t_s), att, sigma_rad)

    def set_setpoint(self, v_sp_mps: np.ndarray, w_sp_rad_s: np.ndarray) -> None:
        self.v_sp_mps = np.asarray(v_sp_mps, dtype=float)
        self.w_sp_rad_s = np.asarray(w_sp_rad_s, dtype=float)

    def step(self, dt_s: float, f_ext_D_n: np.ndarray) -> None:
        p, s = self.p, self.s
        self._noise_left_s -= dt_s
        if self._noise_left_s <= 0.0:
            self._noise_left_s = p.noise_period_s
            self._noise_a = self.rng.normal(0.0, p.accel_noise_mps2, 3)
            self._noise_w = self.rng.normal(0.0, p.ang_noise_rad_s2, 3)
        self.thrust_n = np.clip(
            p.mass_kg * (self.v_sp_mps - s.v_D_mps) / p.velocity_tau_s, -p.thrust_max_n, p.thrust_max_n
        )
        a = (self.thrust_n + f_ext_D_n) / p.mass_kg + self._noise_a
        if any(p.accel_bias_mps2):
            a = a + np.asarray(p.accel_bias_mps2, dtype=float)
        s.v_D_mps = s.v_D_mps + a * dt_s  # semi-implicit Euler: stable with the probe spring
        s.r_D_m = s.r_D_m + s.v_D_mps * dt_s
        alpha = (
            np.clip(
                (self.w_sp_rad_s - s.w_rad_s) / p.rate_tau_s, -p.ang_accel_max_rad_s2, p.ang_accel_max_rad_s2
            )
            + self._noise_w
        )
        s.w_rad_s = s.w_rad_s + alpha * dt_s
        s.att_rad = s.att_rad + s.w_rad_s * dt_s

    # -- ground truth, as navigation would report it ------------------------------------

    @property
    def odometry_bias_mps(self) -> np.ndarray:
        """The odometry's constant error this approach (truth; the vehicle does not report it)."""
        return self._odo_bias_mps.copy() if self.p.odometry else np.zeros(3)

    @property
    def range_m(self) -> float:
        """Probe tip to drogue entrance along the docking axis (negative once inside)."""
        return float(self.s.r_D_m[2])

    @property
    def closing_speed_mps(self) -> float:
        return float(-self.s.v_D_mps[2])

    @property
    def lateral_m(self) -> float:
        return lateral_offset_m(self.s.r_D_m)

    def R_D_cam(self) -> np.ndarray:
        return R_D_cam_from_attitude(self.s.att_rad)

    @property
    def misalignment_deg(self) -> float:
        """Combined yaw/pitch: angle between the camera boresight and -z_D (roll excluded)."""
        return misalignment_deg(self.R_D_cam())

    def clamp_lateral(self, radius_m: float) -> None:
        r = self.lateral_m
        if r > radius_m:
            k = radius_m / r if r > 0 else 0.0
            self.s.r_D_m[:2] *= k
            self.s.v_D_mps[:2] = 0.0

    def clamp_misalignment(self, max_rad: float) -> None:
        e = self.s.att_rad[:2]
        n = float(np.linalg.norm(e))
        if n > max_rad:
            self.s.att_rad[:2] = e * (max_rad / n)
            self.s.w_rad_s[:2] = 0.0
