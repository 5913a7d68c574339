"""The simulated MCU on its own, on a pseudo-terminal, in real time: a bench for ``oibar nav``
and ``oibar link`` without the board.

    python -m oibar_hil.sim_mcu --pty                    # prints "PTY /dev/pts/N", runs until Ctrl-C
    python -m oibar_hil.sim_mcu --pty --frames -- oibar nav --port {pty} --camera {frames}

It is the rig's own machinery (oibar_hil.rig.runner.Rig): the real firmware built for this
machine (``oibar_sim_mcu``, ``make firmware-host``) in lockstep with the simulated mechanism
(latch stepper, fluidic plane, valves, tanks: rig/mechanism.py) and the wire, with the lockstep
loop paced to the wall clock instead of running flat out, and the host's end of the UART on a
pty that any program opens as its serial port. Nothing of the flight code is copied.

The service vehicle holds at the scenario's start (10 m from the target in the nominal
scenario): velocity setpoints go nowhere, so the mechanism sees no contact unless commanded
through a phase that does not need one. ``--frames`` also serves the rig's rendered camera for
that pose at 10 Hz over ``frames+tcp://`` (``{frames}`` in the command), rendered anew once per
second (the view changes only with the light).

With a command after ``--``, ``{pty}`` and ``{frames}`` in it are replaced, the command runs
while the simulator does, and its exit status is ours; Ctrl-C or SIGTERM reach it first (its
planned end of the MCU session is answered) and the simulator stops when it has exited.

exit status: 0 stopped by Ctrl-C/SIGTERM or --duration-s, or the command's own status;
2 bad argument or the simulated MCU could not start (not built: `make firmware-host`).
"""

from __future__ import annotations

import argparse
import dataclasses
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from oibar import argtypes, pb
from oibar_hil.rig.fw_params import FirmwareParamsError, UnknownFirmwareParam
from oibar_hil.rig.runner import REPO_ROOT, Rig, RunResult
from oibar_hil.rig.scenario import load_scenario

DEFAULT_SCENARIO = REPO_ROOT / "hil" / "scenarios" / "nominal.yaml"
EXIT_OK = 0
EXIT_ERROR = 2
FOREVER_S = 10 * 365 * 86400.0  # "until stopped", as a simulated-time limit for the rig's loop
RENDER_EVERY_S = 1.0  # --frames: a new render per simulated second (the vehicle holds)


class PtyMcuRig(Rig):
    """The rig with its host outside: the host's end of the wire is a pty, paced in real time."""

    def __init__(
        self,
        scenario: Any,
        *,
        mcu_path: Path | None = None,
        out_dir: Path | None = None,
        speed: float = 1.0,
        frames: bool = False,
        command: list[str] | None = None,
        announce: Any = print,
    ) -> None:
        super().__init__(scenario, mcu_path=mcu_path, out_dir=out_dir, nav="truth")
        self.speed = speed
        self.serve_frames = frames
        self.command = command
        self.announce = announce
        self.stop_requested = False
        self.child: subprocess.Popen[bytes] | None = None
        self.camera: Any = None
        self.frames_server: Any = None
        self.frames_sent = 0
        self.max_lag_s = 0.0  # how far the loop fell behind the wall clock at worst
        self._ctl = SimpleNamespace(finished=False, outcome="bench (no mission)", notes=[])
        self._still = (np.zeros(3), np.zeros(3))
        self._image: Any = None
        self._rendered_t_s = 0.0

    @property  # type: ignore[misc]  # Rig's controller is the mission's; here it is another process's
    def controller(self) -> Any:
        return self._ctl

    def _new_host(self) -> None:
        from oibar.link.core import LinkCore
        from oibar_hil.rig.sitl import PtyPort

        # the rig's own view of the link, a passive decoder of the MCU's bytes (telemetry for
        # the summary); it never sends. The host is whatever opens the pty.
        self.session = LinkCore(auto_connect=False)  # type: ignore[assignment]  # a passive decoder, not a host session
        self.pty = PtyPort()
        urls = {"pty": self.pty.path, "frames": ""}
        if self.serve_frames:
            from oibar.camera.stream import FrameStreamServer
            from oibar_hil.rig.camera import RigCamera

            self.camera = RigCamera(scene="seq01", seed=self.sc.seed)
            self.frames_server = FrameStreamServer("127.0.0.1", 0)
            urls["frames"] = self.frames_server.url
        self.announce(f"PTY {self.pty.path}")
        if self.frames_server is not None:
            self.announce(f"FRAMES {self.frames_server.url}")
        if self.command:
            cmd = [
                arg.replace("{pty}", urls["pty"]).replace("{frames}", urls["frames"]) for arg in self.command
            ]
            print(f"sim-mcu: running {' '.join(cmd)}", file=sys.stderr, flush=True)
            self.child = subprocess.Popen(cmd)  # in the caller's folder: its relative paths hold
        self._wall0 = time.monotonic()
        self._t_at_wall0 = self.t_s

    def _host_finished(self) -> bool:
        if self.child is not None:
            return self.child.poll() is not None  # a stop waits for the command's planned end
        return self.stop_requested

    def _host_step(self, out: Any) -> Any:
        # the serial cable: the pty's bytes into the wire, the MCU's bytes out to the pty
        host_bytes = self.pty.read()
        if host_bytes:
            self.wire.host_end.write(host_bytes)
        mcu_bytes = self.wire.host_end.read()
        if mcu_bytes:
            self.session.receive(mcu_bytes, self.t_s)
            self.pty.write(mcu_bytes)
        self.world.set_setpoint(*self._still)  # the vehicle holds
        if self.frames_server is not None and self.t_s >= self._next_guidance:
            self._next_guidance += self.sc.rig.guidance_period_s
            # the vehicle holds, so the view changes only with the light: a render per simulated
            # second keeps the loop in real time on two cores (a render costs tens of ms on Mesa's
            # CPU renderer); every frame in between is the last image, stamped with its own time
            if self._image is None or self.t_s - self._rendered_t_s >= RENDER_EVERY_S:
                s = self.world.s
                self._image = self.camera.render(s.r_D_m, s.att_rad, t_s=self.t_s).image
                self._rendered_t_s = self.t_s
            if self.frames_server.send(self._image, self.t_s):
                self.frames_sent += 1
        # real time: wait for the wall clock; when behind, run flat out to catch up
        ahead = (self.t_s - self._t_at_wall0) / self.speed - (time.monotonic() - self._wall0)
        if ahead > 0:
            time.sleep(ahead)
        else:
            self.max_lag_s = max(self.max_lag_s, -ahead)
        return out

    def request_stop(self, signum: int) -> None:
        if self.child is not None and self.child.poll() is None:
            try:
                self.child.send_signal(signal.SIGTERM)  # its planned stop; a second one is ignored
            except OSError:
                pass
        self.stop_requested = True

    def close(self) -> None:
        if self.child is not None and self.child.poll() is None:
            self.child.terminate()
            try:
                self.child.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.child.kill()
                self.child.wait()
        for closer in (self.frames_server, getattr(self, "pty", None), self.camera):
            if closer is not None:
                try:
                    closer.close()
                except Exception:
                    pass


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m oibar_hil.sim_mcu",
        description="The simulated MCU (the real firmware) with the simulated mechanism, alone on a "
        "pseudo-terminal, in real time: a serial port for `oibar nav` and `oibar link` on the bench.",
        epilog="exit status: 0 stopped (Ctrl-C, SIGTERM, --duration-s) or the command's own status; "
        "2 bad argument or the simulated MCU could not start.",
    )
    ap.add_argument(
        "--pty",
        action="store_true",
        required=True,
        help="put the MCU's UART on a new pseudo-terminal and print 'PTY <path>' on stdout",
    )
    ap.add_argument("--frames", action="store_true", help="also serve the rendered camera (frames+tcp://)")
    ap.add_argument(
        "--scenario",
        type=Path,
        default=DEFAULT_SCENARIO,
        help="start pose and plant (YAML; its faults are not injected)",
    )
    ap.add_argument(
        "--mcu", type=Path, default=None, help="simulated MCU executable (default: build/fw-host)"
    )
    ap.add_argument(
        "--duration-s", type=argtypes.positive(), default=None, metavar="S", help="stop after S seconds"
    )
    ap.add_argument(
        "--speed",
        type=argtypes.number(0.1, 10.0),
        default=1.0,
        metavar="X",
        help="simulated seconds per wall second, 0.1-10 (default: 1, real time)",
    )
    ap.add_argument(
        "command", nargs=argparse.REMAINDER, help="after --: a command to run against it ({pty}, {frames})"
    )
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    try:
        sc = load_scenario(args.scenario)
    except (OSError, ValueError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        print(f"sim-mcu: error: scenario {args.scenario}: {why}", file=sys.stderr)
        return EXIT_ERROR
    limit = args.duration_s if args.duration_s is not None else FOREVER_S
    # the scenario's start and plant only: its faults act on the rig's own host, which is not here
    sc = dataclasses.replace(sc, faults=[], rig=dataclasses.replace(sc.rig, max_time_s=limit * 1.0))
    try:  # the scenario's parameter names are checked against this MCU's table here
        rig = PtyMcuRig(
            sc,
            mcu_path=args.mcu,
            speed=args.speed,
            frames=args.frames,
            command=command or None,
            announce=lambda line: print(line, flush=True),
        )
    except (UnknownFirmwareParam, FirmwareParamsError) as exc:
        print(f"sim-mcu: error: scenario {args.scenario}: {exc}", file=sys.stderr)
        return EXIT_ERROR
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: rig.request_stop(signum))
    try:
        result: RunResult = rig.run()
    except FileNotFoundError as exc:
        print(f"sim-mcu: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    finally:
        rig.close()
    tm = rig.session.telemetry
    state = pb.enum_name(pb.State, tm.state) if tm is not None else result.metrics.get("final_state")
    factor = result.sim_time_s / result.wall_time_s if result.wall_time_s > 0 else float("nan")
    print(
        f"sim-mcu: {result.sim_time_s:.1f} s simulated in {result.wall_time_s:.1f} s wall "
        f"(real-time factor {factor:.3f}, worst lag {rig.max_lag_s * 1e3:.0f} ms), final state {state}, "
        f"{result.metrics['lockstep_frames']} lockstep exchanges"
        + (f", {rig.frames_sent} frames served" if rig.frames_server is not None else ""),
        file=sys.stderr,
        flush=True,
    )
    if rig.child is not None:
        return int(rig.child.returncode or 0)
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
