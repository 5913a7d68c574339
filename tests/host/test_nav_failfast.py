"""Issue 60 item 4, "failures fail fast": every argument validated, a corrupt frame skipped and
counted, a source that ends or dies stops the daemon with its documented exit status after the
planned end of the MCU session, Ctrl-C / SIGTERM a planned stop the MCU accepts (no host link
loss fault), and never a traceback.

The estimator is the stand-in of test_nav_daemon.py; the link is either its FakeLink or the
real LinkClient against the fake MCU (tests/host/fake_mcu.py)."""

from __future__ import annotations

import os
import re
import signal
import threading
import time
from pathlib import Path

import pytest
from fake_mcu import FakeMcu, wait_for
from test_nav_daemon import FakeLink, TruthEstimator, grey, make_daemon

from oibar import pb
from oibar.camera import CameraOpenError, CameraSource, FolderSource
from oibar.cli import main
from oibar.nav import cli as nav_cli
from oibar.nav import daemon as nav_daemon
from oibar.nav.core import Navigator

ROOT = Path(__file__).resolve().parents[2]


def write_frames(folder: Path, n: int, corrupt: tuple[int, ...] = ()) -> Path:
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    for k in range(n):
        path = folder / f"{k:06d}.png"
        if k in corrupt:
            path.write_bytes(b"\x89PNG\r\n\x1a\n truncated")
        else:
            Image.fromarray(grey(60 + k % 100)).save(path)
    return folder


class CliEstimator(TruthEstimator):
    range_limits_m = (0.3, 12.0)


@pytest.fixture
def stub_model(monkeypatch, tmp_path):
    """`oibar nav` with the stand-in estimator instead of the ONNX model."""
    monkeypatch.setattr(nav_daemon, "load_navigator", lambda model, threads=2: Navigator(CliEstimator()))
    model = tmp_path / "stub.onnx"
    model.write_bytes(b"stub")
    return model


@pytest.fixture
def restore_signals():
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    for s, h in saved.items():
        signal.signal(s, h)


def nav_args(camera: Path | str, port: str, model: Path, *extra: str) -> list[str]:
    return ["nav", "--camera", str(camera), "--port", port, "--model", str(model), "--no-log", *extra]


# -- arguments --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "bad",
    [
        ["--rate-hz", "0"],
        ["--rate-hz", "-5"],
        ["--rate-hz", "nan"],
        ["--rate-hz", "ten"],
        ["--rate-hz", "1000"],
        ["--camera-rate-hz", "0"],
        ["--camera-dead-s", "0"],
        ["--threads", "0"],
        ["--threads", "1.5"],
        ["--duration-s", "0"],
        ["--duration-s", "inf"],
        ["--target-pressure-kpa", "-1"],
        ["--baudrate", "0"],
    ],
    ids=lambda b: " ".join(b),
)
def test_every_nav_argument_is_validated_with_a_clear_message(bad, capsys, tmp_path):
    """`oibar nav --rate-hz 0` was a ZeroDivisionError traceback."""
    frames = write_frames(tmp_path / "f", 2)
    with pytest.raises(SystemExit) as exc:
        main(nav_args(frames, "none", tmp_path / "m.onnx", *bad))
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert bad[0] in err and "Traceback" not in err
    assert re.search(r"out of range|not a number|not an integer|not a finite number", err), err


@pytest.mark.parametrize(
    "argv",
    [
        ["nav", "--camera", "", "--port", "none"],
        ["nav", "--camera", "0", "--port", ""],
        ["replay", "x.jsonl", "--threads", "0"],
        ["link", "--port", "loop://", "--seconds", "-1"],
        ["link", "--port", "loop://", "--baudrate", "fast"],
        ["link", "--port", "loop://", "--target-pressure-kpa", "nan"],
        ["calib", "extract", "v.mp4", "out", "--every", "0"],
        ["calib", "overlay", "--poses", "p.csv", "--out", "o", "--every", "-3"],
    ],
    ids=lambda a: " ".join(a),
)
def test_other_commands_validate_their_arguments(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "error:" in err and "Traceback" not in err


def test_exit_statuses_are_documented_in_the_help_and_the_docs(capsys):
    with pytest.raises(SystemExit):
        main(["nav", "--help"])
    helptext = capsys.readouterr().out
    doc = (ROOT / "docs" / "navigation.md").read_text()
    codes = {v for k, v in vars(nav_cli).items() if k.startswith("EXIT_")}
    assert codes == {0, 1, 2, 3, 4, 5, 130}
    for code in codes:
        assert re.search(rf"^\s+{code}\s+\S", helptext, re.M), f"exit status {code} not in --help"
        assert re.search(rf"^\|\s*{code}\s*\|", doc, re.M), f"exit status {code} not in docs/navigation.md"


# -- the source: corrupt frame, end, death ---------------------------------------------------


def test_a_corrupt_frame_is_skipped_and_counted_not_a_reopen(tmp_path):
    """One corrupt JPEG in a folder made the source fail; the daemon reopened the folder from
    frame 0, met the same file again, forever."""
    frames = write_frames(tmp_path / "f", 6, corrupt=(2,))
    link = FakeLink()
    d = make_daemon(FolderSource(frames, rate_hz=50.0, realtime=True), link=link)
    summary = d.run(duration_s=5.0)
    assert d.stats.camera_reopens == 0
    assert summary["corrupt_frames"] == 1
    assert 3 <= summary["frames_used"] <= 5
    assert d.stop_reason == nav_daemon.STOP_SOURCE_ENDED


def test_source_end_stops_with_exit_3_after_the_planned_end_of_the_session(tmp_path):
    frames = write_frames(tmp_path / "f", 3)
    link = FakeLink()
    d = make_daemon(FolderSource(frames, rate_hz=50.0, realtime=True), link=link)
    d.run(duration_s=5.0)
    assert d.stop_reason == nav_daemon.STOP_SOURCE_ENDED
    assert link.commands[-1] == (True, pb.CMD_END_SESSION), "the MCU is made safe before the exit"
    assert d.session_end is not None and d.session_end.accepted
    assert nav_cli.exit_status(d)[0] == nav_cli.EXIT_SOURCE_ENDED == 3


class DeadCamera(CameraSource):
    """A camera that is not there (unplugged before the start, or gone for good)."""

    name = "device /dev/video9"

    def _open(self):
        raise CameraOpenError("cannot open camera '/dev/video9': no such device")

    def _read(self):  # pragma: no cover - never opened
        raise AssertionError

    def _close(self):
        pass


def test_a_dead_source_stops_with_exit_4_after_the_planned_end_of_the_session():
    """A camera that never delivers ran forever with a blind retreat, exit 0."""
    link = FakeLink()
    d = make_daemon(DeadCamera(), link=link, camera_dead_s=0.6)
    t0 = time.monotonic()
    d.run(duration_s=10.0)
    assert time.monotonic() - t0 < 3.0
    assert d.stop_reason == nav_daemon.STOP_SOURCE_DIED
    assert link.commands and link.commands[-1] == (True, pb.CMD_END_SESSION)
    rc, why = nav_cli.exit_status(d)
    assert rc == nav_cli.EXIT_SOURCE_DIED == 4 and "no such device" in why


def test_a_camera_that_disappears_mid_run_stops_with_exit_4():
    state = {"frames": 0}

    def render(t):
        state["frames"] += 1
        if state["frames"] > 20:
            raise OSError("camera unplugged")
        return grey()

    from oibar.camera import CallableSource

    link = FakeLink()
    d = make_daemon(CallableSource(render, rate_hz=100.0), link=link, camera_dead_s=0.8)
    d.run(duration_s=10.0)
    assert d.stop_reason == nav_daemon.STOP_SOURCE_DIED and d.stats.frames_used >= 5
    assert link.commands[-1] == (True, pb.CMD_END_SESSION)


# -- the whole command against the fake MCU ---------------------------------------------------


def test_cli_source_end_exit_3_mcu_safe_no_traceback(stub_model, tmp_path, capsys, restore_signals):
    frames = write_frames(tmp_path / "f", 16, corrupt=(5,))
    with FakeMcu(link_timeout_s=1.0) as mcu:
        rc = main(nav_args(frames, mcu.url, stub_model, "--camera-rate-hz", "20"))
        err = capsys.readouterr().err
        assert rc == 3, err
        assert "camera source ended" in err and "1 corrupt frame" in err and "Traceback" not in err
        assert pb.CMD_END_SESSION in mcu.executed
        assert wait_for(lambda: mcu.link_losses >= 1, timeout_s=3.0)
        assert mcu.unplanned_link_losses == 0, "the silence after the planned end is no link loss fault"


def test_cli_empty_or_undecodable_source_is_a_startup_error(stub_model, tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    rc = main(nav_args(tmp_path / "empty", "none", stub_model))
    err = capsys.readouterr().err
    assert rc == 2 and "holds no image" in err and "Traceback" not in err
    video = tmp_path / "broken.mp4"
    video.write_bytes(b"not a video at all")
    rc = main(nav_args(video, "none", stub_model))
    err = capsys.readouterr().err
    assert rc == 2 and "oibar: error:" in err and "Traceback" not in err


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_cli_signal_is_a_planned_stop_the_mcu_accepts(signum, stub_model, tmp_path, capsys, restore_signals):
    """Ctrl-C / SIGTERM used to close the port mid-session: the MCU saw a host link loss and
    went to FAULT. Now the daemon ends the session (CMD_END_SESSION, accepted) and exits 0; the
    silence that follows is a planned end."""
    frames = write_frames(tmp_path / "f", 400)
    with FakeMcu(link_timeout_s=1.0) as mcu:
        mcu.state = pb.STATE_SOFT_DOCKED  # mid-mission: a bare link loss here faults the MCU
        timer = threading.Timer(1.5, os.kill, (os.getpid(), signum))
        timer.start()
        try:
            rc = main(nav_args(frames, mcu.url, stub_model, "--camera-rate-hz", "20", "--duration-s", "20"))
        finally:
            timer.cancel()
        err = capsys.readouterr().err
        assert rc == 0, err
        assert signal.Signals(signum).name in err and "Traceback" not in err
        assert "planned end accepted" in err
        assert mcu.executed[-1] == pb.CMD_END_SESSION
        assert wait_for(lambda: mcu.link_losses >= 1, timeout_s=3.0)
        assert mcu.unplanned_link_losses == 0


def test_cli_mcu_refusing_the_planned_end_is_exit_5(stub_model, tmp_path, capsys, restore_signals):
    frames = write_frames(tmp_path / "f", 400)
    with FakeMcu(link_timeout_s=1.0) as mcu:
        mcu.opcode_nacks[pb.CMD_END_SESSION] = pb.NACK_NOT_SUPPORTED  # an old firmware
        rc = main(nav_args(frames, mcu.url, stub_model, "--camera-rate-hz", "20", "--duration-s", "1.5"))
        err = capsys.readouterr().err
        assert rc == 5, err
        assert "NACK_NOT_SUPPORTED" in err and "Traceback" not in err


def test_cli_internal_error_is_one_line_exit_1(stub_model, tmp_path, capsys, monkeypatch, restore_signals):
    frames = write_frames(tmp_path / "f", 50)

    def broken_step(self, *a, **k):
        raise RuntimeError("boom")

    monkeypatch.setattr(Navigator, "step", broken_step)
    rc = main(nav_args(frames, "none", stub_model, "--camera-rate-hz", "20"))
    err = capsys.readouterr().err
    assert rc == 1 and "internal error: RuntimeError: boom" in err and "Traceback" not in err


def test_end_session_waits_for_a_request_in_flight():
    """Stop and wait: the planned end goes out only after the request in flight is answered."""
    from oibar.link.core import Request

    link = FakeLink()
    pending = Request("command", pb.Packet())
    from oibar.camera import CallableSource

    d = make_daemon(CallableSource(lambda t: grey()), link=link)
    d._handle = pending
    threading.Timer(0.2, lambda: setattr(pending, "done", True)).start()
    t0 = time.monotonic()
    res = d.end_session(timeout_s=2.0)
    assert 0.15 <= time.monotonic() - t0 < 1.5
    assert res.accepted and link.commands[-1] == (True, pb.CMD_END_SESSION)
    assert link.beats > 0, "heartbeats go on while it waits"
