"""The navigation daemon: camera -> OibarNet -> filter -> guidance -> vehicle and MCU, at 10 Hz.

Threads: the camera reader (oibar.camera.LatestFrame: the cycle only ever sees the newest
frame) and the link client's I/O thread (oibar.link.LinkClient). Everything else runs in the
cycle. Mechanism requests are stop and wait and can take up to the link's retry budget (~1 s),
so the cycle never waits for one: it submits it (``link.submit_command``) and reads the handle's
verdict in a later cycle. Heartbeats go out from the cycle (``link.heartbeat()``, the client is
opened with ``heartbeats="caller"``), so a hung navigation loop falls silent and the MCU sees it.

The HIL rig drives this same ``cycle`` on simulated time (oibar_hil.rig.runner) with a
:class:`~oibar.link.session.SessionLink` over the same link core; the real program drives it
from :meth:`NavDaemon.run` with a :class:`~oibar.link.client.LinkClient`.

The link object is anything that fits :class:`oibar.link.protocols.NavLink`: ``link_alive``,
``telemetry``, ``next_event(timeout_s)``, ``send_nav_update(NavUpdate)``, ``heartbeat()``,
``submit_command(opcode, target_kpa)`` and ``submit_param_set(param_id, value)`` returning a
handle with ``done``, ``error``, ``response`` and ``response_kind`` (oibar.link.core.Request).

Failure behaviour (each has a test in tests/host/test_nav_daemon.py):
- model file missing or corrupt: ModelFileError at start, before the camera or the port is opened;
- camera lost (unplugged, stalled): the cycle gets no frame, guidance holds; the daemon
  reopens the camera every ``camera_retry_s``. A reader stuck inside the source's read is
  waited for, never doubled: no reopen until it has left (two readers on one device would
  interleave its frames). No frame for ``camera_dead_s`` (also: none since the start): the
  source is dead, ``run`` ends with ``stop_reason = "source_died"`` (exit 4) after the planned
  end of the MCU session (below);
- a frame that cannot be decoded (a corrupt JPEG in a folder): skipped by the source and
  counted (``corrupt_frames``), the next one is used;
- end of a finite stream (video file, frame folder): not a lost camera. Nothing is reopened
  (that would start the recording again from frame 0), the cycle holds with reason
  "camera: end of stream", and ``run`` ends with ``stop_reason = "source_ended"`` (exit 3)
  after the planned end of the MCU session;
- stop (Ctrl-C, SIGTERM, --duration-s, mission over, source ended or died): the vehicle holds,
  then the MCU session ends as planned (``end_session``: ``CMD_END_SESSION``, valves closed,
  mated states hold, moving ones abort, and the silence that follows is no link-loss fault);
  ``session_end`` says whether the MCU accepted it;
- link lost: no mechanism command is sent (the request fails with LinkDown, guidance retries when
  the MCU is back), navigation updates and heartbeats are skipped, the vehicle holds; the link
  client reconnects (also after an MCU reboot, which it notices by itself);
- navigation not trustworthy (filter not initialised, hold): the NavUpdate says ``valid = false``
  and carries no pose data (guidance.Guidance._nav);
- low confidence or a gated outlier: that cycle holds;
- the vehicle's odometry (VehicleInterface.relative_velocity) raising: camera only that cycle,
  counted in ``odometry_errors``; a gated or malformed one is simply not fused;
- the vehicle's attitude (VehicleInterface.relative_attitude) raising: that frame unchecked,
  counted in ``attitude_errors``; frames fused with its attitude are counted in ``attitude_replaced``;
- log disk full: logging stops with one warning, navigation goes on.
"""

from __future__ import annotations

import collections
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from oibar import pb
from oibar.camera import CameraError, CameraLost, CameraSource, EndOfStream, Frame, LatestFrame
from oibar.link.core import Request
from oibar.link.protocols import Connectable, Event, NavLink
from oibar.nav.core import Navigator, NavStep
from oibar.nav.cycle_stats import DaemonStats
from oibar.nav.flightlog import CycleInputs, FlightLog, camera_intrinsics, run_info
from oibar.nav.guidance import Guidance, GuidanceOutput, MechRequest, Observation, RequestResult
from oibar.nav.mcu_requests import SessionEnd, request_result
from oibar.nav.mcu_requests import end_session as end_mcu_session
from oibar.nav.vehicle import NullVehicle, VehicleInterface


@dataclass
class DaemonParams:
    rate_hz: float = 10.0  # SPEC section 5
    camera_lost_timeout_s: float = 1.0
    camera_retry_s: float = 2.0  # reopen a lost camera this often
    camera_join_s: float = 2.0  # how long stopping a lost camera waits for its reader
    status_every_s: float = 0.5  # live status line refresh
    camera_dead_s: float = 4.0  # no frame this long (or since the start): the source is dead, stop
    end_session_s: float = 3.0  # stop: how long the planned end of the MCU session may take
    stats_window: int = 36_000  # cycle timings kept for the percentiles (1 h at 10 Hz)


# Why run() ended (NavDaemon.stop_reason); the CLI maps each to its exit status (oibar.nav.cli).
STOP_FINISHED = "finished"  # guidance: mission completed, aborted or safed
STOP_DURATION = "duration"  # --duration-s / max_cycles reached
STOP_SIGNAL = "signal"  # Ctrl-C, SIGTERM (NavDaemon.stop)
STOP_SOURCE_ENDED = "source_ended"  # a finite source (video file, frame folder) delivered its last frame
STOP_SOURCE_DIED = "source_died"  # no frame for camera_dead_s (camera gone, never opened)


class NavDaemon:
    def __init__(
        self,
        navigator: Navigator,
        guidance: Guidance,
        camera: CameraSource | None,  # None: the caller feeds each frame to cycle() (the HIL rig)
        link: NavLink | None = None,
        vehicle: VehicleInterface | None = None,
        log: FlightLog | None = None,
        params: DaemonParams | None = None,
        status: Callable[[str], object] | None = None,
        clock: Callable[[], float] = time.monotonic,
        t0_s: float | None = None,
    ) -> None:
        self.nav = navigator
        self.guidance = guidance
        self.camera_source = camera
        self.link = link
        self.vehicle = vehicle or NullVehicle()
        self.log = log
        self.p = params or DaemonParams()
        self.status = status
        self.clock = clock
        self.stats = DaemonStats(
            cycle_ms=collections.deque(maxlen=self.p.stats_window),
            frame_to_command_ms=collections.deque(maxlen=self.p.stats_window),
        )
        self._stop = threading.Event()
        self.stop_reason: str | None = None  # why run() ended (STOP_*)
        self.stop_signal: str | None = None  # SIGINT / SIGTERM when a signal stopped it
        self.session_end: SessionEnd | None = None
        self._last_frame_at: float | None = None  # clock() of the newest frame (or run's start)
        self._cam: LatestFrame | None = None
        self._stuck_cam: LatestFrame | None = None  # a reader still blocked in read(): not reopened under it
        self.camera_ended = False  # a finite source delivered its last frame
        self._cam_error = ""
        self._next_cam_try = 0.0
        self._awaiting: MechRequest | None = None
        self._handle: Request | None = None  # the link's handle of the request in flight
        self._failed: list[RequestResult] = []  # requests the link refused to send
        self._t0 = clock() if t0_s is None else t0_s
        self._t0_fixed = t0_s is not None
        self.last_observation: Observation | None = None
        self._last_status = -1e9
        self._opened_once = False
        self._last_out: GuidanceOutput | None = None
        self._last_step: NavStep | None = None

    # -- camera -------------------------------------------------------------------------

    def _ensure_camera(self, now: float) -> LatestFrame | None:
        if self.camera_source is None:
            self._cam_error = "no camera: frames come through cycle()"
            return None
        if self._cam is None:
            if self.camera_ended or now < self._next_cam_try:
                return None
            self._next_cam_try = now + self.p.camera_retry_s
            if self._stuck_cam is not None:
                if self._stuck_cam.running:
                    self._cam_error = "reader still blocked in the source's read(); not reopened under it"
                    return None
                self._stuck_cam.stop()  # it has left read(): now the source can be closed
                self._stuck_cam = None
            try:
                self._cam = LatestFrame(
                    self.camera_source,
                    lost_timeout_s=self.p.camera_lost_timeout_s,
                    join_timeout_s=self.p.camera_join_s,
                ).start()
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
        cam, self._cam = self._cam, None
        if isinstance(exc, EndOfStream):
            self.camera_ended = True
            self._cam_error = f"end of stream ({exc})"
        if cam is not None and not cam.stop():
            self._stuck_cam = cam  # LatestFrame.stop left it running and the source open
        self._next_cam_try = now + self.p.camera_retry_s

    def wait_frame(self, until: float, min_capture_host: float = -1e18) -> Frame | None:
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
                if (
                    cam.seconds_since_last_capture <= self.p.camera_lost_timeout_s
                    and isinstance(exc, CameraLost)
                    and cam.running
                ):
                    return None  # just no frame before `until`: the camera is fine
                self._drop_camera(exc, self.clock())
                return None
            if frame is None:
                return None
            if frame.t_host >= min_capture_host:
                return frame
            # older than the decimation allows (camera faster than the cycle): take the next

    # -- one cycle ----------------------------------------------------------------------

    def cycle(
        self, frame: Frame | None = None, camera_error: str | None = None
    ) -> tuple[NavStep, GuidanceOutput]:
        """One cycle on ``frame`` (None: no new frame this time). ``camera_error``: why there is
        none, from a caller that runs the camera itself (the HIL rig); default: the daemon's own
        camera state."""
        if camera_error is None:
            camera_error = self._cam_error
        start = self.clock()
        t_s = start - self._t0
        odometry = self._ask_vehicle("relative_velocity", t_s)
        attitude = self._ask_vehicle("relative_attitude", t_s)
        if frame is not None:
            step = self.nav.step(
                t_s,
                frame.image,
                frame_t_s=frame.t_host - self._t0,
                frame_seq=frame.seq,
                odometry=odometry,
                attitude_ref=attitude,
            )
            self.stats.frames_used += 1
            self.stats.attitude_replaced += bool(step.attitude_check and step.attitude_check.replaced)
            self._last_frame_at = start
        else:
            step = self.nav.step(t_s, None, odometry=odometry)
            if camera_error:
                step.hold_reason = step.solution.hold_reason = f"camera: {camera_error}"
        link_up = bool(self.link is not None and self.link.link_alive)
        telemetry = self.link.telemetry if self.link is not None else None
        events: list[Event] = []
        if self.link is not None:
            while (ev := self.link.next_event(0)) is not None:
                events.append(ev)
        results = self._take_results()
        obs = Observation(t_s, step.solution, link_up, telemetry, events, results)
        out = self.guidance.step(t_s, obs)
        self.last_observation = obs
        self.vehicle.send(t_s, out.v_sp_D_mps, out.w_sp_rad_s, out.phase)
        sent = self.clock()
        if self.link is not None:
            try:
                # this cycle ran: say so (the MCU's link timeout sees a hung loop; a link client
                # with caller heartbeats re-handshakes only while we call), then the update
                self.link.heartbeat()
                if link_up:
                    self.link.send_nav_update(out.nav)
            except Exception:  # link dropped between the check and the send: next cycle
                pass
        if out.request is not None:
            self._submit(out.request)
        end = self.clock()
        st = self.stats
        st.corrupt_frames = int(getattr(self.camera_source, "corrupt_frames", 0) or 0)
        st.cycles += 1
        st.cycle_ms.append((end - start) * 1e3)
        if frame is not None:
            st.frame_to_command_ms.append((sent - frame.t_host) * 1e3)
        if step.hold_reason:
            st.holds += 1
        self._log_cycle(t_s, frame, step, out, obs, (end - start) * 1e3, odometry, camera_error, attitude)
        self._last_out, self._last_step = out, step
        return step, out

    def _submit(self, req: MechRequest) -> None:
        """Hand guidance's request to the link without waiting (stop and wait is the link's)."""
        if self.link is None:
            self._failed.append(RequestResult(req, False, "NoLink"))
            return
        try:
            if req.kind == "param_set":
                self._handle = self.link.submit_param_set(req.param_id, req.value)
            else:
                self._handle = self.link.submit_command(req.opcode, req.target_kpa or None)
            self._awaiting = req
        except Exception as exc:  # LinkDown, another request still out: guidance hears it
            self._failed.append(RequestResult(req, False, type(exc).__name__))

    def _take_results(self) -> list[RequestResult]:
        results, self._failed = self._failed, []
        if self._handle is not None and self._handle.done:
            assert self._awaiting is not None  # set together with the handle
            results.append(request_result(self._awaiting, self._handle))
            self._handle = self._awaiting = None
        return results

    def _ask_vehicle(self, what: str, t_s: float) -> Any:
        """The vehicle's own measurement ``what`` ("relative_velocity", "relative_attitude") at
        t_s, or None. A failing vehicle sensor must not stop navigation: raising counts in
        ``stats.odometry_errors`` / ``attitude_errors`` and gives None (camera only, the frame
        unchecked)."""
        try:
            return getattr(self.vehicle, what)(t_s)
        except Exception:
            counter = "odometry_errors" if what == "relative_velocity" else "attitude_errors"
            setattr(self.stats, counter, getattr(self.stats, counter) + 1)
            return None

    def _log_cycle(
        self,
        t_s: float,
        frame: Frame | None,
        step: NavStep,
        out: GuidanceOutput,
        obs: Observation,
        cycle_ms: float,
        odometry: Any = None,
        camera_error: str = "",
        attitude: Any = None,
    ) -> None:
        """The cycle into the flight log (oibar.nav.flightlog): it copies what it needs and
        writes in its own thread, and never raises."""
        if self.log is None:
            return
        tm = obs.telemetry
        self.log.cycle(
            CycleInputs(
                t_s=t_s,
                # numbered by the daemon: the camera's seq restarts at 0 when the camera is reopened
                cycle=self.stats.cycles,
                step=step,
                out=out,
                image=frame.image if frame is not None else None,
                frame_seq=frame.seq if frame is not None else None,
                frame_t_s=frame.t_host - self._t0 if frame is not None else None,
                odometry=odometry,
                vehicle_attitude=attitude if frame is not None else None,
                link_up=obs.link_up,
                telemetry=tm,
                events=list(obs.events),
                results=list(obs.results),
                mcu_state=pb.enum_name(pb.State, tm.state) if tm is not None else "",
                cycle_ms=cycle_ms,
                corrupt_frames=self.stats.corrupt_frames,
                camera_error=camera_error if frame is None else "",
            ),
            nav_filter=self.nav.filter,
        )

    # -- the loop -----------------------------------------------------------------------

    def start_log(self) -> None:
        """The flight log's run information: versions, model, onnxruntime threads, intrinsics
        (``run`` calls it; a caller that drives ``cycle`` itself calls it first)."""
        if self.log is None:
            return
        est = self.nav.estimator
        source = "cycle() caller" if self.camera_source is None else self.camera_source.name
        info = run_info(est, source, self.p.rate_hz, time.time() - (self.clock() - self._t0))
        self.log.start(info, camera_intrinsics(est)[1])

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
        bad = f"  corrupt {self.stats.corrupt_frames}" if self.stats.corrupt_frames else ""
        chk = step.attitude_check
        att = f"  ATT: vehicle's (camera {chk.disagreement_deg:.1f} deg off)" if chk and chk.replaced else ""
        return (
            f"t {self._last_t():7.1f} s  {out.phase:<18} range {rng}  lat {sol.lateral_m * 100:5.1f} cm  "
            f"conf {sol.confidence:4.2f}  MCU {st:<16} link {link}  cycle {cyc:5.1f} ms  "
            f"missed {self.stats.missed_deadlines}{bad}{att}{hold}{logw}"
        )

    def _last_t(self) -> float:
        return self.clock() - self._t0

    def stop(self, signal_name: str | None = None) -> None:
        """Ask ``run`` to end after the current cycle (a planned stop; thread and signal safe)."""
        if signal_name is not None and self.stop_signal is None:
            self.stop_signal = signal_name
        self._stop.set()

    def source_dead(self, now: float) -> bool:
        """True when the camera has delivered no frame for ``camera_dead_s`` (counted from the
        newest frame, or from the start of ``run``), and is not just a finite source that ended."""
        if self.camera_ended or self._last_frame_at is None:
            return False
        return now - self._last_frame_at >= self.p.camera_dead_s

    def end_session(self, timeout_s: float | None = None) -> SessionEnd:
        """The planned end of the MCU session (oibar.nav.mcu_requests.end_session): wait
        (boundedly) for a request still in flight, then send ``CMD_END_SESSION`` and wait for its
        answer. The MCU closes the valves, stops a transfer, holds mated states, aborts moving
        ones (docs/state_table.md) and, once it has accepted, does not count the silence that
        follows as a host link loss. Never raises."""
        if self.link is None:
            self.session_end = SessionEnd(False, False, None, "no MCU (--port none)")
        else:
            wait_s = self.p.end_session_s if timeout_s is None else timeout_s
            self.session_end = end_mcu_session(self.link, self._handle, wait_s)
        return self.session_end

    def run(self, duration_s: float | None = None, max_cycles: int | None = None) -> dict[str, Any]:
        """Frame-driven at ``rate_hz``: each cycle starts when a frame arrives that was captured
        at least 0.9 periods after the previous one used (a faster camera is decimated); with no
        frame by 1.5 periods after the previous cycle, the cycle runs without one (guidance
        holds, the link and the MCU keep being served). There is no grid of absolute deadlines:
        every wait counts from the previous cycle's start (or capture), so a late cycle moves
        the ones after it instead of making them hurry. A deadline is missed when a cycle's work
        takes longer than one period, or when cycles are more than 1.5 periods apart while
        frames are coming."""
        period = 1.0 / self.p.rate_hz
        t_start = self.clock()
        if not self._t0_fixed:
            self._t0 = t_start
        if self.log is not None:
            self.start_log()
        last_start = t_start - period
        last_capture = -1e18
        self._last_frame_at = t_start
        self.stop_reason = None
        k = 0
        try:
            while True:
                if self._stop.is_set():
                    self.stop_reason = STOP_SIGNAL
                elif self.guidance.finished:
                    self.stop_reason = STOP_FINISHED
                elif self.camera_ended:
                    self.stop_reason = STOP_SOURCE_ENDED
                elif self.source_dead(self.clock()):
                    self.stop_reason = STOP_SOURCE_DIED
                elif (duration_s is not None and self.clock() - t_start >= duration_s) or (
                    max_cycles is not None and k >= max_cycles
                ):
                    self.stop_reason = STOP_DURATION
                if self.stop_reason is not None:
                    break
                frame = self.wait_frame(
                    until=last_start + 1.5 * period, min_capture_host=last_capture + 0.9 * period
                )
                if self._stop.is_set():
                    self.stop_reason = STOP_SIGNAL
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
        """Vehicle hold, the planned end of the MCU session (``end_session``), vehicle closed,
        camera stopped, log footer written. The link is its opener's to close (oibar nav closes
        it after ``run``)."""
        try:
            self.vehicle.hold(self._last_t())
        except Exception:
            pass
        if self.session_end is None:
            self.end_session()
        try:
            self.vehicle.close()
        except Exception:
            pass
        if self._cam is not None:
            self._cam.stop()
            self._cam = None
        if self.log is not None:
            try:
                vehicle = self.vehicle.statistics()
            except Exception as exc:  # a user's vehicle class: its counters must not lose the footer
                vehicle = {"error": repr(exc)[:80]}
            self.log.close(
                {
                    "summary": self.stats.summary(),
                    "outcome": self.guidance.outcome,
                    "stop_reason": self.stop_reason,
                    "stop_signal": self.stop_signal,
                    "session_end": None
                    if self.session_end is None
                    else {
                        "accepted": self.session_end.accepted,
                        "state": self.session_end.state,
                        "detail": self.session_end.detail,
                    },
                    "notes": self.guidance.notes,
                    "vehicle": vehicle,
                },
                t_s=self._last_t(),
            )


def install_sigint(daemon: NavDaemon) -> None:
    """Ctrl-C / SIGTERM: a planned stop. Finish the current cycle, hold the vehicle, end the
    MCU session (CMD_END_SESSION), close everything. A second signal while stopping changes
    nothing (the stop is already under way; no KeyboardInterrupt traceback)."""

    def handler(signum: int, _frame: object) -> None:
        name = signal.Signals(signum).name
        if daemon._stop.is_set():
            return
        daemon.stop(name)
        print(
            f"\n{name}: stopping (vehicle hold, planned end of the MCU session, closing link and camera)",
            file=sys.stderr,
        )

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


def load_navigator(
    model_path: str | Path, threads: int = 2, calibration: str | Path | None = None
) -> Navigator:
    """The model's navigator; with ``calibration`` (OpenCV or ROS camera_info YAML) its frames are
    remapped to the model's canonical camera (PoseEstimator.use_calibration)."""
    from oibar.nav.pose import PoseEstimator

    estimator = PoseEstimator(model_path, threads=threads)
    if calibration is not None:
        estimator.use_calibration(calibration)
    return Navigator(estimator)


def connect_in_background(
    link: Connectable,
    retry_s: float = 2.0,
    on_error: Callable[[str], None] | None = None,
    stop: threading.Event | None = None,
) -> threading.Thread:
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
                if isinstance(exc, LinkClosed):  # closed by the daemon: stop trying
                    return
            stop.wait(retry_s)

    t = threading.Thread(target=run, name="oibar-link-connect", daemon=True)
    t.start()
    return t
