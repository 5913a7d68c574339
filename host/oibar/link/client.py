"""The companion computer's end of the link: a thin threaded pyserial driver around the core.

Every link rule (handshake verdict, stop and wait with retransmission of the same seq, sequence
tracking, heartbeats, link loss, MCU reboot detection, re-handshake) lives in
:class:`oibar.link.core.LinkCore`; the HIL rig runs the same core on simulated time
(:class:`oibar.link.session.LinkSession`). :class:`LinkClient` only adds what a real port needs:

- one I/O thread (``oibar-link-io``) that reads the port, feeds the core, steps its timers on
  the wall clock, writes what it queued, re-opens a port that failed (every
  ``reconnect_period_s``) and runs the callbacks, in order;
- blocking requests (:meth:`LinkClient.command`, :meth:`~LinkClient.param_set`, ...) for tools,
  and non-blocking ones (:meth:`LinkClient.submit_command`, :meth:`~LinkClient.submit_param_set`:
  a :class:`~oibar.link.core.Request` handle) for a loop that must not stall, like the
  navigation daemon;
- ``heartbeats="auto"`` (the core sends them every ``heartbeat_period_s``: tools, the console)
  or ``"caller"`` (only :meth:`LinkClient.heartbeat` sends them: the navigation daemon calls it
  once per cycle, so the MCU sees a hung navigation loop as a silent host).

The thread is a daemon, so a forgotten client cannot keep the process alive, but
:meth:`LinkClient.close` stops and joins it.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from typing import Any, cast

import serial

from oibar import __version__, pb
from oibar.link.core import LinkCore, Notice, Request
from oibar.link.errors import (
    LinkClosed,
    LinkDown,
    LinkError,
    PortError,
    ProtocolVersionError,
)
from oibar.link.results import (
    CommandResult,
    HandshakeInfo,
    LinkStatistics,
    ParamValue,
    command_result,
    info_from_reply,
    param_value,
    parse_opcode,
)

_log = logging.getLogger(__name__)


_READ_TIMEOUT_S = 0.01  # the I/O thread steps the core's timers at least this often
_WRITE_TIMEOUT_S = 1.0  # a port that cannot take a 247-byte frame in 1 s has failed
_JOIN_TIMEOUT_S = 2.0
_TELEMETRY_RATE_WINDOW_S = 2.0


# ---------------------------------------------------------------------------
# The driver


class LinkClient:
    """Host side of the OIBAR link over a serial port, ``socket://host:port`` or ``loop://``.

    Typical use::

        with LinkClient("/dev/ttyACM0") as link:
            info = link.connect()
            result = link.command("NOOP")

    Callbacks (``on_telemetry(Telemetry)``, ``on_event(Event)``, ``on_link_state(alive)``)
    run on the client's I/O thread, in order: keep them short, and do not issue blocking
    requests from them (that would wait for a response only that thread could deliver; it
    raises :class:`LinkError` instead). Exceptions they raise are logged and swallowed.
    """

    def __init__(
        self,
        url: str,
        baudrate: int = 115200,
        host_version: str = __version__,
        heartbeat_period_s: float = 0.2,
        link_timeout_s: float = 1.0,
        retransmit_timeout_s: float = 0.2,
        max_retries: int = 3,
        reconnect_period_s: float = 0.5,
        on_telemetry: Callable[[pb.Telemetry], None] | None = None,
        on_event: Callable[[pb.Event], None] | None = None,
        on_link_state: Callable[[bool], None] | None = None,
        *,
        protocol_version: int = pb.PROTOCOL_VERSION,
        event_queue_size: int = 256,
        heartbeats: str = "auto",
    ) -> None:
        if heartbeats not in ("auto", "caller"):
            raise ValueError("heartbeats is 'auto' or 'caller'")
        self.url = url
        self.baudrate = baudrate
        self.host_version = host_version
        self.protocol_version = protocol_version
        self.heartbeat_period_s = heartbeat_period_s
        self.link_timeout_s = link_timeout_s
        self.retransmit_timeout_s = retransmit_timeout_s
        self.max_retries = max_retries
        self.reconnect_period_s = reconnect_period_s
        self.heartbeats = heartbeats
        self._on_telemetry = on_telemetry
        self._on_event = on_event
        self._on_link_state = on_link_state
        self._clock_origin_s = time.monotonic()
        # The core, with every link rule. _cond's lock guards it and every field below.
        self._core = LinkCore(
            host_version=host_version,
            heartbeat_period_s=heartbeat_period_s,
            link_timeout_s=link_timeout_s,
            retransmit_timeout_s=retransmit_timeout_s,
            max_retries=max_retries,
            reconnect_period_s=reconnect_period_s,
            auto_connect=False,
            auto_heartbeat=heartbeats == "auto",
            protocol_version=protocol_version,
            event_queue_size=event_queue_size,
        )
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._port: serial.SerialBase | None = None
        self._thread: threading.Thread | None = None
        self._started = False
        self._closed = False
        self._notified_alive = False  # what on_link_state last said (I/O thread)
        self._last_retry_problem = ""  # I/O thread: log each new problem once
        self._next_open_s = 0.0
        self._telemetry_times_s: collections.deque[float] = collections.deque()

    def _now(self) -> float:
        return time.monotonic() - self._clock_origin_s

    # -- lifecycle ---------------------------------------------------------

    def connect(self) -> HandshakeInfo:
        """Open the port and handshake; start the I/O thread.

        Raises :class:`PortError` (cannot open), :class:`LinkTimeout` (no answer),
        :class:`ProtocolVersionError` or :class:`Nack` (handshake refused). On failure
        nothing keeps running, and ``connect()`` may be called again.
        """
        with self._cond:
            if self._closed:
                raise LinkClosed("the client is closed; create a new one")
            if self._started:
                raise LinkError("already connected")
            self._started = True
            self._stop.clear()
        try:
            port = self._open_port()
            with self._cond:
                self._port = port
                self._core.port_opened(self._now())
                req = self._core.connect(self._now())
                self._flush_locked()
            self._thread = threading.Thread(target=self._io_loop, name="oibar-link-io", daemon=True)
            self._thread.start()
            self._wait(req)
            if req.error is not None:
                raise req.error
            with self._cond:
                # from now on the core re-handshakes by itself after a loss
                self._core.auto_connect = True
                while not self._notified_alive and self._core.link_up and not self._stop.is_set():
                    self._cond.wait(0.05)
        except BaseException:
            self._shutdown()
            with self._cond:
                self._started = False
                self._core.auto_connect = False
                self._core.link_up = False
            raise
        return info_from_reply(req.response)

    def close(self) -> None:
        """Stop the thread, fail a waiting request with :class:`LinkClosed`, close the port.
        Idempotent; safe from any thread, including a callback."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
        self._shutdown()
        if self._notified_alive:
            self._notified_alive = False
            self._call_back(self._on_link_state, False)

    def __enter__(self) -> LinkClient:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # -- state -------------------------------------------------------------

    @property
    def link_alive(self) -> bool:
        """True between a successful handshake and the next link loss."""
        with self._cond:
            return self._core.link_up

    @property
    def handshake_info(self) -> HandshakeInfo | None:
        """The reply of the latest successful handshake."""
        with self._cond:
            reply = self._core.handshake_info
        return None if reply is None else info_from_reply(reply)

    @property
    def telemetry(self) -> pb.Telemetry | None:
        """The newest ``Telemetry`` message, or None before the first."""
        with self._cond:
            return self._core.telemetry

    @property
    def telemetry_rate_hz(self) -> float:
        """Telemetry packets per second over the last couple of seconds."""
        now = self._now()
        with self._cond:
            self._trim_telemetry_times(now)
            times = list(self._telemetry_times_s)
        if len(times) < 2:
            return 0.0
        return (len(times) - 1) / max(now - times[0], times[-1] - times[0], 1e-9)

    @property
    def statistics(self) -> LinkStatistics:
        """Snapshot of the decoder's and the core's counters."""
        with self._cond:
            d = self._core.decoder.counters
            c = self._core.counters
            return LinkStatistics(
                rx_packets=d.rx_packets,
                rx_crc_errors=d.rx_crc_errors,
                rx_framing_errors=d.rx_framing_errors,
                rx_oversize=d.rx_oversize,
                rx_bad_header=d.rx_bad_header,
                rx_decode_errors=d.rx_decode_errors,
                rx_unknown_type=d.rx_unknown_type,
                tx_packets=c.tx_packets,
                retransmissions=c.retransmissions,
                timeouts=c.timeouts,
                lost_peer_packets=c.lost_peer_packets,
                reconnects=c.reconnects,
                unmatched_responses=c.unmatched_responses,
                events_dropped=c.events_dropped,
                link_losses=c.link_losses,
                mcu_restarts=c.mcu_restarts,
            )

    def next_event(self, timeout_s: float | None = None) -> pb.Event | None:
        """Pop the oldest queued ``Event``; wait up to ``timeout_s`` (None: forever).
        Returns None on timeout or when the client is closed."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while not self._core.events:
                if self._closed:
                    return None
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._cond.wait(remaining)
            return self._core.events.popleft()

    # -- requests ----------------------------------------------------------

    def submit_command(self, opcode: int | str, target_pressure_kpa: float | None = None) -> Request:
        """Send a mechanism command without waiting: the handle's ``done`` turns True when the
        MCU answered, the retries ran out or the link dropped (``error`` says which).
        Raises :class:`LinkDown` at once while the link is down, :class:`LinkError` while
        another request is outstanding (stop and wait)."""
        code = parse_opcode(opcode)
        return self._submit(lambda now: self._core.command(code, target_pressure_kpa, now_s=now))

    def submit_param_set(self, param_id: int, value: float) -> Request:
        """Like :meth:`submit_command`, for a parameter write."""
        return self._submit(lambda now: self._core.param_set(param_id, value, now_s=now))

    def command(self, opcode: int | str, target_pressure_kpa: float | None = None) -> CommandResult:
        """Send a mechanism command and return the MCU's verdict.

        ``opcode`` is a CommandOpcode value or name ("NOOP" or "CMD_NOOP").
        Raises :class:`LinkDown` / :class:`LinkTimeout`, never for a refusal.
        """
        code = parse_opcode(opcode)
        req = self._request(lambda now: self._core.command(code, target_pressure_kpa, now_s=now))
        return command_result(req)

    def command_checked(self, opcode: int | str, target_pressure_kpa: float | None = None) -> CommandResult:
        """Like :meth:`command`, but a refusal raises :class:`Nack`."""
        code = parse_opcode(opcode)
        result = self.command(code, target_pressure_kpa)
        return result.raise_for_nack(pb.enum_name(pb.CommandOpcode, code))

    def param_get(self, param_id: int) -> ParamValue:
        """Read a parameter; a failure is reported in ``ParamValue.reason``."""
        req = self._request(lambda now: self._core.param_get(param_id, now_s=now))
        return param_value(req, param_id)

    def param_set(self, param_id: int, value: float) -> ParamValue:
        """Write a parameter; returns the value the MCU now holds (or why it refused)."""
        req = self._request(lambda now: self._core.param_set(param_id, value, now_s=now))
        return param_value(req, param_id)

    def send_nav_update(self, nav: pb.NavUpdate) -> bool:
        """Send a ready ``NavUpdate`` message, fire and forget (the newest one wins on the MCU).
        Returns False (and sends nothing) while the link is down."""
        with self._cond:
            if not self._core.nav_update(nav, now_s=self._now()):
                return False
            return self._flush_locked()

    def send_nav(
        self,
        *,
        frame_id: int = 0,
        stamp_ms: int | None = None,
        t_cam_target_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
        q_cam_target: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0),
        range_m: float = 0.0,
        closing_speed_mps: float = 0.0,
        phase: int | str = 0,
        confidence: float = 0.0,
        valid: bool = False,
    ) -> bool:
        """Build and send a NavUpdate (see :meth:`send_nav_update`).

        ``q_cam_target`` is (w, x, y, z); ``stamp_ms`` defaults to the host clock. ``valid``
        must be said: without it the MCU takes none of the fields as data.
        """
        nav = pb.NavUpdate()
        nav.frame_id = frame_id
        nav.stamp_ms = self._host_clock_ms() if stamp_ms is None else stamp_ms
        nav.t_cam_target_m.x, nav.t_cam_target_m.y, nav.t_cam_target_m.z = t_cam_target_m
        q = nav.q_cam_target
        q.w, q.x, q.y, q.z = q_cam_target
        nav.range_m = range_m
        nav.closing_speed_mps = closing_speed_mps
        nav.phase = cast("pb.NavPhase", pb.NavPhase.Value(phase) if isinstance(phase, str) else phase)
        nav.confidence = confidence
        nav.valid = bool(valid)
        return self.send_nav_update(nav)

    def heartbeat(self, *, force: bool = False) -> bool:
        """Send a Heartbeat if one is due (``heartbeats="caller"``: the caller's loop says it is
        alive). False while the link is down or when none was due."""
        with self._cond:
            if not self._core.heartbeat(self._now(), force=force):
                return False
            return self._flush_locked()

    # -- request machinery -------------------------------------------------

    def _submit(self, make: Callable[[float], Request]) -> Request:
        with self._cond:
            self._check_open_locked()
            req = make(self._now())
            self._flush_locked()
            return req

    def _request(self, make: Callable[[float], Request]) -> Request:
        """Wait for our turn (stop and wait), send, wait for the handle to complete."""
        if threading.current_thread() is self._thread:
            raise LinkError("requests cannot be issued from a link callback")
        with self._cond:
            while True:
                self._check_open_locked()
                if not self._core.busy:
                    break
                self._cond.wait()
            req = make(self._now())
            self._flush_locked()
        self._wait(req)
        if req.error is not None:
            raise req.error
        return req

    def _check_open_locked(self) -> None:
        if self._closed or self._stop.is_set():
            raise LinkClosed("the link client is closed")
        if not self._core.link_up:
            raise LinkDown("the link is down; waiting for the MCU to answer again")

    def _wait(self, req: Request) -> None:
        with self._cond:
            while not req.done:
                if self._thread is None or not self._thread.is_alive():
                    if not req.done:
                        self._core.fail_pending(self._now(), LinkClosed("the link client was closed"))
                    break
                self._cond.wait(0.1)

    # -- the port ------------------------------------------------------------

    def _flush_locked(self) -> bool:
        """Write the frames the core queued; a failing port is dropped (the I/O thread re-opens
        it). True when everything was written."""
        frames = self._core.take_output()
        port = self._port
        if not frames:
            return True
        if port is None:
            return False
        try:
            for frame in frames:
                port.write(frame)
        except Exception as exc:  # SerialException, OSError, or a port closed under us
            self._port_failed_locked(port, exc)
            return False
        return True

    def _port_failed_locked(self, port: Any, exc: BaseException) -> None:
        if self._port is not port:
            return
        self._port = None
        self._core.port_lost(self._now(), str(exc))
        self._next_open_s = self._now() + self.reconnect_period_s
        _log.warning("port %s failed: %s", self.url, exc)
        self._close_port_quietly(port)
        self._cond.notify_all()

    def _io_loop(self) -> None:
        """Read, feed the core, step its timers, write, re-open a failed port, call back."""
        while not self._stop.is_set():
            with self._cond:
                port = self._port
            if port is None:
                self._try_reopen()
                self._stop.wait(0.01)
            else:
                data = b""
                try:
                    data = port.read(1)  # blocks up to _READ_TIMEOUT_S
                    if data:
                        waiting = port.in_waiting
                        if waiting:
                            data += port.read(waiting)
                except Exception as exc:  # unplugged device, socket closed, port closed by close()
                    if self._stop.is_set():
                        return
                    with self._cond:
                        self._port_failed_locked(port, exc)
            with self._cond:
                now = self._now()
                if data:
                    self._core.receive(data, now)
                self._core.step(now)
                self._flush_locked()
                notices = self._core.take_notices()
                self._cond.notify_all()
            self._deliver(notices)

    def _try_reopen(self) -> None:
        now = self._now()
        with self._cond:
            if now < self._next_open_s or not self._core.auto_connect:
                return
            self._next_open_s = now + self.reconnect_period_s
        try:
            port = self._open_port()
        except PortError as exc:
            self._retry_problem(logging.INFO, f"waiting for the port to come back: {exc}")
            return
        with self._cond:
            if self._stop.is_set():
                self._close_port_quietly(port)
                return
            self._port = port
            self._core.port_opened(self._now())
        _log.info("re-opened %s", self.url)

    def _deliver(self, notices: list[Notice]) -> None:
        """Log and call back, in the order the core saw things (I/O thread, no lock held)."""
        for n in notices:
            if n.what == "telemetry":
                with self._cond:
                    self._telemetry_times_s.append(n.t_s)
                    self._trim_telemetry_times(n.t_s)
                self._call_back(self._on_telemetry, n.body)
            elif n.what == "event":
                self._call_back(self._on_event, n.body)
            elif n.what == "link_down":
                _log.warning("link lost on %s: %s", self.url, n.detail)
                self._set_notified(False)
            elif n.what == "link_up":
                self._last_retry_problem = ""
                info = self._core.handshake_info
                assert info is not None  # set before the core announces link_up, never cleared
                _log.info(
                    "link up on %s: firmware %s (build %s), protocol %d, reset cause %s",
                    self.url,
                    info.firmware_version,
                    info.build_id,
                    info.protocol_version,
                    pb.enum_name(pb.ResetCause, info.reset_cause),
                )
                self._set_notified(True)
            elif (
                n.what == "request_done"
                and n.request is not None
                and n.request.kind == "handshake"
                and n.request.error
            ):
                with self._cond:
                    retrying = self._core.auto_connect
                if retrying:
                    level = (
                        logging.ERROR if isinstance(n.request.error, ProtocolVersionError) else logging.INFO
                    )
                    self._retry_problem(level, f"handshake failed, retrying: {n.request.error}")

    def _set_notified(self, alive: bool) -> None:
        if alive != self._notified_alive:
            self._call_back(self._on_link_state, alive)
            with self._cond:
                self._notified_alive = alive
                self._cond.notify_all()

    def _retry_problem(self, level: int, message: str) -> None:
        """Log a re-establishment problem at ``level`` once, then at DEBUG while it
        repeats every reconnect period."""
        kind = message.split(":", 1)[0]
        _log.log(level if kind != self._last_retry_problem else logging.DEBUG, "%s", message)
        self._last_retry_problem = kind

    def _shutdown(self) -> None:
        """Stop and join the thread, fail the waiting request, close the port."""
        with self._cond:
            self._stop.set()
            port, self._port = self._port, None
            self._core.fail_pending(self._now(), LinkClosed("the link client was closed"))
            self._core.link_up = False
            self._core.auto_connect = False
            self._cond.notify_all()
        if port is not None:
            self._close_port_quietly(port)
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(_JOIN_TIMEOUT_S)
            if thread.is_alive():
                _log.warning("thread %s did not stop within %.1f s", thread.name, _JOIN_TIMEOUT_S)
        self._thread = None

    def _trim_telemetry_times(self, now: float) -> None:
        times = self._telemetry_times_s
        while times and now - times[0] > _TELEMETRY_RATE_WINDOW_S:
            times.popleft()

    # -- helpers -----------------------------------------------------------

    def _open_port(self) -> serial.SerialBase:
        try:
            return serial.serial_for_url(
                self.url,
                baudrate=self.baudrate,
                timeout=_READ_TIMEOUT_S,
                write_timeout=_WRITE_TIMEOUT_S,
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise PortError(f"cannot open {self.url}: {exc}") from exc

    @staticmethod
    def _close_port_quietly(port: serial.SerialBase) -> None:
        try:
            cancel = getattr(port, "cancel_read", None)
            if cancel is not None:
                cancel()
        except Exception:  # best effort: close() below is what matters
            pass
        try:
            port.close()
        except Exception as exc:
            _log.debug("closing the port: %s", exc)

    @staticmethod
    def _call_back(callback: Callable[[Any], None] | None, arg: Any) -> None:
        if callback is None:
            return
        try:
            callback(arg)
        except Exception:
            _log.exception("link callback %r failed", callback)

    def _host_clock_ms(self) -> int:
        return int(self._now() * 1000) & 0xFFFFFFFF
