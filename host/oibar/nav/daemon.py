"""The navigation daemon: camera -> OibarNet -> filter -> guidance -> vehicle and MCU, at 10 Hz.

Threads: the camera reader (oibar.camera.LatestFrame: the cycle only ever sees the newest
frame), the link client's reader and supervisor (oibar.link.LinkClient), and one mechanism
worker that runs the stop-and-wait mechanism requests (a command can take up to the link's
retry budget, ~1 s; it must not stall the 10 Hz cycle). Everything else runs in the cycle, on
absolute deadlines (``next = start + k * period``), so one slow cycle does not shift the rest.

Failure behaviour (each has a test in tests/host/test_nav_daemon.py):
- model file missing or corrupt: ModelFileError at start, before the camera or the port is opened;
- camera lost (unplugged, stream ended): the cycle gets no frame, guidance holds; the daemon
  reopens the camera every ``camera_retry_s``; after ``nav_lost_abort_s`` guidance aborts;
- link lost: no mechanism command is sent (the request fails with LinkDown, guidance retries when
  the MCU is back), navigation updates are skipped, the vehicle holds; LinkClient reconnects;
- low confidence or a gated outlier: that cycle holds;
- the vehicle's odometry (VehicleInterface.relative_velocity) raising: camera only that cycle,
  counted in ``odometry_errors``; a gated or malformed one is simply not fused;
- log disk full: logging stops with one warning, navigation goes on.
"""

from __future__ import annotations

import queue
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from oibar import pb
from oibar.camera import CameraError, CameraLost, CameraSource, LatestFrame
from oibar.nav.core import Navigator, NavStep
from oibar.nav.cyclelog import CycleLog
from oibar.nav.guidance import Guidance, GuidanceOutput, MechRequest, Observation, RequestResult
from oibar.nav.vehicle import NullVehicle, VehicleInterface


@dataclass
class DaemonParams:
    rate_hz: float = 10.0             # SPEC section 5
    camera_lost_timeout_s: float = 1.0
    camera_retry_s: float = 2.0       # reopen a lost camera this often
    status_every_s: float = 0.5       # live status line refresh


@dataclass
class DaemonStats:
    cycles: int = 0
    missed_deadlines: int = 0
    cycle_ms: list[float] = field(default_factory=list)           # cycle start -> end of work
    frame_to_command_ms: list[float] = field(default_factory=list)  # capture -> setpoint sent
    frames_used: int = 0
    camera_reopens: int = 0
    holds: int = 0
    odometry_errors: int = 0          # the vehicle's relative_velocity raised

    def summary(self) -> dict:
        def pct(xs, q):
            return float(np.percentile(xs, q)) if xs else None
        return {"cycles": self.cycles, "missed_deadlines": self.missed_deadlines, "frames_used": self.frames_used,
                "camera_reopens": self.camera_reopens, "hold_cycles": self.holds,
                "odometry_errors": self.odometry_errors,
                "cycle_ms_median": pct(self.cycle_ms, 50), "cycle_ms_p99": pct(self.cycle_ms, 99),
                "frame_to_command_ms_median": pct(self.frame_to_command_ms, 50),
                "frame_to_command_ms_p99": pct(self.frame_to_command_ms, 99),
                "frame_to_command_ms_max": max(self.frame_to_command_ms) if self.frame_to_command_ms else None}


class MechanismWorker:
    """Runs one mechanism request at a time on its own thread; results come back in order."""

    def __init__(self, link: Any) -> None:
        self.link = link
        self._jobs: queue.Queue = queue.Queue(maxsize=1)
        self._results: list[RequestResult] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="oibar-mech", daemon=True)
        self._thread.start()

    def submit(self, req: MechRequest) -> None:
        self._jobs.put_nowait(req)   # guidance sends at most one at a time (stop and wait)

    def take_results(self) -> list[RequestResult]:
        with self._lock:
            out, self._results = self._results, []
        return out

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                req = self._jobs.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                if req.kind == "param_set":
                    r = self.link.param_set(req.param_id, req.value)
                    res = RequestResult(req, r.ok, r.reason)
                else:
                    r = self.link.command(req.opcode, req.target_kpa if req.target_kpa else None)
                    res = RequestResult(req, r.accepted, r.reason, r.state)
            except Exception as exc:  # LinkDown, LinkTimeout, closed port: guidance hears it
                res = RequestResult(req, False, type(exc).__name__)
            with self._lock:
                self._results.append(res)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)


class NavDaemon:
    def __init__(self, navigator: Navigator, guidance: Guidance, camera: CameraSource,
                 link: Any | None = None, vehicle: VehicleInterface | None = None,
                 log: CycleLog | None = None, params: DaemonParams | None = None,
                 status: Callable[[str], None] | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.nav = navigator
        self.guidance = guidance
        self.camera_source = camera
        self.link = link
        self.vehicle = vehicle or NullVehicle()
        self.log = log
        self.p = params or DaemonParams()
        self.status = status
        self.clock = clock
        self.stats = DaemonStats()
        self._stop = threading.Event()
        self._cam: LatestFrame | None = None
        self._cam_error = ""
        self._next_cam_try = 0.0
        self._worker = MechanismWorker(link) if link is not None else None
        self._awaiting: MechRequest | None = None
        self._t0 = clock()
        self._last_status = -1e9
        self._opened_once = False
        self._last_out: GuidanceOutput | None = None
        self._last_step: NavStep | None = None

    # -- camera -------------------------------------------------------------------------

    def _ensure_camera(self, now: float) -> LatestFrame | None:
        if self._cam is None:
            if now < self._next_cam_try:
                return None
            self._next_cam_try = now + self.p.camera_retry_s
            try:
                self._cam = LatestFrame(self.camera_source, lost_timeout_s=self.p.camera_lost_timeout_s).start()
                if self._opened_once:
                    self.stats.camera_reopens += 1
                self._opened_once = True
                self._cam_error = ""
            except CameraError as exc:
                self._cam_error = str(exc)
                return None
        return self._cam

    def _drop_camera(self, exc: BaseException, now: float) -> None:
        self._cam_error = str(exc)
        if self._cam is not None:
            self._cam.stop()
        self._cam = None
        self._next_cam_try = now + self.p.camera_retry_s

    def wait_frame(self, until: float, min_capture_host: float = -1e18):
        """The newest frame captured at or after ``min_capture_host`` (host clock), waiting for
        one until ``until``; None if none came (or the camera is gone: then ``_cam_error`` says
        why). Waiting for the frame, rather than ticking on our own, keeps frame-to-command
        latency at the processing time instead of up to a whole camera period."""
        while True:
            now = self.clock()
            cam = self._ensure_camera(now)
            remaining = until - now
            if cam is None:
                if remaining > 0:
                    self._stop.wait(min(remaining, max(0.0, self._next_cam_try - now)))
                    if self.clock() < until and not self._stop.is_set():
                        continue
                return None
            try:
                frame = cam.poll() if remaining <= 0 else cam.get(timeout_s=remaining)
            except CameraError as exc:
                if cam.seconds_since_last_capture <= self.p.camera_lost_timeout_s and \
                        isinstance(exc, CameraLost) and cam.running:
                    return None          # just no frame before `until`: the camera is fine
                self._drop_camera(exc, self.clock())
                return None
            if frame is None:
                return None
            if frame.t_host >= min_capture_host:
                return frame
            # older than the decimation allows (camera faster than the cycle): take the next

    # -- one cycle ----------------------------------------------------------------------

    def cycle(self, frame: Any = None) -> tuple[NavStep, GuidanceOutput]:
        """One cycle on ``frame`` (None: no new frame this time)."""
        start = self.clock()
        t_s = start - self._t0
        odometry = self._odometry(t_s)
        if frame is not None:
            step = self.nav.step(t_s, frame.image, frame_t_s=frame.t_host - self._t0, frame_seq=frame.seq,
                                 odometry=odometry)
            self.stats.frames_used += 1
        else:
            step = self.nav.step(t_s, None, odometry=odometry)
            if self._cam_error:
                step.hold_reason = step.solution.hold_reason = f"camera: {self._cam_error}"
        link_up = bool(self.link is not None and self.link.link_alive)
        telemetry = self.link.telemetry if self.link is not None else None
        events = []
        if self.link is not None:
            while (ev := self.link.next_event(0)) is not None:
                events.append(ev)
        results = self._worker.take_results() if self._worker else []
        for r in results:
            if r.request is self._awaiting:
                self._awaiting = None
        out = self.guidance.step(t_s, Observation(t_s, step.solution, link_up, telemetry, events, results))
        self.vehicle.send(t_s, out.v_sp_D_mps, out.w_sp_rad_s, out.phase)
        sent = self.clock()
        if link_up:
            n = out.nav
            try:
                self.link.send_nav(frame_id=n.frame_id, t_cam_target_m=(n.t_cam_target_m.x, n.t_cam_target_m.y,
                                                                         n.t_cam_target_m.z),
                                   q_cam_target=(n.q_cam_target.w, n.q_cam_target.x, n.q_cam_target.y, n.q_cam_target.z),
                                   range_m=n.range_m, closing_speed_mps=n.closing_speed_mps, phase=n.phase,
                                   confidence=n.confidence, valid=n.valid)
            except Exception:  # link dropped between the check and the send: next cycle
                pass
            if out.request is not None and self._worker is not None:
                self._awaiting = out.request
                self._worker.submit(out.request)
        end = self.clock()
        st = self.stats
        st.cycles += 1
        st.cycle_ms.append((end - start) * 1e3)
        if frame is not None:
            st.frame_to_command_ms.append((sent - frame.t_host) * 1e3)
        if step.hold_reason:
            st.holds += 1
        self._log_cycle(t_s, frame, step, out, link_up, telemetry, (end - start) * 1e3, odometry)
        self._last_out, self._last_step = out, step
        return step, out

    def _odometry(self, t_s: float) -> Any:
        """The vehicle's own relative velocity, if it reports one (VehicleInterface.relative_velocity)."""
        try:
            return self.vehicle.relative_velocity(t_s)
        except Exception:  # a failing vehicle sensor must not stop navigation: camera only this cycle
            self.stats.odometry_errors += 1
            return None

    @staticmethod
    def _odometry_record(odometry: Any, upd: Any) -> dict | None:
        """The vehicle's measurement as fed (replay feeds it again) and the filter's verdict."""
        if odometry is None:
            return None
        try:
            rec = {"t_s": float(odometry[0]), "v_D_mps": [float(v) for v in odometry[1]],
                   "sigma_mps": float(odometry[2])}
        except (TypeError, ValueError, IndexError):
            rec = {"malformed": repr(odometry)[:80]}
        return {**rec, "reason": upd.reason if upd is not None else "dropped"}

    def _log_cycle(self, t_s, frame, step: NavStep, out: GuidanceOutput, link_up, tm, cycle_ms,
                   odometry: Any = None) -> None:
        if self.log is None:
            return
        est = step.estimate
        frame_file = self.log.save_frame(frame.image, frame.seq) if frame is not None else None
        sol = step.solution
        upd = step.update
        self.log.write({
            "kind": "cycle", "t_s": t_s, "cycle": self.stats.cycles,
            "frame": None if frame is None else {"seq": frame.seq, "t_s": frame.t_host - self._t0, "file": frame_file},
            "estimate": None if est is None else {"T_cam_target_m": est.T_cam_target_m, "q_cam_target": est.q_cam_target,
                                                  "confidence": est.confidence, "latency_ms": est.latency_ms},
            "filter": None if upd is None else {"accepted": upd.accepted, "gated": upd.gated,
                                                "reinitialised": getattr(upd, "reinitialised", False)},
            "odometry": self._odometry_record(odometry, step.velocity_update),
            "nav": {"valid": sol.valid, "r_D_m": sol.r_D_m, "v_D_mps": sol.v_D_mps, "att_rad": sol.att_rad,
                    "hold_reason": sol.hold_reason},
            "guidance": {"phase": out.phase, "v_sp_D_mps": out.v_sp_D_mps, "w_sp_rad_s": out.w_sp_rad_s,
                         "request": out.request.label if out.request else None},
            "link_up": link_up, "mcu_state": pb.enum_name(pb.State, tm.state) if tm is not None else None,
            "timings_ms": {**step.timings_ms, "cycle": cycle_ms},
        })

    # -- the loop -----------------------------------------------------------------------

    def status_line(self) -> str:
        out, step = self._last_out, self._last_step
        if out is None or step is None:
            return "starting"
        sol = step.solution
        tm = self.link.telemetry if self.link is not None else None
        st = pb.enum_name(pb.State, tm.state).replace("STATE_", "") if tm is not None else "-"
        link = "up" if self.link is not None and self.link.link_alive else "DOWN"
        rng = f"{sol.range_m:6.2f} m" if sol.valid else "   -   "
        cyc = self.stats.cycle_ms[-1] if self.stats.cycle_ms else 0.0
        hold = f"  HOLD: {sol.hold_reason}" if sol.hold_reason else ""
        logw = f"  LOG: {self.log.error}" if self.log is not None and self.log.error else ""
        return (f"t {self._last_t():7.1f} s  {out.phase:<18} range {rng}  lat {sol.lateral_m * 100:5.1f} cm  "
                f"conf {sol.confidence:4.2f}  MCU {st:<16} link {link}  cycle {cyc:5.1f} ms  "
                f"missed {self.stats.missed_deadlines}{hold}{logw}")

    def _last_t(self) -> float:
        return self.clock() - self._t0

    def stop(self) -> None:
        self._stop.set()

    def run(self, duration_s: float | None = None, max_cycles: int | None = None) -> dict:
        """Frame-driven at ``rate_hz``: each cycle starts when a frame arrives that was captured
        at least 0.9 periods after the previous one used (a faster camera is decimated); with no
        frame by 1.5 periods after the previous cycle, the cycle runs without one (guidance
        holds, the link and the MCU keep being served). A deadline is missed when a cycle's work
        takes longer than one period, or when cycles are more than 1.5 periods apart while
        frames are coming."""
        period = 1.0 / self.p.rate_hz
        t_start = self.clock()
        self._t0 = t_start
        if self.log is not None:
            self.log.write({"kind": "header", "rate_hz": self.p.rate_hz, "camera": self.camera_source.name,
                            "model": str(getattr(self.nav.estimator, "path", "")),
                            "model_version": getattr(self.nav.estimator, "meta", {}).get("model_version"),
                            "wall_clock_start": time.time()})
        last_start = t_start - period
        last_capture = -1e18
        k = 0
        try:
            while not self._stop.is_set() and not self.guidance.finished:
                if duration_s is not None and self.clock() - t_start >= duration_s:
                    break
                if max_cycles is not None and k >= max_cycles:
                    break
                frame = self.wait_frame(until=last_start + 1.5 * period,
                                        min_capture_host=last_capture + 0.9 * period)
                if self._stop.is_set():
                    break
                start = self.clock()
                if frame is not None:
                    if start - last_start > 1.5 * period + 0.005 and k > 0 and last_capture > -1e17:
                        self.stats.missed_deadlines += 1
                    last_capture = frame.t_host
                self.cycle(frame)
                k += 1
                now = self.clock()
                if now - start > period:
                    self.stats.missed_deadlines += 1
                last_start = start
                if self.status and now - self._last_status >= self.p.status_every_s:
                    self._last_status = now
                    self.status(self.status_line())
        finally:
            self.shutdown()
        return self.stats.summary()

    def shutdown(self) -> None:
        """Vehicle hold, stop the worker, camera and link; write the footer."""
        try:
            self.vehicle.hold(self._last_t())
        except Exception:
            pass
        try:
            self.vehicle.close()
        except Exception:
            pass
        if self._worker is not None:
            self._worker.close()
            self._worker = None
        if self._cam is not None:
            self._cam.stop()
            self._cam = None
        if self.log is not None:
            try:
                vehicle = self.vehicle.statistics()
            except Exception as exc:   # a user's vehicle class: its counters must not lose the footer
                vehicle = {"error": repr(exc)[:80]}
            self.log.write({"kind": "footer", "summary": self.stats.summary(), "outcome": self.guidance.outcome,
                            "notes": self.guidance.notes, "log_lines_lost": self.log.lines_lost,
                            "log_error": self.log.error, "vehicle": vehicle})
            self.log.close()


def install_sigint(daemon: NavDaemon) -> None:
    """Ctrl-C / SIGTERM: finish the current cycle, hold the vehicle, close everything."""
    def handler(signum, _frame):
        daemon.stop()
        print(f"\n{signal.Signals(signum).name}: stopping (vehicle hold, closing link and camera)", file=sys.stderr)
    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


def load_navigator(model_path: str | Path, threads: int = 2) -> Navigator:
    from oibar.nav.pose import PoseEstimator

    return Navigator(PoseEstimator(model_path, threads=threads))


def connect_in_background(link: Any, retry_s: float = 2.0, on_error: Callable[[str], None] | None = None,
                          stop: threading.Event | None = None) -> threading.Thread:
    """Keep calling ``link.connect()`` until it succeeds: a daemon started before the MCU is
    powered (or with the cable out) comes up by itself. After the first handshake the link
    client's own supervisor reconnects."""
    stop = stop or threading.Event()

    from oibar.link.errors import LinkClosed

    def run() -> None:
        last = ""
        while not stop.is_set():
            try:
                link.connect()
                return
            except Exception as exc:  # PortError, LinkTimeout, ProtocolVersionError, closed
                msg = f"{type(exc).__name__}: {exc}"
                if on_error and msg != last:
                    on_error(msg)
                last = msg
                if isinstance(exc, LinkClosed):   # closed by the daemon: stop trying
                    return
            stop.wait(retry_s)

    t = threading.Thread(target=run, name="oibar-link-connect", daemon=True)
    t.start()
    return t
