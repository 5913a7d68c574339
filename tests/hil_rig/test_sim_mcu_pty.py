"""The simulated MCU alone on a pty in real time (hil/oibar_hil/sim_mcu.py): a real `oibar link`
session against it, its clock against the wall clock, and its stop."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OIBAR = [sys.executable, "-c", "import sys; from oibar.cli import main; sys.exit(main())"]


def env() -> dict[str, str]:
    return dict(
        os.environ, PYTHONPATH=os.pathsep.join([str(ROOT / "hil"), str(ROOT / "host")]), OIBAR_CONFIG="none"
    )


def start(sim_mcu_path: Path, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "oibar_hil.sim_mcu", "--pty", "--mcu", str(sim_mcu_path), *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env(), cwd=ROOT,
    )  # fmt: skip


def test_oibar_link_session_through_the_command_mode(sim_mcu_path: Path) -> None:
    """One command: the simulator starts, runs `oibar link` on its pty, and exits with its status."""
    proc = start(
        sim_mcu_path, "--duration-s", "60", "--", *OIBAR, "link", "--port", "{pty}",
        "--command", "NOOP", "APPROACH_ARM", "--seconds", "1",
    )  # fmt: skip
    out, err = proc.communicate(timeout=90)
    assert proc.returncode == 0, out + err
    pty = re.search(r"^PTY (\S+)$", out, re.M)
    assert pty and pty.group(1).startswith("/dev/pts/")
    assert f"connected to {pty.group(1)}: firmware sim-" in out and "protocol 2" in out
    assert "CMD_NOOP: accepted, reason NACK_NONE, state STATE_IDLE" in out
    # APPROACH_ARM needs the mechanism home (latch home, plane retracted: the simulated
    # mechanism's switches) and is accepted
    assert "CMD_APPROACH_ARM: accepted, reason NACK_NONE, state STATE_APPROACH_READY" in out
    assert "real-time factor" in err  # it stopped when the command ended, not at --duration-s
    sim_s = float(re.search(r"sim-mcu: ([0-9.]+) s simulated", err).group(1))  # type: ignore[union-attr]
    assert sim_s < 30


def test_runs_in_real_time_and_stops_on_sigterm(sim_mcu_path: Path) -> None:
    from oibar.link.client import LinkClient

    proc = start(sim_mcu_path)
    try:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        assert line.startswith("PTY "), line
        client = LinkClient(line.split()[1])
        try:
            info = client.connect()
            assert info.firmware_version.startswith("sim-")

            def uptime_now() -> tuple[float, float]:
                """(MCU uptime, wall clock) at the arrival of a fresh telemetry frame."""
                seen = client.telemetry.uptime_ms if client.telemetry else None
                deadline = time.monotonic() + 2
                while time.monotonic() < deadline:
                    tm = client.telemetry
                    if tm is not None and tm.uptime_ms != seen:
                        return tm.uptime_ms / 1000, time.monotonic()
                    time.sleep(0.002)
                raise AssertionError("no telemetry for 2 s")

            mcu0, wall0 = uptime_now()
            time.sleep(4.0)
            mcu1, wall1 = uptime_now()
        finally:
            client.close()
        factor = (mcu1 - mcu0) / (wall1 - wall0)
        # telemetry every 100 ms: +-0.1 s of the 4 s either way; a lockstep flat out would be 10x+
        assert 0.9 <= factor <= 1.1, factor
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    m = re.search(r"real-time factor ([0-9.]+)", err)
    assert m and 0.95 <= float(m.group(1)) <= 1.05, err
    assert "final state STATE_IDLE" in err


def test_missing_executable_is_a_clear_error(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "oibar_hil.sim_mcu", "--pty", "--mcu", str(tmp_path / "nope")],
        capture_output=True, text=True, env=env(), cwd=ROOT, timeout=60, check=False,
    )  # fmt: skip
    assert proc.returncode == 2
    assert "make firmware-host" in proc.stderr and "Traceback" not in proc.stderr
