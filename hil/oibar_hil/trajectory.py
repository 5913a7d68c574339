"""Chaser (SV) trajectories relative to the berthing fixture, after the paper's three phases.

Frames. Target frame F_t (berthing fixture): origin at the centre of the front face of the
fixture's rectangular boundary (the berthing plane); +Z_t along the docking axis *into* the port
(from the chaser towards the station); +X_t along the long edge, +Y_t along the short edge,
+Y_t being the image "down" direction of an aligned camera. The chaser's docking frame F_s has
its origin at the centre of the end-effector shaft plane and is parallel to F_t when aligned, so
the chaser sits at negative z_t and `distance_m = -z` is the paper's shaft-plane to
berthing-plane distance.

All numbers the paper does not give are assumptions and live in `TrajectoryParams`.
Everything is deterministic for a seed (NumPy PCG64 via default_rng).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from oibar.geometry.rotations import matrix_to_rotvec, rotvec_to_matrix

PHASE_ACQUISITION = 1
PHASE_FORCED_TRANSLATION = 2
PHASE_ALIGNMENT_SOFT_DOCK = 3
PHASE_NAMES = {1: "acquisition", 2: "forced_translation", 3: "alignment_soft_docking"}


@dataclass(frozen=True)
class TrajectoryParams:
    dt_s: float = 0.1  # 10 Hz frames (paper)
    start_distance_m: float = 10.0  # paper
    # Phase 1 (paper): waypoints 1-2 m off axis, speed 0.09-0.12 m/s, attitude aligned.
    waypoint_radius_min_m: float = 1.0
    waypoint_radius_max_m: float = 2.0
    waypoint_min_separation_m: float = 1.0  # assumption: keeps the two waypoints distinct
    acq_speed_min_mps: float = 0.09
    acq_speed_max_mps: float = 0.12
    # Phase 2 (paper): 10 m -> 3 m at 0.03 m/s with PI-controlled perturbations.
    forced_speed_mps: float = 0.03
    forced_end_distance_m: float = 3.0
    pert_speed_mps: float = 0.002
    pert_cross_m: float = 0.01
    pert_attitude_deg: float = 0.1
    pert_probability: float = 0.10
    pert_tick_s: float = 1.0  # assumption: a perturbation may occur once a second
    pi_kp: float = 2.0  # assumption: PI gains (1/s, 1/s^2), critically damped
    pi_ki: float = 1.0
    # Phase 3 (paper gives no numbers; assumptions).
    align_duration_s: float = 10.0
    final_speed_mps: float = 0.04
    slow_distance_m: float = 0.5
    contact_speed_mps: float = 0.02
    soft_dock_distance_m: float = 0.10  # shaft plane to berthing plane when latches engage
    # Envelope mode (mechanism capture limits, beyond the paper).
    env_max_misalignment_deg: float = 9.8  # + perturbations (<= 0.17 deg) stays <= 10 deg
    env_max_closing_speed_mps: float = 0.05
    env_min_closing_speed_mps: float = 0.01
    env_max_lateral_m: float = 0.02  # assumption: residual offset inside the drogue's reach
    env_ramp_s: float = 20.0


@dataclass
class Trajectory:
    """Samples at t = k * dt. p_t_s: chaser docking-frame origin in F_t (m);
    R_t_s: chaser attitude (F_s -> F_t); v_t_s: velocity (m/s, analytic for each sample)."""

    t_s: np.ndarray
    phase: np.ndarray
    p_t_s: np.ndarray
    R_t_s: np.ndarray
    v_t_s: np.ndarray
    misalignment_rotvec_rad: np.ndarray
    params: TrajectoryParams
    seed: int
    envelope: bool
    info: dict = field(default_factory=dict)

    @property
    def distance_m(self) -> np.ndarray:
        return -self.p_t_s[:, 2]

    def __len__(self) -> int:
        return len(self.t_s)


class _PIChannel:
    """A deviation that tracks a randomly re-drawn setpoint through a PI law on an integrator
    plant (x' = u), saturated at +-bound: the paper's 'simple PI controller' perturbations."""

    def __init__(self, bound: float, kp: float, ki: float):
        self.bound, self.kp, self.ki = bound, kp, ki
        self.x = 0.0
        self.setpoint = 0.0
        self.integral = 0.0

    def step(self, dt: float) -> float:
        err = self.setpoint - self.x
        self.integral += err * dt
        u = self.kp * err + self.ki * self.integral
        x_new = self.x + u * dt
        if abs(x_new) > self.bound:  # saturate and stop integrating (anti-windup)
            x_new = float(np.clip(x_new, -self.bound, self.bound))
            self.integral -= err * dt
        self.x = x_new
        return self.x


def _random_waypoint(rng: np.random.Generator, p: TrajectoryParams) -> np.ndarray:
    # Uniform over the annulus area.
    r = np.sqrt(rng.uniform(p.waypoint_radius_min_m**2, p.waypoint_radius_max_m**2))
    a = rng.uniform(0.0, 2 * np.pi)
    return np.array([r * np.cos(a), r * np.sin(a)])


def _segment(p0: np.ndarray, p1: np.ndarray, speed_mps: float, p: TrajectoryParams):
    """Straight constant-speed leg sampled on the dt grid; the step count is rounded and then
    nudged so the realised speed stays inside the phase-1 speed band."""
    length = float(np.linalg.norm(p1 - p0))
    n = max(1, int(round(length / (speed_mps * p.dt_s))))
    while length / (n * p.dt_s) > p.acq_speed_max_mps:
        n += 1
    while n > 1 and length / (n * p.dt_s) < p.acq_speed_min_mps:
        n -= 1
    frac = np.arange(1, n + 1) / n
    pts = p0[None, :] + frac[:, None] * (p1 - p0)[None, :]
    vel = np.repeat(((p1 - p0) / (n * p.dt_s))[None, :], n, axis=0)
    return pts, vel


def generate(
    seed: int,
    envelope: bool = False,
    params: TrajectoryParams | None = None,
    turned_deg: float = 0.0,
    offaxis_m: float = 0.0,
    rolled_deg: float = 0.0,
) -> Trajectory:
    """`turned_deg` > 0: the chaser keeps a constant misalignment of that size (about a random
    axis in the berthing plane, from its own generator so the rest of the trajectory is the same
    as without) from 10 m to contact, on top of everything else: the case of a vehicle that
    never lines up, as in the rig's nominal mission (2.5 deg). The paper's phases align it.

    `offaxis_m` > 0: from the end of phase 1 to contact the chaser wanders off the docking axis
    (off_axis_offsets: up to `offaxis_m`, and never more than OFFAXIS_MAX_ANGLE of the view
    from the fixture, so it stays in the picture close in), again from its own generator. The
    paper's phases hold it within 1-2 cm of the axis below 10 m, so a network trained on them
    alone has never seen the fixture's depth (the drogue's throat) from the side: it reads a
    lateral offset as a rotation, which is what a closed loop that is off the axis shows it.

    `rolled_deg`: the chaser is rolled by this much about its own docking axis throughout (the
    probe is round; the fixture turns in the picture), so a test set measures attitude beyond
    the near-aligned frames of the paper's sequences."""
    p = params or TrajectoryParams()
    rng = np.random.default_rng(seed)
    dt = p.dt_s
    z0 = -p.start_distance_m

    # ---- Phase 1: acquisition (attitude aligned, constant z) ----
    wp_a = _random_waypoint(rng, p)
    while True:
        wp_b = _random_waypoint(rng, p)
        if np.linalg.norm(wp_b - wp_a) >= p.waypoint_min_separation_m:
            break
    pos = [np.array([wp_a[0], wp_a[1], z0])]
    vel = [np.zeros(3)]
    for a, b in ((wp_a, wp_b), (wp_b, np.zeros(2))):
        speed = rng.uniform(p.acq_speed_min_mps, p.acq_speed_max_mps)
        pts, v = _segment(np.array([*a, z0]), np.array([*b, z0]), speed, p)
        pos.extend(pts)
        vel.extend(v)
    # The first sample sits at waypoint A with the first leg's velocity.
    vel[0] = vel[1]
    n1 = len(pos)
    phase = [PHASE_ACQUISITION] * n1
    rot = [np.zeros(3)] * n1
    misalign = [np.zeros(3)] * n1

    # ---- Phase 2: forced translation with PI perturbations ----
    ch_speed = _PIChannel(p.pert_speed_mps, p.pi_kp, p.pi_ki)
    ch_x = _PIChannel(p.pert_cross_m, p.pi_kp, p.pi_ki)
    ch_y = _PIChannel(p.pert_cross_m, p.pi_kp, p.pi_ki)
    att_bound = np.radians(p.pert_attitude_deg)
    ch_att = [_PIChannel(att_bound, p.pi_kp, p.pi_ki) for _ in range(3)]
    channels = [ch_speed, ch_x, ch_y, *ch_att]

    env_rotvec = np.zeros(3)
    env_speed = p.final_speed_mps
    env_lateral = np.zeros(2)
    if envelope:
        angle = np.radians(rng.uniform(0.0, p.env_max_misalignment_deg))
        axis_dir = rng.uniform(0.0, 2 * np.pi)
        # Combined yaw (about Y_t) and pitch (about X_t): the mechanism's capture case.
        env_rotvec = angle * np.array([np.cos(axis_dir), np.sin(axis_dir), 0.0])
        env_speed = rng.uniform(p.env_min_closing_speed_mps, p.env_max_closing_speed_mps)
        env_lateral = _random_lateral(rng, p.env_max_lateral_m)

    ticks_per_pert = max(1, int(round(p.pert_tick_s / dt)))
    z = z0
    k = 0
    t_phase2 = 0.0
    while -z > p.forced_end_distance_m:
        if k % ticks_per_pert == 0:
            for ch in channels:
                if rng.random() < p.pert_probability:
                    ch.setpoint = rng.uniform(-ch.bound, ch.bound)
        k += 1
        t_phase2 += dt
        dv = ch_speed.step(dt)
        vz = p.forced_speed_mps + dv
        # No clamping at 3 m: the phase ends on the first sample at or inside 3 m, so every
        # sample keeps a speed inside the perturbation band.
        z = z + vz * dt
        ex, ey = ch_x.step(dt), ch_y.step(dt)
        att = np.array([c.step(dt) for c in ch_att])
        ramp = _smoothstep(t_phase2 / p.env_ramp_s) if envelope else 0.0
        m = env_rotvec * ramp
        p_prev = pos[-1]
        p_new = np.array([ex, ey, z])
        pos.append(p_new)
        v_new = (p_new - p_prev) / dt
        v_new[2] = vz
        vel.append(v_new)
        rot.append(att + m)
        misalign.append(m)
        phase.append(PHASE_FORCED_TRANSLATION)

    # ---- Phase 3: alignment, then translation to soft-dock ----
    p_start = pos[-1].copy()
    r_start = rot[-1].copy()
    m_start = misalign[-1].copy()
    # Nominal: back to the axis, attitude aligned. Envelope: keep the misalignment and end at a
    # small lateral offset, to arrive at capture at the limits of the mechanism.
    p_goal = np.array([env_lateral[0], env_lateral[1], p_start[2]])
    r_goal = m_start if envelope else np.zeros(3)
    n_align = int(round(p.align_duration_s / dt))
    for i in range(1, n_align + 1):
        s = _smoothstep(i / n_align)
        p_new = p_start + s * (p_goal - p_start)
        vel.append((p_new - pos[-1]) / dt)
        pos.append(p_new)
        rot.append(r_start + s * (r_goal - r_start))
        misalign.append(m_start)
        phase.append(PHASE_ALIGNMENT_SOFT_DOCK)
    z = float(p_goal[2])
    while -z > p.soft_dock_distance_m + 1e-12:
        if envelope:
            speed = env_speed
        else:
            speed = p.final_speed_mps if -z > p.slow_distance_m else p.contact_speed_mps
        z_new = z + speed * dt  # ends on the first sample at or inside the soft-dock distance
        p_new = np.array([p_goal[0], p_goal[1], z_new])
        vel.append(np.array([0.0, 0.0, (z_new - z) / dt]))
        pos.append(p_new)
        rot.append(r_goal.copy())
        misalign.append(m_start)
        phase.append(PHASE_ALIGNMENT_SOFT_DOCK)
        z = z_new

    if offaxis_m:
        off = off_axis_offsets(np.random.default_rng([seed, 11]), np.stack(pos)[:, 2], offaxis_m, n1, dt)
        pos = [q + np.array([o[0], o[1], 0.0]) for q, o in zip(pos, off, strict=True)]
        dv = np.gradient(off, dt, axis=0)
        vel = [v + np.array([w[0], w[1], 0.0]) for v, w in zip(vel, dv, strict=True)]
    if turned_deg:
        axis_rad = np.random.default_rng([seed, 7]).uniform(0.0, 2 * np.pi)
        turn = np.radians(turned_deg) * np.array([np.cos(axis_rad), np.sin(axis_rad), 0.0])
        rot = [r + turn for r in rot]
        misalign = [m + turn for m in misalign]
    n = len(pos)
    R = np.stack([rotvec_to_matrix(r) for r in rot])
    if rolled_deg:
        R_roll = rotvec_to_matrix(np.array([0.0, 0.0, np.radians(rolled_deg)]))
        R = R @ R_roll
        misalign = [matrix_to_rotvec(rotvec_to_matrix(m) @ R_roll) for m in misalign]
    info = {
        "waypoint_a_m": wp_a.tolist(),
        "waypoint_b_m": wp_b.tolist(),
        "duration_s": round((n - 1) * dt, 3),
        "envelope_misalignment_deg": float(np.degrees(np.linalg.norm(env_rotvec))),
        "envelope_closing_speed_mps": float(env_speed) if envelope else None,
        "turned_deg": float(turned_deg),
        "offaxis_m": float(offaxis_m),
        "rolled_deg": float(rolled_deg),
    }
    return Trajectory(
        t_s=np.round(np.arange(n) * dt, 6),
        phase=np.array(phase, dtype=np.int8),
        p_t_s=np.stack(pos),
        R_t_s=R,
        v_t_s=np.stack(vel),
        misalignment_rotvec_rad=np.stack(misalign),
        params=p,
        seed=seed,
        envelope=envelope,
        info=info,
    )


OFFAXIS_MAX_ANGLE = 0.15  # lateral offset / distance (8.5 deg): the fixture stays in view at 0.5 m
# the shortest and longest period of the wander's two slow motions (turn about the axis, size), s
OFFAXIS_PERIOD_S = (40.0, 120.0)


def off_axis_offsets(
    rng: np.random.Generator, z_m: np.ndarray, max_m: float, first: int, dt_s: float
) -> np.ndarray:
    """(n, 2) lateral offsets (m) for samples at z (chaser z in F_t, negative): 0 before sample
    `first`, then ramping in over 20 s to a slow wander. Its size drifts between 30 % and 100 %
    of max_m and its direction turns at a random rate, both smooth; capped at
    OFFAXIS_MAX_ANGLE x distance."""
    n = len(z_m)
    t = np.maximum(np.arange(n) - first, 0) * dt_s
    phase0, phase1 = rng.uniform(0.0, 2 * np.pi, 2)
    w_dir = 2 * np.pi / rng.uniform(*OFFAXIS_PERIOD_S) * rng.choice([-1.0, 1.0])
    w_mag = 2 * np.pi / rng.uniform(*OFFAXIS_PERIOD_S)
    mag = max_m * (0.65 + 0.35 * np.sin(phase1 + w_mag * t))
    mag = np.minimum(mag, OFFAXIS_MAX_ANGLE * np.abs(z_m))
    ramp = np.array([_smoothstep(x) for x in t / 20.0])
    ramp[: min(first, n)] = 0.0
    a = phase0 + w_dir * t
    return (ramp * mag)[:, None] * np.stack([np.cos(a), np.sin(a)], axis=1)


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


def _random_lateral(rng: np.random.Generator, max_m: float) -> np.ndarray:
    r = max_m * np.sqrt(rng.uniform())
    a = rng.uniform(0.0, 2 * np.pi)
    return np.array([r * np.cos(a), r * np.sin(a)])


def params_dict(p: TrajectoryParams) -> dict:
    return asdict(p)
