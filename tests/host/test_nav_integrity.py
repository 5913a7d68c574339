"""The navigator's integrity check of the camera's attitude against the vehicle's own
(oibar.nav.integrity): campaign cnn_300's mission 71, where the network misread the fixture's tilt
by 15 deg at high confidence and guidance followed the reading 1.9 m off the docking axis.

The estimator here reads a fixed pose: the true bearing and range with the tilt misread, as the
network did; the navigator, the filter, the daemon, the flight log and the replay are the real ones.
"""

import numpy as np
import pytest
from test_nav_daemon import FakeLink, RecordingVehicle, decoded, grey

from oibar.camera import CallableSource
from oibar.geometry.docking import camera_pose_from_docking, lateral_offset_m
from oibar.geometry.rotations import matrix_to_quat
from oibar.nav.core import Navigator
from oibar.nav.daemon import DaemonParams, NavDaemon
from oibar.nav.flightlog import FlightLog
from oibar.nav.guidance import Guidance, MissionParams
from oibar.nav.integrity import AttitudeCheckParams, check_attitude, disagreement_deg, valid_reference
from oibar.nav.pose import PoseEstimate
from oibar.nav.replay import replay
from oibar.nav.vehicle import RelativeAttitude

R_TRUE_D_M = np.array([0.04, -0.03, 7.0])  # probe tip 5 cm off the axis, 7 m out
ATT_TRUE_RAD = np.radians([1.0, -0.5, 0.3])  # the chaser's true attitude error


def misread(tilt_deg):
    """The true pose as the camera sees it, with the attitude read ``tilt_deg`` off about the
    camera's x axis (a tilt), and the translation (bearing and range) right."""
    T, _ = camera_pose_from_docking(R_TRUE_D_M, ATT_TRUE_RAD)
    _, R_bad = camera_pose_from_docking(np.zeros(3), ATT_TRUE_RAD + np.radians([tilt_deg, 0.0, 0.0]))
    return T, R_bad


class MisreadingEstimator:
    path = "misreading-estimator"
    meta = {"model_version": "test"}
    size_wh = (64, 40)

    def __init__(self, tilt_deg, confidence=0.95):
        self.T, self.R = misread(tilt_deg)
        self.confidence = confidence

    def estimate(self, image, t_s=0.0):
        T, R = self.T.copy(), self.R.copy()
        return PoseEstimate(T, matrix_to_quat(R), R, t_s, 1.0, self.confidence, float(np.linalg.norm(T)), 0.0)


def vehicle_ref(t_s, bias_deg=(0.8, -0.6, 0.4), sigma_deg=1.0):
    return RelativeAttitude(t_s, ATT_TRUE_RAD + np.radians(bias_deg), float(np.radians(sigma_deg)))


def fly(tilt_deg, with_ref, frames=20):
    nav = Navigator(MisreadingEstimator(tilt_deg))
    steps = [
        nav.step(0.1 * k, grey(), frame_t_s=0.1 * k, attitude_ref=vehicle_ref(0.1 * k) if with_ref else None)
        for k in range(frames)
    ]
    return nav, steps


def lateral_error_m(step):
    return lateral_offset_m(step.solution.r_D_m[:2] - R_TRUE_D_M[:2])


def test_a_tilt_misread_beyond_the_bound_is_fused_with_the_vehicles_attitude():
    _, blind = fly(15.0, with_ref=False)
    assert blind[-1].solution.valid and not blind[-1].hold_reason
    assert lateral_error_m(blind[-1]) > 1.5, "the misread tilt turns the 7 m bearing 1.8 m off the axis"
    _, checked = fly(15.0, with_ref=True)
    last = checked[-1]
    assert last.solution.valid and not last.hold_reason, "the approach goes on, on the vehicle's attitude"
    assert all(s.attitude_check is not None and s.attitude_check.replaced for s in checked)
    assert last.attitude_check.disagreement_deg == pytest.approx(15.0, abs=1.5)
    assert last.attitude_check.limit_deg == pytest.approx(5.0 + 3.0 * 1.0)
    # what is left: the vehicle's own 1 deg error turned through 7 m, not the camera's 15 deg
    assert lateral_error_m(last) < 0.2
    assert np.degrees(np.linalg.norm(last.solution.att_rad - ATT_TRUE_RAD)) < 2.0


def test_an_attitude_within_the_bound_is_used_as_read():
    """A reading the bound allows is the camera's own: the check replaces nothing, and the
    navigation is the one it was without a vehicle attitude, to the bit."""
    _, blind = fly(4.0, with_ref=False)
    _, checked = fly(4.0, with_ref=True)
    assert all(s.attitude_check is not None and not s.attitude_check.replaced for s in checked)
    assert checked[-1].attitude_check.disagreement_deg == pytest.approx(4.0, abs=1.5)
    assert np.array_equal(checked[-1].solution.r_D_m, blind[-1].solution.r_D_m)
    assert np.array_equal(checked[-1].solution.att_rad, blind[-1].solution.att_rad)


def test_the_bound_widens_with_the_vehicles_own_uncertainty():
    T, R = misread(10.0)
    sharp = vehicle_ref(0.0, bias_deg=(0, 0, 0), sigma_deg=1.0)  # bound 5 + 3 x 1 = 8 deg
    vague = vehicle_ref(0.0, bias_deg=(0, 0, 0), sigma_deg=2.0)  # bound 11 deg
    assert check_attitude(T, R, sharp)[2].replaced
    assert not check_attitude(T, R, vague)[2].replaced
    assert check_attitude(T, R, vague, AttitudeCheckParams(limit_deg=2.0))[2].replaced
    assert disagreement_deg(R, ATT_TRUE_RAD) == pytest.approx(10.0, abs=0.5)


@pytest.mark.parametrize(
    "bad",
    [
        None,
        (0.0, [0.0, 0.0], 0.01),  # not 3 axes
        (0.0, [0.0, float("nan"), 0.0], 0.01),
        (0.0, [0.0, 0.0, 0.0], 0.0),  # no sigma: no bound can be drawn from it
        (0.0, [0.0, 0.0, 0.0], float("inf")),
        (float("nan"), [0.0, 0.0, 0.0], 0.01),
        "not an attitude",
        (0.0,),
    ],
)
def test_a_malformed_vehicle_attitude_leaves_the_frame_unchecked(bad):
    assert valid_reference(bad) is None
    nav = Navigator(MisreadingEstimator(15.0))
    step = nav.step(0.0, grey(), frame_t_s=0.0, attitude_ref=bad)
    assert step.attitude_check is None and step.solution.valid


class AttitudeVehicle(RecordingVehicle):
    """A vehicle whose GNC knows the relative attitude; ``fail``: its sensor raises."""

    def __init__(self, fail=False):
        super().__init__()
        self.fail = fail

    def relative_attitude(self, t_s):
        if self.fail:
            raise OSError("star tracker blinded")
        return vehicle_ref(t_s)


def daemon(vehicle, log=None):
    return NavDaemon(
        Navigator(MisreadingEstimator(15.0)),
        Guidance(MissionParams(nav_lost_abort_s=60.0)),
        CallableSource(lambda t: grey(), rate_hz=100.0),
        link=FakeLink(),
        vehicle=vehicle,
        log=log,
        params=DaemonParams(rate_hz=50.0, status_every_s=10.0),
    )


def test_the_daemon_checks_every_frame_logs_the_verdict_and_replays_it(tmp_path):
    log = FlightLog(tmp_path / "flight.mcap", frames=True)
    d = daemon(AttitudeVehicle(), log)
    summary = d.run(max_cycles=25)
    assert summary["frames_used"] >= 20
    assert summary["attitude_replaced"] == summary["frames_used"]
    assert "ATT: vehicle's (camera 1" in d.status_line(), "the operator sees it live"
    assert lateral_offset_m(d.nav.filter.state(d.clock() - d._t0).r_D_m[:2] - R_TRUE_D_M[:2]) < 0.2
    cycles = [c for c in decoded(tmp_path / "flight.mcap", "/nav/cycle") if c.has_frame]
    att = [c.vehicle_attitude for c in cycles]
    assert all(a.checked and a.replaced and 13.0 < a.disagreement_deg < 17.0 for a in att)
    assert list(att[0].att_rad) == pytest.approx(list(vehicle_ref(0.0).att_rad))
    # replay feeds the recorded attitude again: the same filter, bit for bit
    res = replay(tmp_path / "flight.mcap", Navigator(MisreadingEstimator(15.0)))
    assert res.exact and res.filter_exact == res.filter_compared > 0


def test_a_failing_vehicle_attitude_leaves_navigation_on_the_camera():
    d = daemon(AttitudeVehicle(fail=True))
    summary = d.run(max_cycles=20)
    assert summary["attitude_errors"] == summary["cycles"] == 20
    assert summary["attitude_replaced"] == 0 and summary["frames_used"] >= 15


def test_the_udp_vehicle_takes_the_gnc_attitude_back():
    """The GNC computer's datagram may carry the relative attitude, with the odometry or alone.
    The newest valid one is kept (not used up: every frame is checked against it) until it is
    stale; a malformed one is counted and ignored, and a bad attitude does not lose the odometry."""
    import json
    import socket
    import time

    from oibar.nav.vehicle import open_vehicle

    gnc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gnc.bind(("127.0.0.1", 0))
    gnc.settimeout(2.0)
    v = open_vehicle(f"udp://127.0.0.1:{gnc.getsockname()[1]}")
    try:
        assert v.relative_attitude(0.0) is None
        v.send(10.0, np.zeros(3), np.zeros(3), "APPROACH")
        _, daemon_addr = gnc.recvfrom(2048)

        def reply(now_s, n_more, **msg):
            """Send one datagram; drain until ``n_more`` more verdicts were counted."""
            gnc.sendto(json.dumps(msg).encode(), daemon_addr)
            seen = lambda: v.attitude_received + v.attitude_rejected + v.odometry_received  # noqa: E731
            want, deadline = seen() + n_more, time.monotonic() + 2.0
            while seen() < want and time.monotonic() < deadline:
                v.drain(now_s)
                time.sleep(0.005)

        reply(10.1, 1, att_rad=[0.01, -0.02, 0.0], att_sigma_rad=0.02, t_s=10.05)  # alone
        att = v.relative_attitude(10.1)
        assert att.t_s == pytest.approx(10.05) and att.sigma_rad == pytest.approx(0.02)
        assert list(att.att_rad) == pytest.approx([0.01, -0.02, 0.0])
        assert v.relative_attitude(10.2) is not None, "kept for the next frame's check"
        assert v.relative_velocity(10.2) is None and v.odometry_rejected == 0
        # with the odometry, one bad half: the attitude is refused, the odometry kept
        reply(
            10.3,
            2,
            v_D_mps=[0.0, 0.0, -0.03],
            sigma_mps=0.003,
            att_rad=[0.0, float("nan"), 0.0],
            att_sigma_rad=0.02,
            t_s=10.3,
        )
        assert v.attitude_rejected == 1 and v.relative_velocity(10.3) is not None
        assert v.relative_attitude(10.3).t_s == pytest.approx(10.05), "the last good one"
        reply(
            10.4,
            2,
            v_D_mps=[0.0, 0.0, -0.03],
            sigma_mps=0.003,
            att_rad=[0.03, 0.0, 0.0],
            att_sigma_rad=0.02,
            t_s=10.4,
        )
        assert v.relative_attitude(10.4).att_rad[0] == pytest.approx(0.03)
        assert v.relative_attitude(11.0) is None, "0.6 s old: stale"
        assert v.statistics()["attitude_received"] == 2 and v.statistics()["attitude_rejected"] == 1
    finally:
        v.close()
        gnc.close()
