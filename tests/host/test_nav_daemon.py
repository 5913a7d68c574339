"""The navigation daemon's failure behaviour (issue 8 "Failures", issue 11 host robustness):
camera unplugged and replugged, link lost and back, low confidence, log disk full, model file
missing or corrupt, and the replay of a recorded run. The flight log itself (MCAP: its
channels, a kill, exact replay with the real model, the live view) is tested in
test_flightlog.py.

The estimator here is a stand-in that reports a fixed true pose (the network itself is tested
in test_nav_pose.py); everything else is the real daemon: threads, scheduler, filter, guidance,
log.
"""

import os
import threading

import numpy as np
import pytest

from oibar import pb
from oibar.camera import CallableSource, FolderSource
from oibar.cli import main
from oibar.geometry.docking import camera_pose_from_docking
from oibar.geometry.rotations import matrix_to_quat
from oibar.link.core import Request
from oibar.nav.core import Navigator
from oibar.nav.daemon import DaemonParams, NavDaemon
from oibar.nav.flightlog import FlightLog, FlightLogError, inspect_log, read_messages, read_summary
from oibar.nav.guidance import Guidance, MissionParams
from oibar.nav.logschema import ProtobufDecoder
from oibar.nav.pose import PoseEstimate
from oibar.nav.replay import replay
from oibar.nav.vehicle import NullVehicle, RelativeVelocity, VehicleInterface, open_vehicle

R_TRUE_D_M = np.array([0.05, -0.02, 4.0])


class TruthEstimator:
    """Reports the pose the frame's mean brightness encodes (so replay can check it really
    re-reads the frames) with a settable confidence."""

    path = "truth-estimator"
    meta = {"model_version": "test"}
    size_wh = (64, 40)

    def __init__(self, confidence=0.9):
        self.confidence = confidence
        self.calls = 0

    def estimate(self, image, t_s=0.0):
        self.calls += 1
        r = R_TRUE_D_M.copy()
        r[2] = 2.0 + float(np.asarray(image).mean()) / 64.0
        T, R = camera_pose_from_docking(r, np.zeros(3))
        return PoseEstimate(T, matrix_to_quat(R), R, t_s, 1.0, self.confidence, float(np.linalg.norm(T)), 0.0)


class FakeLink:
    def __init__(self):
        self.alive = True
        self.navs = []
        self.commands = []
        self.beats = 0
        self.lock = threading.Lock()
        tm = pb.Telemetry()
        tm.state = pb.STATE_IDLE
        self._tm = tm

    @property
    def link_alive(self):
        return self.alive

    @property
    def telemetry(self):
        return self._tm

    def next_event(self, timeout_s=None):
        return None

    def send_nav_update(self, nav):
        with self.lock:
            self.navs.append(
                (self.alive, {"closing_speed_mps": nav.closing_speed_mps, "valid": nav.valid, "nav": nav})
            )
        return True

    def heartbeat(self, force=False):
        self.beats += 1
        return True

    def submit_command(self, opcode, target_kpa=None):
        with self.lock:
            self.commands.append((self.alive, opcode))
        ack = pb.Ack(accepted=True, reason=pb.NACK_NONE, state=pb.STATE_APPROACH_READY)
        return Request("command", pb.Packet(), done=True, response=ack, response_kind="ack")

    def submit_param_set(self, pid, value):
        raise AssertionError("not used")


class RecordingVehicle(VehicleInterface):
    def __init__(self):
        self.sent = []

    def send(self, t_s, v, w, phase):
        self.sent.append((t_s, np.asarray(v).copy(), phase))


def decoded(path, topic):
    """The messages of one topic of a flight log, decoded."""
    dec = ProtobufDecoder()
    return [
        dec.decode(m.schema_id, m.schema_name, m.schema_data, m.data) for m in read_messages(path, [topic])
    ]


def grey(level=128):
    return np.full((40, 64, 3), level, np.uint8)


def tick(d, wait_s=0.05):
    """One cycle as run() does it: wait (boundedly) for a new frame, then the cycle."""
    return d.cycle(d.wait_frame(until=d.clock() + wait_s))


def make_daemon(camera, link=None, log=None, vehicle=None, confidence=0.9, **params):
    p = DaemonParams(rate_hz=50.0, camera_lost_timeout_s=0.2, camera_retry_s=0.1, status_every_s=10.0)
    for k, v in params.items():
        setattr(p, k, v)
    est = TruthEstimator(confidence)
    return NavDaemon(
        Navigator(est),
        Guidance(MissionParams(nav_lost_abort_s=60.0)),
        camera,
        link=link,
        vehicle=vehicle or RecordingVehicle(),
        log=log,
        params=p,
    )


def test_nominal_cycles_are_logged_and_commanded(tmp_path):
    link = FakeLink()
    log = FlightLog(tmp_path / "flight.mcap")
    veh = RecordingVehicle()
    d = make_daemon(CallableSource(lambda t: grey(), rate_hz=100.0), link=link, log=log, vehicle=veh)
    summary = d.run(max_cycles=30)
    assert summary["cycles"] == 30 and summary["frames_used"] >= 20
    inv = inspect_log(tmp_path / "flight.mcap")
    assert inv.complete and inv.message_counts["/run/info"] >= 1
    assert inv.message_counts["/nav/cycle"] == 30
    footer = read_summary(tmp_path / "flight.mcap")
    assert footer["vehicle"] == {}  # a sink without counters (VehicleInterface default)
    assert footer["summary"]["cycles"] == 30 and footer["log_messages_lost"] == 0
    moving = [v for _, v, ph in veh.sent if ph != "HOLD"]
    assert moving and all(v[2] < 0 for v in moving), "approaching on a trusted solution"
    assert link.navs, "navigation updates reach the MCU"
    assert summary["frame_to_command_ms_p99"] is not None and summary["frame_to_command_ms_p99"] > 0
    assert veh.sent[-1][2] == "HOLD", "shutdown holds the vehicle"


def test_camera_unplugged_and_replugged(tmp_path):
    state = {"plugged": True}

    def render(t):
        if not state["plugged"]:
            raise OSError("camera unplugged")
        return grey()

    d = make_daemon(CallableSource(render, rate_hz=100.0))
    steps = []
    d._t0 = d.clock()
    for k in range(60):
        if k == 15:
            state["plugged"] = False
        if k == 35:
            state["plugged"] = True
        step, out = tick(d)
        steps.append((k, step.hold_reason, out.phase))
        d._stop.wait(0.02)
    d.shutdown()
    lost = [s for s in steps if s[1].startswith("camera:")]
    assert lost, "the loss is reported as the hold reason"
    assert all(ph == "HOLD" for _, _, ph in lost), "guidance holds while the camera is gone"
    assert d.stats.camera_reopens >= 1
    assert not steps[-1][1], f"frames flow again after the replug: {steps[-1]}"


def test_link_lost_holds_the_vehicle_and_commands_nothing():
    link = FakeLink()
    veh = RecordingVehicle()
    d = make_daemon(CallableSource(lambda t: grey(), rate_hz=100.0), link=link, vehicle=veh)
    d._t0 = d.clock()
    for k in range(40):
        link.alive = not (10 <= k < 30)
        tick(d)
        d._stop.wait(0.02)
    d.shutdown()
    assert not [c for c in link.commands if not c[0]], "no mechanism command while the link is down"
    assert not [n for n in link.navs if not n[0]], "no navigation update while the link is down"
    down = veh.sent[11:29]
    assert down and all(ph == "HOLD" and not v.any() for _, v, ph in down)
    assert any(ph != "HOLD" for _, _, ph in veh.sent[31:]), "the approach resumes with the link"


def test_low_confidence_holds():
    link = FakeLink()
    d = make_daemon(CallableSource(lambda t: grey(), rate_hz=100.0), link=link, confidence=0.1)
    d._t0 = d.clock()
    reasons = []
    for _ in range(10):
        step, out = tick(d)
        reasons.append((step.hold_reason, out.phase))
        d._stop.wait(0.02)
    d.shutdown()
    frames = [r for r in reasons if r[0].startswith("low confidence")]
    assert frames and all(ph == "HOLD" for _, ph in frames)


def test_log_disk_full_does_not_stop_navigation():
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    # a flush per cycle: the full disk is met during the run, not at the end
    log = FlightLog("/dev/full", frames=True)
    log.flush_every_s = 0.0
    d = make_daemon(CallableSource(lambda t: grey(), rate_hz=100.0), link=FakeLink(), log=log)
    summary = d.run(max_cycles=15)
    assert summary["cycles"] == 15
    assert log.error and "space" in log.error.lower()
    assert log.messages_lost >= 14


def test_replay_rereads_the_recorded_frames(tmp_path):
    levels = iter(range(40, 240, 4))
    d = make_daemon(
        CallableSource(lambda t: grey(next(levels, 200)), rate_hz=100.0),
        link=FakeLink(),
        log=FlightLog(tmp_path / "flight.mcap", frames=True),
    )
    d.run(max_cycles=20)
    n_frames = inspect_log(tmp_path / "flight.mcap").message_counts["/camera/image"]
    assert n_frames == d.stats.frames_used >= 10
    res = replay(tmp_path / "flight.mcap", Navigator(TruthEstimator()), tmp_path / "replay.jsonl")
    assert res.frames_replayed == n_frames and res.frames_missing == 0
    # lossless frames, the same times: every estimate and filter state bit for bit
    assert res.exact and res.estimates_exact == res.estimates_compared >= 10
    assert res.filter_exact == res.filter_compared == 20
    assert max(res.dt_m) == 0.0
    # another estimator on the same flight: the differences are reported, not hidden
    res2 = replay(tmp_path / "flight.mcap", Navigator(TruthEstimator(confidence=0.7)))
    assert not res2.exact and "estimate differs" in res2.first_difference


def test_replay_without_frames_says_how_to_record(tmp_path):
    d = make_daemon(CallableSource(lambda t: grey(), rate_hz=100.0), log=FlightLog(tmp_path / "c.mcap"))
    d.run(max_cycles=3)
    with pytest.raises(FlightLogError, match="no camera frame.*--record-frames"):
        replay(tmp_path / "c.mcap", Navigator(TruthEstimator()))


@pytest.mark.parametrize("content", [None, b"", b"\x00garbage" * 100])
def test_cli_model_missing_or_corrupt_is_one_clear_line(tmp_path, capsys, content):
    frames = tmp_path / "frames"
    frames.mkdir()
    from PIL import Image

    Image.fromarray(grey()).save(frames / "000001.png")
    model = tmp_path / "model.onnx"
    if content is not None:
        model.write_bytes(content)
    rc = main(
        [
            "nav",
            "--camera",
            str(frames),
            "--port",
            "none",
            "--model",
            str(model),
            "--no-log",
            "--duration-s",
            "1",
        ]
    )
    err = capsys.readouterr().err
    assert rc == 2
    assert "oibar: error:" in err and str(model) in err
    assert "Traceback" not in err


def test_cli_help_explains_the_options(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["nav", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for word in ("--camera", "--port", "--model", "--vehicle", "--record-frames", "Ctrl-C", "udp://"):
        assert word in out


def test_vehicle_specs():
    assert isinstance(open_vehicle("none"), NullVehicle)
    v = open_vehicle("udp://127.0.0.1:9")
    v.send(0.0, np.zeros(3), np.zeros(3), "HOLD")
    v.close()
    from oibar.nav.vehicle import VehicleError

    for bad in ("udp://nohost", "python:nosuchmodule:X", "tcp://x", "python:os:getcwd"):
        with pytest.raises(VehicleError):
            open_vehicle(bad)


def test_vehicles_report_no_odometry_by_default():
    assert NullVehicle().relative_velocity(1.0) is None
    assert RecordingVehicle().relative_velocity(1.0) is None  # a sink that only implements send
    v = open_vehicle("udp://127.0.0.1:9")
    assert v.relative_velocity(1.0) is None
    v.close()


def test_udp_vehicle_takes_the_gnc_odometry_back():
    """A GNC computer on UDP: it receives the setpoints and answers with its odometry on the same
    socket. Each measurement is reported once, the newest wins, stale / malformed / future ones
    are dropped and counted, and nothing raises."""
    import json
    import socket
    import time as _time

    gnc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gnc.bind(("127.0.0.1", 0))
    gnc.settimeout(2.0)
    v = open_vehicle(f"udp://127.0.0.1:{gnc.getsockname()[1]}")
    try:
        v.send(10.0, np.array([0.0, 0.0, -0.03]), np.zeros(3), "SOFT_DOCK")
        setpoint, daemon_addr = gnc.recvfrom(2048)
        assert json.loads(setpoint)["phase"] == "SOFT_DOCK"

        def reply(**msg):
            gnc.sendto(json.dumps(msg).encode(), daemon_addr)

        def drained(t_s, n):
            """relative_velocity(t_s) once the socket has seen n more datagrams (loopback is fast
            but not synchronous)."""
            want = v.odometry_received + v.odometry_rejected + n
            deadline = _time.monotonic() + 2.0
            while v.odometry_received + v.odometry_rejected < want and _time.monotonic() < deadline:
                v.drain(t_s)
                _time.sleep(0.005)
            return v.relative_velocity(t_s)

        reply(v_D_mps=[0.0, 0.0, -0.028], sigma_mps=0.004, t_s=10.02)
        reply(v_D_mps=[0.001, 0.0, -0.030], sigma_mps=0.003, t_s=10.05)  # newer: this one wins
        odo = drained(10.1, 2)
        assert isinstance(odo, RelativeVelocity)
        assert odo.t_s == pytest.approx(10.05) and odo.sigma_mps == pytest.approx(0.003)
        assert odo.v_D_mps == pytest.approx([0.001, 0.0, -0.030])
        assert v.relative_velocity(10.2) is None  # reported once, not again

        reply(v_D_mps=[0.0, 0.0, -0.03], sigma_mps=0.003)  # no t_s: valid when read
        odo = drained(10.3, 1)
        assert odo is not None and odo.t_s == pytest.approx(10.3)

        bad = [
            {"v_D_mps": [0.0, 0.0], "sigma_mps": 0.003, "t_s": 10.3},  # not 3 axes
            {"v_D_mps": [0.0, 0.0, float("nan")], "sigma_mps": 0.003},
            {"v_D_mps": [0.0, 0.0, -0.03], "sigma_mps": 0.0},
            {"v_D_mps": [0.0, 0.0, -0.03], "sigma_mps": 0.003, "t_s": 99.0},
        ]  # from the future
        for m in bad:
            gnc.sendto(json.dumps(m).encode(), daemon_addr)
        gnc.sendto(b"not json", daemon_addr)
        assert drained(10.4, 5) is None
        assert v.odometry_rejected == 5 and v.odometry_received == 3

        reply(v_D_mps=[0.0, 0.0, -0.03], sigma_mps=0.003, t_s=9.0)  # 1.5 s old: stale
        assert drained(10.5, 1) is None
        assert v.statistics() == {
            "send_errors": 0,
            "odometry_received": 4,
            "odometry_rejected": 5,
            "attitude_received": 0,
            "attitude_rejected": 0,
        }
    finally:
        v.close()
        gnc.close()


class OdometryVehicle(RecordingVehicle):
    """A vehicle whose GNC knows the relative velocity (here: closing at 20 mm/s)."""

    def __init__(self, v_D_mps=(0.0, 0.0, -0.02), sigma_mps=0.002, fail=False):
        super().__init__()
        self.v, self.sigma, self.fail, self.asked = np.asarray(v_D_mps, float), sigma_mps, fail, []

    def relative_velocity(self, t_s):
        self.asked.append(t_s)
        if self.fail:
            raise OSError("GNC link down")
        return RelativeVelocity(t_s, self.v.copy(), self.sigma)


def test_the_vehicles_odometry_reaches_the_filter_and_the_mcu(tmp_path):
    """The camera sees a fixed pose (no motion); the vehicle says it closes at 20 mm/s with 2 mm/s
    confidence: the filter believes the vehicle, and the NavUpdate carries it."""

    def closing_after(vehicle, log=None):
        link = FakeLink()
        d = make_daemon(CallableSource(lambda t: grey(), rate_hz=100.0), link=link, vehicle=vehicle, log=log)
        d.run(max_cycles=30)
        return d, link.navs[-1][1]["closing_speed_mps"]

    log = FlightLog(tmp_path / "flight.mcap", frames=True)
    veh = OdometryVehicle()
    d, closing = closing_after(veh, log)
    assert len(veh.asked) >= 30, "asked once per cycle"
    assert d.nav.filter.velocity_counts["fused"] >= 20
    assert closing == pytest.approx(0.02, abs=0.005)
    cycles = decoded(tmp_path / "flight.mcap", "/nav/cycle")
    fused = [c.odometry for c in cycles if c.HasField("odometry") and c.odometry.reason == "fused"]
    assert fused and list(fused[0].v_D_mps) == [0.0, 0.0, -0.02] and fused[0].sigma_mps == 0.002
    # replay feeds the recorded odometry again: the same filter, bit for bit
    again = Navigator(TruthEstimator())
    res = replay(tmp_path / "flight.mcap", again)
    assert again.filter.velocity_counts == d.nav.filter.velocity_counts
    assert res.exact and res.filter_exact == res.filter_compared == 30
    assert again.filter.state(cycles[-1].t_s).closing_speed_mps == pytest.approx(0.02, abs=0.005)
    d0, closing0 = closing_after(RecordingVehicle())
    assert abs(closing0) < 0.002 and d0.nav.filter.velocity_counts["fused"] == 0


def test_a_failing_odometry_leaves_navigation_on_the_camera():
    veh = OdometryVehicle(fail=True)
    link = FakeLink()
    d = make_daemon(CallableSource(lambda t: grey(), rate_hz=100.0), link=link, vehicle=veh)
    summary = d.run(max_cycles=20)
    assert summary["cycles"] == 20 and summary["odometry_errors"] == 20
    assert d.nav.filter.velocity_counts["fused"] == 0
    assert link.navs and any(ph != "HOLD" for _, _, ph in veh.sent), "the approach goes on"


def test_end_of_a_recorded_stream_is_not_a_lost_camera(tmp_path):
    """Issue 17: a finished frame folder (or video) was handled as a lost camera and reopened,
    so navigation started again from frame 0. End of stream: each frame is used once, nothing
    is reopened, the cycle holds saying why, and run() ends."""
    frames = tmp_path / "frames"
    frames.mkdir()
    from PIL import Image

    for k in range(3):
        Image.fromarray(grey(100 + k)).save(frames / f"{k:06d}.png")
    d = make_daemon(FolderSource(frames, rate_hz=100.0, realtime=True), link=FakeLink())
    d._t0 = d.clock()
    reasons = []
    for _ in range(30):
        step, _ = tick(d)
        reasons.append(step.hold_reason)
        d._stop.wait(0.02)
    d.shutdown()
    # at most the 3 frames (the newest-frame reader may skip one), never the folder again
    assert d.stats.frames_used <= 3 and d.stats.camera_reopens == 0, (d.stats.frames_used, reasons)
    assert any("end of stream" in r for r in reasons[5:]), reasons
    d2 = make_daemon(FolderSource(frames, rate_hz=100.0, realtime=True), link=FakeLink())
    summary = d2.run(duration_s=5.0)
    assert d2.camera_ended and summary["frames_used"] <= 3 and summary["cycles"] < 20


def test_recorded_frames_survive_a_camera_reopen(tmp_path):
    """Issue 17: recorded frames were named by the camera's frame counter, which restarts when
    the camera is reopened, so the frames before the reopen were overwritten. In the flight log
    each frame belongs to its cycle, numbered by the daemon."""
    log = FlightLog(tmp_path / "flight.mcap", frames=True)
    d = make_daemon(CallableSource(lambda t: grey(), rate_hz=100.0), link=FakeLink(), log=log)
    d._t0 = d.clock()
    for _ in range(6):
        tick(d)
    from oibar.camera import CameraLost

    d._drop_camera(CameraLost("unplugged for the test"), d.clock())
    d._next_cam_try = 0.0
    for _ in range(6):
        tick(d)
    d.shutdown()
    assert d.stats.camera_reopens == 1
    cycles = [c for c in decoded(tmp_path / "flight.mcap", "/nav/cycle") if c.has_frame]
    assert len(cycles) == d.stats.frames_used and len({c.cycle for c in cycles}) == len(cycles)
    assert inspect_log(tmp_path / "flight.mcap").message_counts["/camera/image"] == len(cycles)
    assert min(c.frame_seq for c in cycles[1:]) == 0, "the camera's counter restarted: cycles tell them apart"


def test_a_reader_stuck_in_read_is_never_doubled():
    """Issue 17: after a read that hung past the join timeout, the daemon reopened the camera
    while the old reader was still inside read(): two threads reading one device. Now it waits
    for the stuck reader to leave before reopening."""
    from oibar.camera import CameraSource

    class HangingSource(CameraSource):
        name = "hanging"

        def __init__(self):
            super().__init__()
            self.lock = threading.Lock()
            self.active = self.max_active = self.reads = 0

        def _open(self):
            pass

        def _close(self):
            pass

        def _read(self):
            with self.lock:
                self.active += 1
                self.max_active = max(self.max_active, self.active)
                self.reads += 1
                n = self.reads
            try:
                threading.Event().wait(0.8 if n == 5 else 0.01)  # the 5th read hangs
            finally:
                with self.lock:
                    self.active -= 1
            return grey(), __import__("time").monotonic()

    src = HangingSource()
    d = make_daemon(src, link=FakeLink(), camera_lost_timeout_s=0.15, camera_retry_s=0.05, camera_join_s=0.05)
    d._t0 = d.clock()
    t_end = d.clock() + 1.6
    while d.clock() < t_end:
        tick(d)
    d.shutdown()
    assert src.reads > 10, "the camera came back after the hang"
    assert src.max_active == 1, f"{src.max_active} readers at once on one source"


def test_serial_port_unplugged_and_replugged_with_the_real_link_client(mcu, make_client):
    """The real LinkClient against the fake MCU, whose port vanishes for a while: the daemon
    sends nothing while it is gone, holds the vehicle, and carries on after the client has
    reconnected by itself."""
    from fake_mcu import wait_for

    client = make_client(mcu.url)
    client.connect()
    veh = RecordingVehicle()
    d = make_daemon(CallableSource(lambda t: grey(), rate_hz=100.0), link=client, vehicle=veh)
    d._t0 = d.clock()
    for _ in range(10):
        tick(d)
    navs_before = len(mcu.nav_updates)
    assert navs_before >= 5
    mcu.disappear()
    assert wait_for(lambda: not client.link_alive, timeout_s=2.0)
    n_sent = len(veh.sent)
    for _ in range(10):
        tick(d)
    assert all(ph == "HOLD" and not v.any() for _, v, ph in veh.sent[n_sent:])
    mcu.reappear()
    assert wait_for(lambda: client.link_alive, timeout_s=5.0)
    n_sent = len(veh.sent)
    for _ in range(10):
        tick(d)
    d.shutdown()
    assert len(mcu.nav_updates) > navs_before, "navigation updates flow again"
    assert any(ph != "HOLD" for _, _, ph in veh.sent[n_sent:]), "the approach resumes"


def test_navigator_orders_odometry_and_frame_in_time_and_skips_malformed_odometry():
    nav = Navigator(TruthEstimator(0.9))
    nav.step(0.0, grey(), frame_t_s=0.0)
    # odometry older than this cycle's frame: fused first, the filter's clock never goes back
    s = nav.step(0.2, grey(), frame_t_s=0.18, odometry=RelativeVelocity(0.15, np.zeros(3), 0.005))
    assert s.update.reason == "fused" and s.velocity_update.reason == "fused" and not s.hold_reason
    # newer than the frame: after it
    s = nav.step(0.3, grey(), frame_t_s=0.27, odometry=RelativeVelocity(0.3, np.zeros(3), 0.005))
    assert s.update.reason == "fused" and s.velocity_update.reason == "fused"
    # older than what the filter already has: dropped, not an error
    s = nav.step(0.4, None, odometry=RelativeVelocity(0.1, np.zeros(3), 0.005))
    assert s.velocity_update is None and s.hold_reason == "no new frame"
    for bad in (
        (float("nan"), np.zeros(3), 0.005),
        ("x", np.zeros(3), 0.005),
        (0.5, np.zeros(2), 0.005),
        (0.5, None, 0.005),
        (0.5,),
    ):
        s = nav.step(0.5, grey(), frame_t_s=0.5, odometry=bad)
        assert s.solution.valid and s.update is not None
        assert s.velocity_update is None or s.velocity_update.reason == "non_finite"


def test_heartbeats_stop_when_the_navigation_loop_hangs(mcu, fast_timings):
    """Issue 17: heartbeats came from their own thread, so a hung navigation loop still looked
    alive to the MCU. The daemon's link (oibar nav's, open_link) sends them only from the cycle:
    cycling keeps the MCU's link up; a loop that stops cycling lets its link timeout expire."""
    from fake_mcu import wait_for

    from oibar.nav.cli import open_link

    client = open_link(mcu.url, **fast_timings)
    try:
        client.connect()
        d = make_daemon(CallableSource(lambda t: grey(), rate_hz=100.0), link=client)
        d._t0 = d.clock()
        for _ in range(8):  # cycling: 0.05 s apart, link timeout 0.3 s
            tick(d)
            d._stop.wait(0.05)
        assert mcu.link_losses == 0 and mcu.connected
        assert mcu.requests("heartbeat"), "the cycle sends heartbeats"
        beats = len(mcu.requests("heartbeat"))
        assert wait_for(lambda: mcu.link_losses >= 1, timeout_s=2.0), "a hung loop must fall silent"
        assert len(mcu.requests("heartbeat")) == beats
        d._stop.wait(0.6)  # still hung: no re-handshake behind its back
        assert mcu.handshakes_accepted == 1
        for _ in range(20):  # the loop cycles again: the link comes back
            tick(d)
            d._stop.wait(0.05)
            if client.link_alive and mcu.connected:
                break
        # back once at least (a load spike over the 0.3 s timeout between two ticks of this test
        # may drop and restore it once more: 3 in a fresh clone beside a closed-loop study)
        assert client.link_alive and mcu.handshakes_accepted >= 2
        d.shutdown()
    finally:
        client.close()


class TrackingEstimator(TruthEstimator):
    """A TruthEstimator that, like a keypoint model, takes the predicted pose."""

    uses_prior = True

    def __init__(self, confidence=0.9):
        super().__init__(confidence)
        self.priors = []

    def estimate(self, image, t_s=0.0, prior=None):
        self.priors.append(prior)
        return super().estimate(image, t_s)


def test_the_navigator_gives_a_tracking_estimator_the_filters_predicted_pose():
    """No prediction before the filter has a track; then the filter's pose at the frame's time
    (the keypoint model crops there); a direct model (uses_prior False) is never passed one."""
    est = TrackingEstimator(0.9)
    nav = Navigator(est)
    nav.step(0.0, grey(), frame_t_s=0.0)
    assert est.priors == [None]
    s = nav.step(0.1, grey(), frame_t_s=0.1)
    R, T = est.priors[-1]
    st = nav.filter.state(0.1)
    assert np.allclose(T, st.T_cam_target_m) and np.allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.linalg.norm(T - s.estimate.T_cam_target_m) < 0.05
    plain = TruthEstimator(0.9)  # its estimate() takes no prior: a call with one would raise
    nav = Navigator(plain)
    for k in range(3):
        assert nav.step(0.1 * k, grey(), frame_t_s=0.1 * k).update is not None


def test_bench_link_stub_accepts_commands():
    # The nav-cycle benchmark's MCU stub referred to `pb` outside the method that imported it, so
    # the first command guidance sent during a benchmark raised NameError (found by ruff F821).
    from oibar.nav.bench import _InstantLink

    req = _InstantLink().submit_command(pb.CMD_APPROACH_ARM)
    assert req.done and req.response.accepted and req.response_kind == "ack"


class PriorFreeEstimator(TruthEstimator):
    """A keypoint-like estimator whose prior-free measurement sits 0.1 m sideways of its pose."""

    def estimate(self, image, t_s=0.0):
        e = super().estimate(image, t_s)
        e.T_meas_cam_target_m = e.T_cam_target_m + np.array([0.1, 0.0, 0.0])
        e.R_meas_cam_target = e.R_cam_target.copy()
        return e


def test_the_navigator_fuses_the_prior_free_measurement_not_the_prior_leaning_pose():
    """The filter is fed PoseEstimate.measurement(): an attitude prior that leans every frame the
    same way is a bias the filter cannot average out (model card 0.8.1, closed loop lateral p95
    7.8-14.3 cm below 5 m on validation looks with the fused pose fed)."""
    nav = Navigator(PriorFreeEstimator(0.9))
    for k in range(5):
        s = nav.step(0.1 * k, grey(), frame_t_s=0.1 * k)
    st = nav.filter.state(0.4)
    assert np.linalg.norm(st.T_cam_target_m - (s.estimate.T_cam_target_m + [0.1, 0.0, 0.0])) < 0.01
    nav = Navigator(TruthEstimator(0.9))  # no measurement of its own: the pose itself
    for k in range(5):
        s = nav.step(0.1 * k, grey(), frame_t_s=0.1 * k)
    assert np.linalg.norm(nav.filter.state(0.4).T_cam_target_m - s.estimate.T_cam_target_m) < 0.01
