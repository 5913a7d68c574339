"""Plant unit tests: the capture envelope, the probe, the gas model, the valves."""

import numpy as np
import pytest

from oibar_hil.rig.lockstep import DO, McuReply
from oibar_hil.rig.mechanism import Mechanism, MechanismParams, Valve
from oibar_hil.rig.world import VehicleParams, World, WorldState


def reply(**outputs) -> McuReply:
    bits = sum(1 << DO.index(k) for k, v in outputs.items() if v)
    fields = {f: 0 for f in McuReply.__dataclass_fields__}
    fields["do_bits"] = bits
    return McuReply(**fields)


def approach(speed_mps=0.03, misalign_deg=(0.0, 0.0), lateral_m=(0.0, 0.0), push=True):
    rng = np.random.default_rng(0)
    world = World(
        VehicleParams(accel_noise_mps2=0.0, ang_noise_rad_s2=0.0),
        WorldState(
            r_D_m=np.array([lateral_m[0], lateral_m[1], 0.01]),
            v_D_mps=np.array([0.0, 0.0, -speed_mps]),
            att_rad=np.radians([misalign_deg[0], misalign_deg[1], 0.0]),
        ),
        rng,
    )
    mech = Mechanism(MechanismParams(adc_noise_counts=0.0), rng)
    world.set_setpoint(np.array([0.0, 0.0, -(0.05 if push else speed_mps)]), np.zeros(3))
    t, out, max_force = 0.0, reply(), 0.0
    for _ in range(1000):  # 10 s
        t += 0.01
        f = mech.step(0.01, t, out, world)
        world.step(0.01, f)
        mech.after_motion(world)
        max_force = max(max_force, mech.contact_force_n)
        if mech.latched:
            break
    return mech, world, max_force


def test_capture_inside_the_envelope_latches_softly():
    mech, world, max_force = approach(0.03, (3.0, 2.0), (0.03, 0.02))
    assert mech.capture_record and mech.capture_record["captured"]
    assert mech.latched and mech.contact
    assert max_force < 30.0  # paper: soft docking under 30 N
    assert world.lateral_m < 0.002 and world.misalignment_deg < 1.0  # the funnel centred it


@pytest.mark.parametrize(
    "speed, misalign, lateral",
    [
        (0.060, (0.0, 0.0), (0.0, 0.0)),  # too fast (> 50 mm/s)
        (0.030, (9.0, 6.0), (0.0, 0.0)),  # combined misalignment 10.8 deg
        (0.030, (0.0, 0.0), (0.08, 0.08)),  # outside the funnel mouth
    ],
)
def test_capture_outside_the_envelope_bounces(speed, misalign, lateral):
    mech, world, _ = approach(speed, misalign, lateral, push=False)
    first = mech.capture_attempts[0]
    assert not first["captured"]  # the probe glanced off (the SV may come back slower)
    assert mech.capture_record is None or mech.capture_record["t_s"] > first["t_s"]


def test_capture_at_the_envelope_edge():
    mech, _, _ = approach(0.0495, (7.0, 7.0))  # 49.5 mm/s, 9.9 deg
    assert mech.capture_record is not None


def test_latched_probe_is_held_until_the_cam_releases_it():
    mech, world, _ = approach()
    world.set_setpoint(np.array([0.0, 0.0, 0.03]), np.zeros(3))  # back away
    for i in range(300):
        f = mech.step(0.01, 10 + i * 0.01, reply(), world)
        world.step(0.01, f)
        mech.after_motion(world)
    assert mech.latched and -world.range_m >= mech.p.latch_depth_m - mech.p.latch_hold_margin_m - 1e-9
    mech.latch_steps = mech.p.latch_release_steps + 10  # cam turned to release
    for i in range(600):
        f = mech.step(0.01, 20 + i * 0.01, reply(LATCH_ENABLE=True), world)
        world.step(0.01, f)
        mech.after_motion(world)
    assert not mech.latched and not mech.contact and world.range_m > 0.0


def test_gas_model_conserves_mass_and_fills_towards_equilibrium():
    p = MechanismParams()
    mech = Mechanism(p, np.random.default_rng(0))
    mech.latched, mech.plane_mm = True, p.plane_travel_mm  # hard-docked: couplings mated
    mech.sv_valve.open = mech.tv_valve.open = True
    mech.sv_valve.cmd_open = mech.tv_valve.cmd_open = True
    total0 = mech.sv_kpa * p.sv_volume_l + mech.tv_kpa * p.tv_volume_l + mech.line_kpa * p.line_volume_l
    for _ in range(40000):  # 400 s, about 11 time constants
        mech._gas(0.01)
    total = mech.sv_kpa * p.sv_volume_l + mech.tv_kpa * p.tv_volume_l + mech.line_kpa * p.line_volume_l
    assert total == pytest.approx(total0, rel=1e-9)
    eq = total0 / (p.sv_volume_l + p.tv_volume_l + p.line_volume_l)
    assert mech.tv_kpa == pytest.approx(eq, abs=5.0) and mech.fuel_lost_kg == 0.0


def test_half_mated_coupling_with_an_open_valve_vents():
    p = MechanismParams()
    mech = Mechanism(p, np.random.default_rng(0))
    mech.latched, mech.plane_mm = True, 36.0
    mech.sv_valve.open = True
    mech._gas(0.1)
    assert mech.fuel_lost_kg > 0.0


def test_valve_follows_its_coil_after_the_stroke_time():
    v = Valve()
    v.step(0.03, True, 0.05)
    assert not v.open
    v.step(0.03, True, 0.05)
    assert v.open
    v.stuck = "open"
    v.step(0.1, False, 0.05)
    assert v.open


def _drift(params, seed=4, steps=500):
    world = World(
        params,
        WorldState(r_D_m=np.array([0.0, 0.0, 2.0]), v_D_mps=np.array([0.0, 0.0, -0.03])),
        np.random.default_rng(seed),
    )
    world.set_setpoint(np.array([0.01, 0.0, -0.03]), np.zeros(3))
    odo = []
    for k in range(steps):
        world.step(0.01, np.zeros(3))
        if k % 10 == 0:
            m = world.relative_velocity(k * 0.01)
            odo.append(None if m is None else (m, world.s.v_D_mps.copy()))
    return world, odo


def test_the_vehicles_odometry_is_the_truth_plus_its_noise_and_leaves_the_world_alone():
    p = VehicleParams()
    world, odo = _drift(p)
    errs = np.array([m.v_D_mps - v for m, v in odo])
    assert all(m.sigma_mps == p.odometry_sigma_mps and m.t_s >= 0 for m, _ in odo)
    # white part ~ the reported sigma, around a constant per-approach error of ~odometry_bias_mps
    assert np.std(errs, axis=0) == pytest.approx(np.full(3, p.odometry_sigma_mps), rel=0.35)
    assert np.all(np.abs(np.mean(errs, axis=0)) < 4 * p.odometry_bias_mps + 0.003)
    # switched off: no measurement, and the world moves exactly as with it (own noise stream)
    quiet, odo_off = _drift(VehicleParams(odometry=False))
    assert all(m is None for m in odo_off)
    np.testing.assert_array_equal(quiet.s.r_D_m, world.s.r_D_m)
    np.testing.assert_array_equal(quiet.s.v_D_mps, world.s.v_D_mps)


def _turning(params, seed=5, steps=3000):
    """A world turning slowly on guidance's rate setpoint: what its GNC reports of the relative
    attitude every 10th step, beside the truth; and the odometry it reports the while."""
    world = World(params, WorldState(), np.random.default_rng(seed))
    world.set_setpoint(np.zeros(3), np.radians([0.3, -0.1, 0.05]))
    att, odo = [], []
    for k in range(steps):
        world.step(0.01, np.zeros(3))
        if k % 10 == 0:
            m = world.relative_attitude(k * 0.01)
            att.append(None if m is None else (m, world.s.att_rad.copy()))
            odo.append(world.relative_velocity(k * 0.01))
    return world, att, odo


def test_the_vehicles_attitude_is_the_truth_plus_its_errors_and_leaves_the_world_alone():
    p = VehicleParams()
    world, att, odo = _turning(p)
    errs = np.degrees(np.array([m.att_rad - a for m, a in att]))
    sigma_deg = np.hypot(p.attitude_ref_bias_deg, p.attitude_ref_noise_deg)
    assert all(np.degrees(m.sigma_rad) == pytest.approx(sigma_deg) for m, _ in att)
    # it follows the truth as the chaser turns (9 deg here), off by one constant error per approach
    assert np.degrees(np.ptp([a[0] for _, a in att])) > 5.0
    assert np.std(errs, axis=0) == pytest.approx(np.full(3, p.attitude_ref_noise_deg), rel=0.2)
    assert np.all(np.abs(np.mean(errs, axis=0)) < 4 * p.attitude_ref_bias_deg)
    assert np.linalg.norm(np.mean(errs, axis=0)) > 5 * p.attitude_ref_noise_deg, "a constant error, not zero"
    # switched off: no attitude, and the world and its odometry are exactly as with it
    quiet, att_off, odo_off = _turning(VehicleParams(attitude_ref=False))
    assert all(m is None for m in att_off)
    np.testing.assert_array_equal(quiet.s.att_rad, world.s.att_rad)
    np.testing.assert_array_equal([o.v_D_mps for o in odo_off], [o.v_D_mps for o in odo])
