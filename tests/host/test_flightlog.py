"""The flight log (oibar.nav.flightlog, issue 60 item 5): MCAP through the Foxglove SDK, read back
with the `mcap` reader; exact replay with the shipped model; a log cut by a kill; a full disk;
the live view over WebSocket (a plain WebSocket client speaking foxglove.sdk.v1).

The daemon's stand-ins (TruthEstimator, FakeLink) are test_nav_daemon.py's.
"""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from oibar import pb
from oibar.camera import CallableSource
from oibar.nav.core import Navigator
from oibar.nav.flightlog import (
    CHANNELS,
    FlightLog,
    FlightLogError,
    inspect_log,
    read_messages,
    read_summary,
)
from oibar.nav.logschema import ProtobufDecoder
from oibar.nav.replay import read_run_info, replay

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_nav_daemon import FakeLink, TruthEstimator, grey, make_daemon, tick  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = ROOT / "tests" / "golden" / "pose"
MODEL = ROOT / "models" / "oibarnet.onnx"


class EventLink(FakeLink):
    """FakeLink whose MCU sends an event and a fresh telemetry packet every few cycles."""

    def __init__(self):
        super().__init__()
        self._k = 0

    @property
    def telemetry(self):
        self._k += 1
        if self._k % 3 == 0:
            self._tm = pb.Telemetry(state=pb.STATE_IDLE, uptime_ms=self._k, sv_tank_kpa=1000.0)
        return self._tm

    def next_event(self, timeout_s=None):
        if self._k % 5 == 0 and not getattr(self, "_sent", False):
            self._sent = True
            return pb.Event(uptime_ms=self._k, id=pb.EVT_STATE_CHANGE, from_state=pb.STATE_IDLE)
        self._sent = False
        return None


def decoded(path, topic):
    dec = ProtobufDecoder()
    return [
        dec.decode(m.schema_id, m.schema_name, m.schema_data, m.data) for m in read_messages(path, [topic])
    ]


def fly(tmp_path, cycles=20, frames=True, link=None, name="flight.mcap", flush_every_s=None):
    levels = iter(range(40, 240, 3))
    log = FlightLog(tmp_path / name, frames=frames)
    if flush_every_s is not None:
        log.flush_every_s = flush_every_s
    d = make_daemon(
        CallableSource(lambda t: grey(next(levels, 200)), rate_hz=100.0), link=link or EventLink(), log=log
    )
    d.run(max_cycles=cycles)
    return d, tmp_path / name


def test_every_channel_is_in_the_mcap_with_its_schema(tmp_path):
    d, path = fly(tmp_path)
    inv = inspect_log(path)
    assert inv.complete, "closed: the summary section is there"
    assert inv.missing() == [], inv.message_counts
    for topic, schema in CHANNELS.items():
        assert inv.channels[topic] == schema, topic
    assert inv.message_counts["/nav/cycle"] == 20 == inv.message_counts["/guidance/command"]
    assert inv.message_counts["/camera/image"] == d.stats.frames_used
    # the MCU's own messages, decoded from the file's schema alone
    tm = decoded(path, "/link/telemetry")
    assert tm and tm[-1].sv_tank_kpa == 1000.0
    assert decoded(path, "/link/events")[0].id == pb.EVT_STATE_CHANGE
    # Foxglove's: the image is the navigator's pixels, the calibration the canonical camera
    img = decoded(path, "/camera/image")[0]
    assert (img.width, img.height, img.encoding, img.frame_id) == (64, 40, "rgb8", "camera")
    assert np.frombuffer(img.data, np.uint8).reshape(40, 64, 3)[0, 0, 0] == 40
    cal = decoded(path, "/camera/calibration")[0]
    assert cal.frame_id == "camera" and len(cal.K) == 9 and cal.distortion_model == "plumb_bob"
    scene = decoded(path, "/nav/fixture")[0]
    assert {e.frame_id for e in scene.entities} == {"fixture", "fixture_filter"}
    assert all(len(line.points) >= 5 for e in scene.entities for line in e.lines)
    tfs = decoded(path, "/tf")
    assert {t.child_frame_id for t in tfs} == {"fixture", "fixture_filter"}
    assert all(t.parent_frame_id == "camera" for t in tfs)
    # the filter with its sigmas; the estimate in full; guidance's setpoints
    filt = [f for f in decoded(path, "/nav/filter") if f.valid]
    assert filt and all(len(f.pos_sigma_m) == 3 and 0 < min(f.pos_sigma_m) < 1 for f in filt)
    est = decoded(path, "/nav/estimate")[0]
    assert len(est.T_cam_target_m) == 3 and len(est.q_cam_target_wxyz) == 4 and est.confidence == 0.9
    assert any(g.phase and len(g.v_sp_D_mps) == 3 for g in decoded(path, "/guidance/command"))
    info = read_run_info(path)
    assert info.package_version and info.protocol_version == pb.PROTOCOL_VERSION
    assert info.model_version == "test" and info.rate_hz == 50.0
    summary = read_summary(path)
    assert summary["summary"]["cycles"] == 20 and summary["log_messages_lost"] == 0


def test_without_record_frames_the_file_has_everything_but_the_frames(tmp_path):
    d, path = fly(tmp_path, cycles=10, frames=False)
    inv = inspect_log(path)
    assert inv.missing() == ["/camera/image"]
    assert inv.message_counts["/nav/cycle"] == 10
    assert inv.message_counts["/nav/estimate"] == d.stats.frames_used >= 1


def test_a_log_cut_by_a_kill_is_read_up_to_the_cut(tmp_path):
    # a chunk ended every few cycles, as the 1 s flush does in a real flight
    d, path = fly(tmp_path, cycles=40, flush_every_s=0.05)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 4])  # the summary section is the back half
    inv = inspect_log(cut)
    assert not inv.complete
    n = inv.message_counts.get("/nav/cycle", 0)
    assert 3 <= n < 40
    res = replay(cut, Navigator(TruthEstimator()))
    assert res.truncated and res.cycles == n and res.exact
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all" * 10)
    with pytest.raises(FlightLogError, match="not a readable MCAP"):
        list(read_messages(tmp_path / "junk.mcap"))
    with pytest.raises(FlightLogError, match="not found"):
        inspect_log(tmp_path / "none.mcap")


def test_a_full_disk_is_reported_once_and_navigation_goes_on(capfd):
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    log = FlightLog("/dev/full", frames=True)
    log.flush_every_s = 0.0
    d = make_daemon(CallableSource(lambda t: grey(), rate_hz=100.0), link=FakeLink(), log=log)
    summary = d.run(max_cycles=20)
    assert summary["cycles"] == 20
    assert log.error and "No space left" in log.error
    assert log.messages_lost >= 19 * 5, "every message after the failure is counted"
    assert "LOG:" in d.status_line()
    err = capfd.readouterr().err
    assert "error logging message" not in err, "the SDK does not complain on every message"


def test_an_unwritable_log_folder_is_a_start_up_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OSError):
        FlightLog(blocker / "sub" / "flight.mcap")


def test_a_slow_writer_drops_whole_cycles_and_counts_them(tmp_path):
    log = FlightLog(tmp_path / "slow.mcap", queue_cycles=2)
    real = log._write

    def slow(item):
        time.sleep(0.05)
        real(item)

    log._write = slow
    d = make_daemon(CallableSource(lambda t: grey(), rate_hz=100.0), link=FakeLink(), log=log)
    summary = d.run(max_cycles=30)
    assert summary["cycles"] == 30
    assert log.messages_lost > 0
    n = inspect_log(tmp_path / "slow.mcap").message_counts["/nav/cycle"]
    assert n < 30 and n + log.messages_lost // 5 >= 25


@pytest.mark.skipif(not MODEL.is_file(), reason="the shipped model is not in this checkout")
def test_replay_reproduces_the_shipped_models_estimates_bit_for_bit(tmp_path, capsys):
    """The real estimator (keypoints, crops placed by the filter, PnP) on rendered frames:
    replayed from the MCAP with the flight's thread count, every estimate and filter state is
    the recorded one, bit for bit."""
    import cv2

    from oibar.cli import main
    from oibar.nav.daemon import DaemonParams, NavDaemon, load_navigator
    from oibar.nav.guidance import Guidance, MissionParams

    frames = [
        np.ascontiguousarray(cv2.imread(str(GOLDEN / f"{n}.png"))[:, :, ::-1])
        for n in ("track_5m_a", "track_5m_b", "track_5m_a", "track_5m_b", "cold_3m", "cold_3m")
    ]
    k = iter(range(10**6))
    log = FlightLog(tmp_path / "flight.mcap", frames=True)
    d = NavDaemon(
        load_navigator(MODEL, threads=1),
        Guidance(MissionParams(nav_lost_abort_s=60.0)),
        CallableSource(lambda t: frames[min(next(k), len(frames) - 1)], rate_hz=50.0),
        link=FakeLink(),
        log=log,
        params=DaemonParams(rate_hz=10.0),
    )
    d.run(max_cycles=6)
    assert log.error is None
    info = read_run_info(tmp_path / "flight.mcap")
    assert info.ort_intra_op_threads == 1 and len(info.model_sha256) == 64
    assert info.intrinsics.width_px == 744 and not info.intrinsics.calibrated
    res = replay(tmp_path / "flight.mcap", load_navigator(MODEL, threads=1))
    assert res.model_matches is True and res.threads == res.threads_recorded == 1
    assert res.estimates_compared >= 4 and res.exact, res.summary()
    logged = decoded(tmp_path / "flight.mcap", "/nav/estimate")
    assert any(np.isfinite(e.T_cam_target_m[0]) for e in logged)
    # what each cycle's search read, for a slow cycle's cause (PoseEstimate.crops)
    assert all(e.crops >= 1 for e in logged if np.isfinite(e.T_cam_target_m[0]))
    # the command line: the thread count comes from the log
    assert main(["replay", str(tmp_path / "flight.mcap"), "--model", str(MODEL)]) == 0
    out = capsys.readouterr().out
    assert "exact               yes" in out and "onnxruntime threads 1 (flight: 1)" in out


# -- the live view --------------------------------------------------------------------------------


class WsClient:
    """A WebSocket client (RFC 6455), just enough for the foxglove.sdk.v1 subprotocol."""

    def __init__(self, host, port, timeout_s=5.0):
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                "Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
            ).encode()
        )
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            assert chunk, "server closed during the handshake"
            head += chunk
        assert head.startswith(b"HTTP/1.1 101"), head
        assert b"foxglove.sdk.v1" in head

    def _exact(self, n):
        buf = b""
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            assert chunk, "connection closed"
            buf += chunk
        return buf

    def recv(self):
        """(opcode, payload) of the next data frame (fragmented frames are not used here)."""
        while True:
            b0, b1 = self._exact(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._exact(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._exact(8))[0]
            payload = self._exact(n)
            op = b0 & 0x0F
            if op == 0x9:  # ping: answer it
                self.send(payload, opcode=0xA)
                continue
            return op, payload

    def send(self, payload, opcode=0x1):
        mask = os.urandom(4)
        n = len(payload)
        head = bytes([0x80 | opcode])
        if n < 126:
            head += bytes([0x80 | n])
        else:
            head += bytes([0x80 | 126]) + struct.pack(">H", n)
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))

    def close(self):
        self.sock.close()


def test_the_live_view_serves_the_same_channels_over_websocket(tmp_path):
    log = FlightLog(tmp_path / "flight.mcap", live=("127.0.0.1", 0), frames=False)
    assert log.live.url.startswith("ws://127.0.0.1:")
    client = WsClient("127.0.0.1", log.live.port)
    try:
        channels = {}
        deadline = time.monotonic() + 5
        while len(channels) < len(CHANNELS) and time.monotonic() < deadline:
            op, payload = client.recv()
            if op == 0x1:
                msg = json.loads(payload)
                if msg["op"] == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
        assert set(channels) == set(CHANNELS)
        assert channels["/camera/image"]["schemaName"] == "foxglove.RawImage"
        wanted = ["/camera/image", "/nav/cycle", "/nav/fixture", "/tf"]
        subs = [{"id": i, "channelId": channels[t]["id"]} for i, t in enumerate(wanted)]
        client.send(json.dumps({"op": "subscribe", "subscriptions": subs}).encode())
        time.sleep(0.3)  # the subscription reaches the server before the flight starts
        d = make_daemon(CallableSource(lambda t: grey(90), rate_hz=100.0), link=FakeLink(), log=log)
        d._t0 = d.clock()
        d.start_log()
        for _ in range(15):  # cycles as run() drives them, the log left open while we read
            tick(d)
        got: dict[str, list[bytes]] = {t: [] for t in wanted}
        dec = ProtobufDecoder()
        schema = base64.b64decode(channels["/nav/cycle"]["schema"])
        last_cycle = 0
        deadline = time.monotonic() + 5
        while (not all(got.values()) or last_cycle < 15) and time.monotonic() < deadline:
            op, payload = client.recv()
            if op == 0x2 and payload[0] == 0x01:  # messageData: sub id u32, log time u64, message
                sub_id, _log_time = struct.unpack_from("<IQ", payload, 1)
                got[wanted[sub_id]].append(payload[13:])
                if wanted[sub_id] == "/nav/cycle":
                    last_cycle = dec.decode(-1, "oibar.log.Cycle", schema, payload[13:]).cycle
        d.shutdown()
        assert all(got.values()), {t: len(v) for t, v in got.items()}
        assert last_cycle == 15 and len(got["/nav/cycle"]) == 15, "every cycle, live"
        image = dec.decode(
            -2,
            "foxglove.RawImage",
            base64.b64decode(channels["/camera/image"]["schema"]),
            got["/camera/image"][0],
        )
        assert (image.width, image.height) == (64, 40) and image.data[:1] == bytes([90])
    finally:
        client.close()
    # the frames went live but, without --record-frames, not into the file
    assert inspect_log(tmp_path / "flight.mcap").message_counts.get("/camera/image", 0) == 0


def test_live_address_forms():
    from oibar.nav.live import LiveError, parse_address

    assert parse_address("9000") == ("127.0.0.1", 9000)
    assert parse_address("0.0.0.0:8765") == ("0.0.0.0", 8765)
    assert parse_address("[::1]:9") == ("::1", 9)
    with pytest.raises(LiveError):
        parse_address("host:port")


def test_the_sitl_check_names_what_a_log_lacks(tmp_path):
    sitl = pytest.importorskip("oibar_hil.rig.sitl")
    _, full = fly(tmp_path, cycles=10, name="full.mcap")
    m = sitl.flight_log_metrics(full)
    assert m["flight_log_missing_channels"] == [] and m["flight_log_complete"]
    _, lean = fly(tmp_path, cycles=10, frames=False, name="lean.mcap")
    assert sitl.flight_log_metrics(lean)["flight_log_missing_channels"] == ["/camera/image"]
    assert sitl.flight_log_metrics(tmp_path / "none.mcap")["flight_log_missing_channels"] == list(CHANNELS)


def test_a_live_port_in_use_is_a_start_up_error(tmp_path):
    first = FlightLog(None, live=("127.0.0.1", 0))
    try:
        with pytest.raises(OSError, match="cannot serve"):
            FlightLog(tmp_path / "flight.mcap", live=("127.0.0.1", first.live.port))
    finally:
        first.close()
