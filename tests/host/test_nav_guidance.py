"""Guidance's hold and abort rules (oibar.nav.guidance), on hand-made navigation solutions."""

import numpy as np
import pytest

from oibar import pb
from oibar.nav.guidance import Guidance, MissionParams, NavSolution, Observation


def telemetry(state="STATE_IDLE", contact=False):
    tm = pb.Telemetry()
    tm.state = pb.State.Value(state)
    tm.contact = contact
    return tm


def nav(range_m=5.0, lateral=(0.0, 0.0), valid=True, hold_reason=""):
    return NavSolution(
        valid=valid,
        r_D_m=np.array([lateral[0], lateral[1], range_m]),
        confidence=0.9,
        hold_reason=hold_reason,
    )


def obs(t_s, n, link_up=True, tm=None):
    return Observation(t_s, n, link_up, tm if tm is not None else telemetry())


def test_approach_closes_on_a_trusted_solution_and_centres_laterally():
    g = Guidance(MissionParams())
    out = g.step(0.0, obs(0.0, nav(5.0, lateral=(0.2, -0.1))))
    assert out.v_sp_D_mps[2] < 0, "closing"
    assert out.v_sp_D_mps[0] < 0 and out.v_sp_D_mps[1] > 0, "steers towards the axis"
    assert out.phase == "FORCED_TRANSLATION"


@pytest.mark.parametrize(
    "n",
    [
        nav(hold_reason="gated outlier"),
        nav(hold_reason="low confidence 0.20"),
        nav(valid=False, hold_reason="filter not initialised"),
    ],
)
def test_untrusted_navigation_holds(n):
    g = Guidance(MissionParams())
    out = g.step(0.0, obs(0.0, n))
    assert out.phase == "HOLD"
    assert np.all(out.v_sp_D_mps == 0) and np.all(out.w_sp_rad_s == 0)
    assert out.nav.confidence == (0.0 if not n.valid else pytest.approx(0.9))


def test_an_invalid_solution_says_so_and_carries_no_data():
    """Issue 17: an uninitialised filter (zeros everywhere) went out as a perfect NavUpdate:
    closing speed 0, misalignment 0, only the confidence 0. It must say valid = false and carry
    none of those fields; a valid one says valid = true."""
    g = Guidance(MissionParams())
    n = NavSolution(valid=False, hold_reason="filter not initialised")
    out = g.step(0.0, obs(0.0, n))
    sent = {f.name for f, _ in out.nav.ListFields()}
    assert not out.nav.valid
    assert sent <= {"frame_id", "stamp_ms", "phase"}, sent
    assert not out.nav.HasField("t_cam_target_m") and not out.nav.HasField("q_cam_target")
    good = g.step(0.1, obs(0.1, nav(5.0)))
    assert good.nav.valid and good.nav.range_m == pytest.approx(5.0)
    assert good.nav.HasField("q_cam_target")


def test_a_dock_lost_on_the_link_is_sent_again():
    """Issue 17: the "DOCK sent" latch was set before sending and never cleared when the request
    came back LinkDown / LinkTimeout: one lost DOCK left the MCU in RECEPTION until its capture
    timeout, a good capture turned into a fault. After a lost DOCK, guidance sends it again."""
    from oibar.nav.guidance import RequestResult

    tm = telemetry("STATE_RECEPTION", contact=True)
    tm.latch_engaged = True
    g = Guidance(MissionParams())
    g.contacted = True
    first = g.step(0.0, obs(0.0, nav(0.0), tm=tm)).request
    assert first is not None and first.opcode == pb.CMD_DOCK
    for t, reason in ((0.1, "LinkTimeout"), (0.3, "LinkDown")):
        res = RequestResult(first, False, reason)
        again = g.step(t, Observation(t, nav(0.0), True, tm, results=[res])).request
        assert again is not None and again.opcode == pb.CMD_DOCK, reason
        first = again
    # a DOCK the MCU accepted is not sent twice
    ok = RequestResult(first, True, "NACK_NONE", "STATE_SOFT_DOCKED")
    assert g.step(0.5, Observation(0.5, nav(0.0), True, tm, results=[ok])).request is None


def test_link_down_holds_and_sends_no_command():
    g = Guidance(MissionParams(arm_range_m=2.0))
    out = g.step(0.0, obs(0.0, nav(1.5), link_up=False))
    assert out.phase == "HOLD" and np.all(out.v_sp_D_mps == 0)
    assert out.request is None
    out = g.step(0.1, obs(0.1, nav(1.5), link_up=True))  # link back: arm
    assert out.request is not None and out.request.label == "CMD_APPROACH_ARM"


def test_no_arm_command_on_an_untrusted_range():
    g = Guidance(MissionParams(arm_range_m=2.0))
    out = g.step(0.0, obs(0.0, nav(1.5, hold_reason="gated outlier")))
    assert out.request is None


def test_navigation_lost_holds_then_aborts_with_a_blind_retreat():
    m = MissionParams(nav_lost_abort_s=2.0, blind_retreat_s=3.0)
    g = Guidance(m)
    lost = nav(valid=False, hold_reason="camera: unplugged")
    t = 0.0
    while t < 1.95:
        out = g.step(t, obs(t, lost))
        assert out.phase == "HOLD" and not g.mission_aborted
        t += 0.1
    out = g.step(2.05, obs(2.05, lost))
    assert g.mission_aborted
    assert out.phase == "RETREAT" and out.v_sp_D_mps[2] > 0, "backs off along +z_D"
    assert np.all(out.v_sp_D_mps[:2] == 0) and np.all(out.w_sp_rad_s == 0)
    out = g.step(5.2, obs(5.2, lost))
    assert g.finished and g.outcome == "aborted"
    assert np.all(out.v_sp_D_mps == 0)


def test_navigation_back_before_the_timeout_resumes_the_approach():
    g = Guidance(MissionParams(nav_lost_abort_s=2.0))
    g.step(0.0, obs(0.0, nav(valid=False, hold_reason="camera: gone")))
    g.step(1.0, obs(1.0, nav(valid=False, hold_reason="camera: gone")))
    out = g.step(1.5, obs(1.5, nav(4.0)))
    assert not g.mission_aborted and out.v_sp_D_mps[2] < 0
    g.step(3.0, obs(3.0, nav(valid=False, hold_reason="camera: gone")))  # the clock restarts
    assert not g.mission_aborted


def test_docked_states_do_not_abort_on_navigation_loss():
    g = Guidance(MissionParams(nav_lost_abort_s=1.0))
    for k in range(40):
        t = k * 0.1
        out = g.step(
            t, obs(t, nav(valid=False, hold_reason="camera: gone"), tm=telemetry("STATE_HARD_DOCKED", True))
        )
    assert not g.mission_aborted, "docked, the camera is not needed: no abort"
    assert np.all(out.v_sp_D_mps == 0)


def test_attitude_is_left_to_the_vehicle_unless_steering_is_enabled():
    g = Guidance(MissionParams())
    n = nav(5.0)
    n.att_rad = np.radians([5.0, -4.0, 0.0])
    assert np.all(g.step(0.0, obs(0.0, n)).w_sp_rad_s == 0)


def test_attitude_inside_the_deadband_is_left_alone_outside_it_is_corrected():
    g = Guidance(MissionParams(steer_attitude=True))
    n = nav(5.0)
    n.att_rad = np.radians([2.5, 1.0, 0.0])  # a typical network error: no rate command
    out = g.step(0.0, obs(0.0, n))
    assert np.all(out.w_sp_rad_s == 0)
    n.att_rad = np.radians([5.0, -4.0, 0.0])  # a real misalignment: turned back
    out = g.step(0.1, obs(0.1, n))
    assert out.w_sp_rad_s[0] < 0 and out.w_sp_rad_s[1] > 0


def test_approach_corridor_stops_closing_outside_and_backs_off_far_outside():
    from oibar.nav.guidance import corridor_half_width_m

    assert corridor_half_width_m(5.0) == pytest.approx(0.5) and corridor_half_width_m(0.1) == pytest.approx(
        0.05
    )
    g = Guidance(MissionParams())
    inside = g.step(0.0, obs(0.0, nav(3.0, lateral=(0.2, 0.0))))
    assert inside.v_sp_D_mps[2] < 0, "inside the corridor: closing"
    outside = g.step(0.1, obs(0.1, nav(3.0, lateral=(0.4, 0.0))))
    assert outside.v_sp_D_mps[2] == 0 and outside.v_sp_D_mps[0] < 0 and outside.phase == "HOLD"
    far = g.step(0.2, obs(0.2, nav(3.0, lateral=(0.7, 0.0))))
    assert far.v_sp_D_mps[2] > 0 and far.v_sp_D_mps[0] < 0 and far.phase == "RETREAT"


def test_a_command_refused_for_a_lasting_reason_ends_the_mission_safely():
    """Issue 59's fault matrix: with a supply below the target tank (back-flow) or a stuck switch
    the MCU refuses ARM or START for a precondition, and guidance asked again every cycle for
    ever, the mission never ending. After MAX_REFUSALS refusals in a row the mission is aborted,
    so the sequence goes on to its safe end (here: hard-docked and aborted, it unmates). A
    refusal that passes (the link, a busy MCU) or an accepted command starts the count again."""
    from oibar.nav.guidance import MAX_REFUSALS, RequestResult

    tm = telemetry("STATE_HARD_DOCKED", contact=True)
    g = Guidance(MissionParams())
    g.contacted = True
    req = g.step(0.0, obs(0.0, nav(0.0), tm=tm)).request
    assert req is not None and req.opcode == pb.CMD_ARM_TRANSFER
    t = 0.0
    for k in range(1, MAX_REFUSALS):
        t += 0.1
        reason = "NACK_BUSY" if k == 5 else "NACK_PRECONDITION_FAILED"  # a passing refusal in between
        res = RequestResult(req, False, reason)
        req = g.step(t, Observation(t, nav(0.0), True, tm, results=[res])).request
        assert req is not None and req.opcode == pb.CMD_ARM_TRANSFER and not g.mission_aborted, k
    for _ in range(6):  # the count started again after the passing refusal (14 so far): six more
        t += 0.1
        res = RequestResult(req, False, "NACK_PRECONDITION_FAILED")
        req = g.step(t, Observation(t, nav(0.0), True, tm, results=[res])).request
    assert g.mission_aborted and any("refused" in n for _, n in g.notes)
    assert req is None or req.opcode != pb.CMD_ARM_TRANSFER  # no more asking: valves closed, unmate next


def test_a_clear_accepted_after_guidance_gave_up_is_followed_not_called_safed():
    """The fault matrix's overpressure@reception: guidance's third CLEAR_FAULT went out while the
    tank was still high, it gave up ("holding, valves closed"), and the answer that came back
    accepted the clear: the MCU let the probe go and homed the latch (D1), which takes longer
    than the 5 s hold, and the mission was called safed in LATCH_RESET. Leaving FAULT now takes
    the give-up back."""
    from oibar.nav.guidance import MAX_CLEAR_ATTEMPTS, SAFED_HOLD_S, RequestResult

    g = Guidance(MissionParams())
    g.contacted = True
    fault = telemetry("STATE_FAULT")
    t, results = 0.0, []
    for _ in range(MAX_CLEAR_ATTEMPTS + 1):
        req = g.step(t, Observation(t, nav(0.0), True, fault, results=results)).request
        results = [RequestResult(req, False, "NACK_PRECONDITION_FAILED")] if req is not None else []
        t += 2.5
    assert g.gave_up_at is not None
    reset = telemetry("STATE_LATCH_RESET")
    for _ in range(int(SAFED_HOLD_S / 0.1) + 20):
        g.step(t, obs(t, nav(0.0), tm=reset))
        t += 0.1
    assert g.gave_up_at is None and g.outcome != "safed"


def test_a_misaligned_vehicle_held_at_the_gate_turns_its_boresight_in_without_steering():
    # campaign truth_1000, mission 12: a start turned 5.6 deg held at the gate until the mission
    # timed out, since nothing turned the vehicle with steer_attitude off
    g = Guidance(MissionParams())
    n = nav(0.5)
    n.att_rad = np.radians([6.0, -2.0, 30.0])  # tilted 6.3 deg, rolled 30 deg
    n.misalignment_deg = 6.3
    out = g.step(0.0, obs(0.0, n, tm=telemetry("STATE_APPROACH_READY")))
    assert out.phase == "HOLD"
    w = out.w_sp_rad_s
    assert w[0] < 0 and w[1] > 0 and w[2] == 0  # the tilt turned in, the roll left alone
    far = nav(5.0)
    far.att_rad, far.misalignment_deg = n.att_rad, n.misalignment_deg
    assert np.all(Guidance(MissionParams()).step(0.0, obs(0.0, far)).w_sp_rad_s == 0)  # only at the gate
    aligned = nav(0.5)
    aligned.att_rad, aligned.misalignment_deg = np.radians([3.0, 0.0, 30.0]), 3.0
    out = Guidance(MissionParams()).step(0.0, obs(0.0, aligned, tm=telemetry("STATE_APPROACH_READY")))
    assert np.all(out.w_sp_rad_s == 0)  # within the gate: nothing to turn


def test_held_at_the_gate_too_long_aborts_the_mission_and_says_why():
    g = Guidance(MissionParams(gate_hold_max_s=60.0))
    n = nav(0.5)  # aligned and centred, but the MCU never arms (stays IDLE)
    for t in np.arange(0.0, 59.0, 0.5):
        g.step(float(t), obs(float(t), n, tm=telemetry("STATE_IDLE")))
    assert not g.mission_aborted
    for t in np.arange(59.0, 61.0, 0.5):
        out = g.step(float(t), obs(float(t), n, tm=telemetry("STATE_IDLE")))
    assert g.mission_aborted
    assert any(
        "held at the gate for 60 s" in text and "MCU IDLE, not APPROACH_READY" in text for _, text in g.notes
    )
    assert out.v_sp_D_mps[2] > 0  # backing off
