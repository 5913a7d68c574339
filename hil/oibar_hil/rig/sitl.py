"""``make sitl``: the program that flies, ``oibar nav``, flies the mission against the rig.

The PX4 SITL pattern: the same program a user runs on the companion computer, started as its
own process, with its sensors and actuators on the simulator:

- its serial port is a pseudo-terminal whose other end the rig bridges, byte for byte through
  the rig's wire, to the simulated MCU's UART (the firmware in lockstep with the plant);
- its camera is ``frames+tcp://127.0.0.1:PORT`` (oibar.camera.stream): the rig renders the scene
  for the world's pose every 100 ms and serves the frames, as a user's own camera bridge would;
- its vehicle is ``udp://127.0.0.1:PORT`` (oibar.nav.vehicle.UdpJsonVehicle): the rig is the
  vehicle's GNC computer, takes the velocity setpoints and answers with the odometry and the
  relative attitude.

Everything runs in real time on loopback only: the rig paces its lockstep loop to the wall clock.
The run ends when ``oibar nav`` exits (its guidance finished the mission) or at the scenario's
``max_time_s``. The output names the process (PID, exit status) and its own flight log (MCAP, with
its frames), and the rig's checks (capture envelope, forces, valves, outcome) judge the mission
from ground truth. One more check opens that flight log with the ``mcap`` reader and wants every
channel of oibar.nav.flightlog.CHANNELS in it (``flight_log_channels``).

    python -m oibar_hil.rig.sitl [--scenario hil/scenarios/nominal.yaml] [--out build/sitl]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import time
import tty
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from oibar.camera.stream import FrameStreamServer
from oibar.link.core import LinkCore
from oibar_hil.rig.checks import evaluate
from oibar_hil.rig.runner import REPO_ROOT, Rig, RunResult
from oibar_hil.rig.scenario import load_scenario

DEFAULT_SCENARIO = REPO_ROOT / "hil" / "scenarios" / "nominal.yaml"
DEFAULT_OUT = REPO_ROOT / "build" / "sitl"
DEFAULT_MODEL = REPO_ROOT / "models" / "oibarnet.onnx"
SETPOINT_STALE_S = 0.5  # the GNC holds when the daemon's setpoints stop (a hung or dead daemon)


def oibar_command() -> list[str]:
    """The `oibar` command a user runs: the installed console script next to this Python, or
    the same entry point through the interpreter."""
    script = Path(sys.executable).with_name("oibar")
    if script.exists():
        return [str(script)]
    return [sys.executable, "-c", "import sys; from oibar.cli import main; sys.exit(main())"]


class PtyPort:
    """A pseudo-terminal: ``oibar nav`` opens ``path`` as its serial port; the rig reads and
    writes the other end."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)

    def read(self) -> bytes:
        try:
            return os.read(self.master, 65536)
        except (BlockingIOError, OSError):
            return b""

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self.master, view)
            except BlockingIOError:
                time.sleep(0.001)
                continue
            view = view[n:]

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class SitlRig(Rig):
    """The rig with an external host: the ``oibar nav`` process."""

    def __init__(
        self,
        scenario: Any,
        *,
        out_dir: Path,
        model: Path = DEFAULT_MODEL,
        scene: str = "seq01",
        mcu_path: Path | None = None,
        threads: int = 2,
        speed: float = 1.0,
    ) -> None:
        super().__init__(scenario, mcu_path=mcu_path, out_dir=out_dir, nav="truth")
        from oibar_hil.rig.camera import RigCamera

        self.model = Path(model)
        self.threads = threads
        self.speed = speed
        self.camera = RigCamera(scene=scene, seed=scenario.seed)
        self.proc: subprocess.Popen | None = None
        self.nav_log_dir = Path(out_dir) / "oibar_nav"
        self.footer: dict | None = None
        self._ctl = SimpleNamespace(finished=False, outcome="running", notes=[])
        self._setpoint = SimpleNamespace(v_sp_D_mps=np.zeros(3), w_sp_rad_s=np.zeros(3), phase="")
        self._setpoint_wall = -1e18
        self._setpoint_t = 0.0
        self._gnc_addr: Any = None
        self.frames_sent = 0

    # -- the external host ----------------------------------------------------------------

    @property  # type: ignore[misc]  # Rig's controller is the mission's; here it is another process's
    def controller(self) -> Any:
        return self._ctl

    def _new_host(self) -> None:
        # the rig's own view of the link: a passive decoder of the MCU's bytes (telemetry for
        # the report); it never sends. The host is the oibar nav process.
        self.session = LinkCore(auto_connect=False)  # type: ignore[assignment]  # a passive decoder, not a host session
        self.pty = PtyPort()
        self.frames = FrameStreamServer("127.0.0.1", 0)
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.udp.bind(("127.0.0.1", 0))
        self.udp.setblocking(False)
        self.nav_log_dir.mkdir(parents=True, exist_ok=True)
        cmd = oibar_command() + [
            "nav",
            "--camera",
            self.frames.url,
            "--port",
            self.pty.path,
            "--vehicle",
            f"udp://127.0.0.1:{self.udp.getsockname()[1]}",
            "--model",
            str(self.model),
            "--log",
            str(self.nav_log_dir),
            "--record-frames",
            "--threads",
            str(self.threads),
            "--target-pressure-kpa",
            str(self.sc.mission.target_kpa),
            "--duration-s",
            str(self.sc.rig.max_time_s),
        ]
        env = dict(os.environ)
        inherited = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
        env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT / "host"), *inherited])
        assert self.out_dir is not None  # a SitlRig is always given one
        self._stdout = open(Path(self.out_dir) / "oibar_nav.out", "wb")  # noqa: SIM115  (closed by stop())
        self.command = cmd
        self.proc = subprocess.Popen(
            cmd, stdout=self._stdout, stderr=subprocess.STDOUT, env=env, cwd=REPO_ROOT
        )
        print(f"sitl: started `oibar nav` (PID {self.proc.pid}): {' '.join(cmd[-22:])}", flush=True)
        self._wall0 = time.monotonic()
        self._t_at_wall0 = self.t_s

    def _host_finished(self) -> bool:
        if self.proc is None or self.proc.poll() is None:
            return False
        if not self._ctl.finished:
            self._ctl.finished = True
            self._read_footer()
        return True

    @property
    def flight_log(self) -> Path:
        return self.nav_log_dir / "flight.mcap"

    def _read_footer(self) -> None:
        from oibar.nav.flightlog import FlightLogError, read_summary

        try:
            rec = read_summary(self.flight_log)
        except (FlightLogError, OSError):
            return
        if rec is not None:
            self.footer = rec
            self._ctl.outcome = rec.get("outcome", "running")
            self._ctl.notes = [(float(t), f"oibar nav: {n}") for t, n in rec.get("notes", [])]

    def _host_step(self, out: Any) -> Any:
        # the serial cable: host bytes into the wire (the MCU reads them next exchange), the
        # MCU's bytes that crossed the wire out to the host's port
        host_bytes = self.pty.read()
        if host_bytes:
            self.wire.host_end.write(host_bytes)
        mcu_bytes = self.wire.host_end.read()
        if mcu_bytes:
            self.session.receive(mcu_bytes, self.t_s)
            self.pty.write(mcu_bytes)
        if self.session.telemetry is not None:
            self.host_fault_flags |= self.session.telemetry.fault_flags
        self._vehicle()
        if self.t_s >= self._next_guidance:
            self._next_guidance += self.sc.rig.guidance_period_s
            s = self.world.s
            image = self.camera.render(s.r_D_m, s.att_rad, t_s=self.t_s).image
            if self.frames.send(image, self.t_s):
                self.frames_sent += 1
        # real time: the lockstep loop waits for the wall clock
        ahead = (self.t_s - self._t_at_wall0) / self.speed - (time.monotonic() - self._wall0)
        if ahead > 0:
            time.sleep(ahead)
        return self._setpoint

    def _vehicle(self) -> None:
        """The GNC computer: setpoints in, odometry back (UdpJsonVehicle's datagrams)."""
        now = time.monotonic()
        got = False
        while True:
            try:
                data, addr = self.udp.recvfrom(4096)
            except (BlockingIOError, OSError):
                break
            try:
                msg = json.loads(data)
                v = np.asarray(msg["v_D_mps"], dtype=float)
                w = np.asarray(msg["w_rad_s"], dtype=float)
            except (ValueError, KeyError, TypeError):
                continue
            self._setpoint = SimpleNamespace(v_sp_D_mps=v, w_sp_rad_s=w, phase=str(msg.get("phase", "")))
            self._setpoint_t = float(msg.get("t_s", 0.0))
            self._setpoint_wall = now
            self._gnc_addr = addr
            got = True
        if now - self._setpoint_wall > SETPOINT_STALE_S:
            self.world.set_setpoint(np.zeros(3), np.zeros(3))
        else:
            self.world.set_setpoint(self._setpoint.v_sp_D_mps, self._setpoint.w_sp_rad_s)
        if got and self._gnc_addr is not None:
            odo = self.world.relative_velocity(self.t_s)
            att = self.world.relative_attitude(self.t_s)
            if odo is not None or att is not None:
                # its time of validity on the daemon's clock: the setpoint's t_s plus our time since
                back: dict[str, Any] = {"t_s": self._setpoint_t + (time.monotonic() - self._setpoint_wall)}
                if odo is not None:
                    back.update(v_D_mps=[float(x) for x in odo.v_D_mps], sigma_mps=float(odo.sigma_mps))
                if att is not None:
                    back.update(att_rad=[float(x) for x in att.att_rad], att_sigma_rad=float(att.sigma_rad))
                try:
                    self.udp.sendto(json.dumps(back).encode(), self._gnc_addr)
                except OSError:
                    pass

    # -- the run ---------------------------------------------------------------------------

    def run(self) -> RunResult:
        try:
            result = super().run()
        finally:
            self._stop_host()
        result.metrics.update(self.host_metrics())
        return result

    def _stop_host(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()  # SIGTERM: oibar nav holds the vehicle, closes, writes its footer
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
            self._read_footer()
        for closer in (
            getattr(self, "frames", None),
            getattr(self, "pty", None),
            getattr(self, "udp", None),
            getattr(self, "_stdout", None),
            self.camera,
        ):
            if closer is not None:
                try:
                    closer.close()
                except Exception:
                    pass

    def host_metrics(self) -> dict:
        summary = (self.footer or {}).get("summary", {})
        return {
            "host": "oibar nav (separate process)",
            "host_pid": self.proc.pid if self.proc else None,
            "host_exit_status": self.proc.returncode if self.proc else None,
            "host_flight_log": str(self.flight_log),
            **flight_log_metrics(self.flight_log),
            "host_cycles": summary.get("cycles"),
            "host_missed_deadlines": summary.get("missed_deadlines"),
            "host_frames_used": summary.get("frames_used"),
            "host_frame_to_command_ms_p99": summary.get("frame_to_command_ms_p99"),
            "frames_served": self.frames_sent,
        }


def flight_log_metrics(path: Path) -> dict:
    """The ``mcap`` reader's view of the daemon's flight log: its size, whether it was finished,
    its channels and the ones of oibar.nav.flightlog.CHANNELS it lacks."""
    from oibar.nav.flightlog import CHANNELS, FlightLogError, inspect_log

    try:
        inv = inspect_log(path)
    except (FlightLogError, OSError) as exc:
        return {"flight_log_error": str(exc), "flight_log_missing_channels": list(CHANNELS)}
    return {
        "flight_log_bytes": inv.size_bytes,
        "flight_log_complete": inv.complete,
        "flight_log_duration_s": inv.duration_s,
        "flight_log_messages": dict(sorted(inv.message_counts.items())),
        "flight_log_missing_channels": inv.missing(),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_hil.rig.sitl", description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", type=Path, default=DEFAULT_SCENARIO)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    ap.add_argument("--mcu", type=Path, default=None, help="simulated MCU executable")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime threads of oibar nav")
    args = ap.parse_args(argv)
    sc = load_scenario(args.scenario)
    out_dir = args.out / sc.name
    print(
        f"sitl: {sc.name} from {sc.start.range_m:g} m in real time (about {sc.rig.max_time_s / 60:.0f} min at most); "
        f"output in {out_dir}",
        flush=True,
    )
    rig = SitlRig(sc, out_dir=out_dir, model=args.model, mcu_path=args.mcu, threads=args.threads)
    result = rig.run()
    result.checks = evaluate(result)
    from oibar_hil.rig.report import write_report

    result.report_path = write_report(result, out_dir)
    m = result.metrics
    print(
        f"sitl: `oibar nav` (PID {m['host_pid']}, exit status {m['host_exit_status']}) flew {sc.name}: "
        f"outcome {result.outcome}, {m.get('host_cycles')} cycles of its own, "
        f"{m.get('host_missed_deadlines')} missed deadlines, frame-to-command p99 "
        f"{m.get('host_frame_to_command_ms_p99') or float('nan'):.1f} ms, "
        f"{m['frames_served']} frames served; {result.sim_time_s:.0f} s in {result.wall_time_s:.0f} s wall"
    )
    print(f"  its flight log: {m['host_flight_log']}; its output: {out_dir / 'oibar_nav.out'}")
    for c in result.checks:
        verdict = "n/a " if c.ok is None else ("pass" if c.ok else "FAIL")
        print(f"  [{verdict}] {c.id:<32} {c.text}  ({c.measured})")
    missing = m.get("flight_log_missing_channels") or []
    log_ok = not missing and bool(m.get("flight_log_complete"))
    size_mb = (m.get("flight_log_bytes") or 0) / 1e6
    per_min = size_mb / max(m.get("flight_log_duration_s") or 0.0, 1e-9) * 60.0
    print(
        f"  [{'pass' if log_ok else 'FAIL'}] {'flight_log_channels':<32} the flight log opens with the mcap reader, "
        f"finished, with every channel  ({m.get('flight_log_error') or ''}"
        f"{size_mb:.1f} MB, {per_min:.1f} MB/min, "
        f"{'complete' if m.get('flight_log_complete') else 'NOT finished'}, "
        f"{'all channels' if not missing else 'missing ' + ', '.join(missing)})"
    )
    print(f"  report: {result.report_path}")
    return 0 if result.passed and log_ok and m["host_exit_status"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
