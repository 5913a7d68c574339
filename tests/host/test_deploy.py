"""Deployment: the systemd unit (checked by systemd-analyze) and the daemon's sd_notify
notifications (READY=1, WATCHDOG=1, STOPPING=1) on a socket the test binds, as systemd would."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from oibar import cli, config
from oibar.sdnotify import Notifier

ROOT = Path(__file__).resolve().parents[2]
UNIT = ROOT / "deploy" / "systemd" / "oibar-nav.service"
GOLDEN_FRAMES = sorted((ROOT / "tests" / "golden" / "pose").glob("*.png"))


def unit_settings() -> dict[str, str]:
    out = {}
    for line in UNIT.read_text().splitlines():
        if "=" in line and not line.lstrip().startswith(("#", ";")):
            key, value = line.split("=", 1)
            out[key.strip()] = value.strip()
    return out


def bind_notify_socket(path: Path) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(0.2)
    return sock


def drain(sock: socket.socket) -> list[str]:
    out = []
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except TimeoutError:
            return out


# -- the unit ------------------------------------------------------------------------------------


def test_unit_restarts_and_watches_the_daemon() -> None:
    s = unit_settings()
    assert s["Type"] == "notify" and s["NotifyAccess"] == "main"
    assert s["Restart"] == "on-failure" and s["RestartPreventExitStatus"] == "2"
    assert s["WatchdogSec"] == "10s"
    # the daemon pets the watchdog from its status calls (every DaemonParams.status_every_s):
    # the watchdog period must leave room for several of them and for a slow cycle
    from oibar.nav.daemon import DaemonParams

    assert 4 * DaemonParams().status_every_s <= 10.0
    # its stop (vehicle hold, the planned end of the MCU session) fits in the stop timeout
    assert float(s["TimeoutStopSec"].rstrip("s")) > DaemonParams().end_session_s + 5


def test_unit_command_line_parses_with_the_template_config() -> None:
    argv = unit_settings()["ExecStart"].split()
    assert Path(argv[0]).name == "oibar" and argv[1:3] == ["nav", "--config"]
    parser = cli.build_parser()
    config.apply(parser, ROOT / "deploy" / "oibar.toml")  # the template for argv[3]
    a = parser.parse_args(argv[1:2])
    assert a.subcommand == "nav" and a.camera and a.port


def _verify(unit_text: str, tmp_path: Path) -> subprocess.CompletedProcess[str]:
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed (Debian package systemd, scripts/apt-packages.txt)")
    unit = tmp_path / "oibar-nav.service"
    # ExecStart must name an executable that exists here: this venv's own oibar
    oibar = Path(sys.executable).with_name("oibar")
    assert oibar.exists(), "the venv has no oibar console script (make setup)"
    unit.write_text(unit_text.replace("/opt/oibar/venv/bin/oibar", str(oibar)))
    return subprocess.run(
        ["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60, check=False
    )


def test_systemd_analyze_verify_accepts_the_unit(tmp_path: Path) -> None:
    res = _verify(UNIT.read_text(), tmp_path)
    about_unit = [line for line in (res.stdout + res.stderr).splitlines() if "oibar-nav" in line]
    assert res.returncode == 0 and not about_unit, res.stdout + res.stderr


def test_systemd_analyze_verify_would_catch_a_mistake(tmp_path: Path) -> None:
    """The check above is real: a misspelt key and a missing executable are reported."""
    res = _verify(UNIT.read_text().replace("WatchdogSec=", "WatchdogSecs="), tmp_path)
    assert "Unknown key" in res.stderr and "WatchdogSecs" in res.stderr
    res = _verify(UNIT.read_text().replace("/opt/oibar/venv/bin/oibar", "/nonexistent/oibar"), tmp_path)
    assert res.returncode != 0 and "/nonexistent/oibar" in res.stderr


# -- sd_notify ------------------------------------------------------------------------------------


def test_notifier_sends_nothing_outside_systemd() -> None:
    n = Notifier({})
    assert not n.enabled and not n.ready() and not n.watchdog() and not n.stopping()


def test_notifier_datagrams_and_watchdog_pacing(tmp_path: Path) -> None:
    path = tmp_path / "notify"
    with bind_notify_socket(path) as sock:
        n = Notifier({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "400000"})
        assert n.watchdog_s == pytest.approx(0.4)
        assert n.ready("up")
        assert n.watchdog("cycling")
        assert not n.watchdog()  # within half the period: not sent again
        time.sleep(0.25)
        assert n.watchdog()
        assert n.stopping()
        n.close()
        assert drain(sock) == ["READY=1\nSTATUS=up", "WATCHDOG=1\nSTATUS=cycling", "WATCHDOG=1", "STOPPING=1"]
    # another process's watchdog (WATCHDOG_PID) is not ours to pet
    assert (
        Notifier({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "1", "WATCHDOG_PID": "1"}).watchdog_s is None
    )


def test_notifier_abstract_socket() -> None:
    name = f"oibar-test-{os.getpid()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name)
        sock.settimeout(2)
        assert Notifier({"NOTIFY_SOCKET": "@" + name}).ready()
        assert sock.recv(100) == b"READY=1"


def test_notifier_never_raises(tmp_path: Path) -> None:
    n = Notifier({"NOTIFY_SOCKET": str(tmp_path / "nobody-listens")})
    assert n.enabled and not n.ready()


@pytest.mark.skipif(len(GOLDEN_FRAMES) < 3, reason="needs the golden pose frames")
def test_oibar_nav_notifies_ready_watchdog_and_stopping(tmp_path: Path) -> None:
    """The real daemon under a stand-in for systemd: READY=1 after start-up, WATCHDOG=1 while
    it cycles, STOPPING=1 on the way out (a frame folder that ends: exit status 3)."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for i, f in enumerate(GOLDEN_FRAMES[:3]):
        shutil.copy(f, frames / f"{i:04d}.png")
    path = tmp_path / "notify"
    env = dict(os.environ, NOTIFY_SOCKET=str(path), WATCHDOG_USEC="1000000", OIBAR_CONFIG="none")
    env.pop("WATCHDOG_PID", None)
    with bind_notify_socket(path) as sock:
        t0 = time.monotonic()
        proc = subprocess.run(
            [
                sys.executable, "-c", "import sys; from oibar.cli import main; sys.exit(main())",
                "nav", "--camera", str(frames), "--camera-rate-hz", "1", "--port", "none", "--no-log",
            ],
            env=env, capture_output=True, text=True, timeout=120, check=False, cwd=tmp_path,
        )  # fmt: skip
        wall_s = time.monotonic() - t0
        got = drain(sock)
    assert proc.returncode == 3, proc.stderr
    kinds = [m.split("\n", 1)[0] for m in got]
    assert kinds[0] == "READY=1" and kinds[-1] == "STOPPING=1", got
    # 3 frames at 1 Hz: about 3 s of cycles, a pet at most every 0.5 s, one at least every 1 s
    pets = kinds.count("WATCHDOG=1")
    assert 2 <= pets <= 10, (got, wall_s)
    assert all(m.startswith(("READY=1", "WATCHDOG=1", "STOPPING=1")) for m in got)
    assert any("STATUS=" in m for m in got if m.startswith("WATCHDOG=1"))
