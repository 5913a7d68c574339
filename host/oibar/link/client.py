"""The companion computer's end of the link: handshake, requests, heartbeats, link loss.

:class:`LinkClient` implements the host rules of docs/link.md:

- one request outstanding at a time (stop and wait), matched to its response by
  ``ack_seq``, retransmitted with the *same* seq after ``retransmit_timeout_s`` at most
  ``max_retries`` times, so the MCU can answer a duplicate from its cache instead of
  moving hardware twice;
- a ``Heartbeat`` every ``heartbeat_period_s`` while the link is up;
- link loss when no valid packet arrived for ``link_timeout_s``: the user is told, requests
  fail fast with :class:`LinkDown`, and a supervisor re-opens the port if it failed and
  handshakes again (a new seq numbering session) until the link is back.

Threads: a reader (feeds the decoder, dispatches packets, runs the callbacks), a heartbeat
sender and a supervisor. All are daemons, so a forgotten client cannot keep the process
alive, but :meth:`LinkClient.close` stops and joins them.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import serial

from oibar import __version__, pb
from oibar.link.errors import (
    LinkClosed,
    LinkDown,
    LinkError,
    LinkTimeout,
    Nack,
    PortError,
    ProtocolVersionError,
)
from oibar.link.framing import FrameDecoder, Packet, check_link_settings, encode_frame
from oibar.link.seq import follow_peer_seq, next_seq

_log = logging.getLogger(__name__)


_RESPONSE_BODIES = frozenset({"handshake_reply", "ack", "param_value"})
_READ_TIMEOUT_S = 0.05  # bounds how long the reader takes to notice close()
_WRITE_TIMEOUT_S = 1.0  # a port that cannot take a 247-byte frame in 1 s has failed
_JOIN_TIMEOUT_S = 2.0
_TELEMETRY_RATE_WINDOW_S = 2.0


# ---------------------------------------------------------------------------
# Results


@dataclass(frozen=True)
class HandshakeInfo:
    """What the MCU told us when the link was opened."""

    firmware_version: str
    build_id: str
    protocol_version: int
    reset_cause: str  # ResetCause name, e.g. "RESET_POWER_ON"
    uptime_ms: int


@dataclass(frozen=True)
class CommandResult:
    """The MCU's answer to a command. A refusal is a normal result, not an exception."""

    accepted: bool
    reason: str  # NackReason name; "NACK_NONE" when accepted
    state: str  # State name after the command was handled

    def raise_for_nack(self, what: str = "command") -> "CommandResult":
        """Return self if accepted, else raise :class:`Nack`."""
        if not self.accepted:
            raise Nack(self.reason, what, self.state)
        return self


@dataclass(frozen=True)
class ParamValue:
    """A parameter as reported by the MCU; ``reason`` says why a get/set failed."""

    param_id: int
    value: float
    min: float
    max: float
    default_value: float
    name: str
    unit: str
    reason: str  # NackReason name; "NACK_NONE" on success

    @property
    def ok(self) -> bool:
        return self.reason == "NACK_NONE"

    def raise_for_nack(self, what: str = "parameter request") -> "ParamValue":
        """Return self if the get/set succeeded, else raise :class:`Nack`."""
        if not self.ok:
            raise Nack(self.reason, what)
        return self


@dataclass(frozen=True)
class LinkStatistics:
    """Decoder counters (same names as the schema's LinkCounters) and the client's own."""

    rx_packets: int
    rx_crc_errors: int
    rx_framing_errors: int
    rx_oversize: int
    rx_bad_header: int
    rx_decode_errors: int
    rx_unknown_type: int
    tx_packets: int
    retransmissions: int
    timeouts: int
    lost_peer_packets: int
    reconnects: int
    unmatched_responses: int
    events_dropped: int


def parse_opcode(opcode: int | str) -> int:
    """Accept a CommandOpcode value or a name with or without ``CMD_`` (any case)."""
    if isinstance(opcode, int):
        return opcode
    name = opcode.strip().upper()
    if not name.startswith("CMD_"):
        name = "CMD_" + name
    try:
        return pb.CommandOpcode.Value(name)
    except ValueError:
        known = ", ".join(n[4:] for n in pb.CommandOpcode.keys() if n != "CMD_UNSPECIFIED")
        raise ValueError(f"unknown command {opcode!r}; known commands: {known}") from None


# ---------------------------------------------------------------------------
# Internals


class _Pending:
    """The one outstanding request; the reader completes it, close/link loss fail it."""

    __slots__ = ("seq", "done", "response", "error")

    def __init__(self) -> None:
        self.seq = 0
        self.done = threading.Event()
        self.response: Packet | None = None
        self.error: LinkError | None = None


class _Counters:
    """The client's own counters, guarded by the client's condition lock."""

    def __init__(self) -> None:
        self.tx_packets = 0
        self.retransmissions = 0
        self.timeouts = 0
        self.lost_peer_packets = 0
        self.reconnects = 0
        self.unmatched_responses = 0
        self.events_dropped = 0


class LinkClient:
    """Host side of the OIBAR link over a serial port, ``socket://host:port`` or ``loop://``.

    Typical use::

        with LinkClient("/dev/ttyACM0") as link:
            info = link.connect()
            result = link.command("NOOP")

    Callbacks (``on_telemetry(Telemetry)``, ``on_event(Event)``, ``on_link_state(alive)``)
    run on the client's threads: keep them short, and do not issue requests from them
    (that would wait for a response only the calling thread could deliver; it raises
    :class:`LinkError` instead). Exceptions they raise are logged and swallowed.
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
        on_telemetry: Callable[[Any], None] | None = None,
        on_event: Callable[[Any], None] | None = None,
        on_link_state: Callable[[bool], None] | None = None,
        *,
        protocol_version: int = pb.PROTOCOL_VERSION,
        event_queue_size: int = 256,
    ) -> None:
        check_link_settings(host_version, max_retries, heartbeat_period_s, link_timeout_s,
                            retransmit_timeout_s, reconnect_period_s)
        self.url = url
        self.baudrate = baudrate
        self.host_version = host_version
        self.protocol_version = protocol_version
        self.heartbeat_period_s = heartbeat_period_s
        self.link_timeout_s = link_timeout_s
        self.retransmit_timeout_s = retransmit_timeout_s
        self.max_retries = max_retries
        self.reconnect_period_s = reconnect_period_s
        self._on_telemetry = on_telemetry
        self._on_event = on_event
        self._on_link_state = on_link_state

        # _cond guards every field below that more than one thread touches.
        self._cond = threading.Condition()
        self._request_busy = False  # stop and wait: one request at a time (under _cond)
        self._write_lock = threading.Lock()  # frames never interleave; seq order == wire order
        self._stop = threading.Event()
        self._wake_supervisor = threading.Event()

        self._decoder = FrameDecoder()
        self._counters = _Counters()
        self._port: serial.SerialBase | None = None
        self._threads: list[threading.Thread] = []
        self._reader_thread: threading.Thread | None = None
        self._started = False
        self._closed = False
        self._link_up = False
        self._notified_alive = False  # what on_link_state last said (supervisor-owned)
        self._last_retry_problem = ""  # supervisor-owned: log each new problem once
        self._last_rx_s = 0.0
        self._tx_seq = 0
        self._peer_seq: int | None = None
        self._pending: _Pending | None = None
        self._handshake_info: HandshakeInfo | None = None
        self._telemetry: Any = None
        self._telemetry_times_s: collections.deque[float] = collections.deque()
        self._events: collections.deque[Any] = collections.deque(maxlen=event_queue_size)
        self._clock_origin_s = time.monotonic()

    # -- lifecycle ---------------------------------------------------------

    def connect(self) -> HandshakeInfo:
        """Open the port and handshake; start the heartbeat and supervisor threads.

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
            self._start_thread("reader", self._reader_loop, reader=True)
            info = self._handshake()
        except BaseException:
            self._shutdown()
            with self._cond:
                self._started = False
            raise
        self._start_thread("heartbeat", self._heartbeat_loop)
        self._notified_alive = True
        self._notify_link_state(True)
        self._start_thread("supervisor", self._supervisor_loop)
        return info

    def close(self) -> None:
        """Stop every thread, fail a waiting request with :class:`LinkClosed`, close the
        port. Idempotent; safe from any thread, including a callback."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
        self._shutdown()  # joins the supervisor, so _notified_alive is ours now
        if self._notified_alive:
            self._notified_alive = False
            self._notify_link_state(False)

    def __enter__(self) -> "LinkClient":
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # -- state -------------------------------------------------------------

    @property
    def link_alive(self) -> bool:
        """True between a successful handshake and the next link loss."""
        with self._cond:
            return self._link_up

    @property
    def handshake_info(self) -> HandshakeInfo | None:
        """The reply of the latest successful handshake."""
        with self._cond:
            return self._handshake_info

    @property
    def telemetry(self) -> Any:
        """The newest ``Telemetry`` message, or None before the first."""
        with self._cond:
            return self._telemetry

    @property
    def telemetry_rate_hz(self) -> float:
        """Telemetry packets per second over the last couple of seconds."""
        now = time.monotonic()
        with self._cond:
            self._trim_telemetry_times(now)
            times = list(self._telemetry_times_s)
        if len(times) < 2:
            return 0.0
        return (len(times) - 1) / max(now - times[0], times[-1] - times[0], 1e-9)

    @property
    def statistics(self) -> LinkStatistics:
        """Snapshot of the decoder's and the client's counters."""
        decoder = self._decoder.counters
        with self._cond:
            c = self._counters
            return LinkStatistics(
                rx_packets=decoder.rx_packets,
                rx_crc_errors=decoder.rx_crc_errors,
                rx_framing_errors=decoder.rx_framing_errors,
                rx_oversize=decoder.rx_oversize,
                rx_bad_header=decoder.rx_bad_header,
                rx_decode_errors=decoder.rx_decode_errors,
                rx_unknown_type=decoder.rx_unknown_type,
                tx_packets=c.tx_packets,
                retransmissions=c.retransmissions,
                timeouts=c.timeouts,
                lost_peer_packets=c.lost_peer_packets,
                reconnects=c.reconnects,
                unmatched_responses=c.unmatched_responses,
                events_dropped=c.events_dropped,
            )

    def next_event(self, timeout_s: float | None = None) -> Any:
        """Pop the oldest queued ``Event``; wait up to ``timeout_s`` (None: forever).
        Returns None on timeout or when the client is closed."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while not self._events:
                if self._closed:
                    return None
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._cond.wait(remaining)
            return self._events.popleft()

    # -- requests ----------------------------------------------------------

    def command(self, opcode: int | str, target_pressure_kpa: float | None = None) -> CommandResult:
        """Send a mechanism command and return the MCU's verdict.

        ``opcode`` is a CommandOpcode value or name ("NOOP" or "CMD_NOOP").
        Raises :class:`LinkDown` / :class:`LinkTimeout`, never for a refusal.
        """
        code = parse_opcode(opcode)
        packet = Packet()
        packet.command.opcode = code
        if target_pressure_kpa is not None:
            packet.command.target_pressure_kpa = target_pressure_kpa
        response = self._request(packet)
        kind = response.WhichOneof("body")
        if kind != "ack":
            raise LinkError(f"unexpected {kind} in answer to a command")
        ack = response.ack
        return CommandResult(
            accepted=ack.accepted,
            reason=pb.enum_name(pb.NackReason, ack.reason),
            state=pb.enum_name(pb.State, ack.state),
        )

    def command_checked(
        self, opcode: int | str, target_pressure_kpa: float | None = None
    ) -> CommandResult:
        """Like :meth:`command`, but a refusal raises :class:`Nack`."""
        code = parse_opcode(opcode)
        result = self.command(code, target_pressure_kpa)
        return result.raise_for_nack(pb.enum_name(pb.CommandOpcode, code))

    def param_get(self, param_id: int) -> ParamValue:
        """Read a parameter; a failure is reported in ``ParamValue.reason``."""
        packet = Packet()
        packet.param_get.param_id = param_id
        return self._param_value(self._request(packet), param_id)

    def param_set(self, param_id: int, value: float) -> ParamValue:
        """Write a parameter; returns the value the MCU now holds (or why it refused)."""
        packet = Packet()
        packet.param_set.param_id = param_id
        packet.param_set.value = value
        return self._param_value(self._request(packet), param_id)

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
        """Send a NavUpdate, fire and forget (the newest one wins on the MCU).

        ``q_cam_target`` is (w, x, y, z); ``stamp_ms`` defaults to the host clock. ``valid``
        says the navigation solution is initialised and trusted; the MCU ignores the data
        of an update not marked valid (protocol 2).
        Returns False (and sends nothing) while the link is down, so a 10 Hz navigation
        loop keeps running through a link loss.
        """
        packet = Packet()
        nav = packet.nav_update
        nav.frame_id = frame_id
        nav.stamp_ms = self._host_clock_ms() if stamp_ms is None else stamp_ms
        nav.t_cam_target_m.x, nav.t_cam_target_m.y, nav.t_cam_target_m.z = t_cam_target_m
        q = nav.q_cam_target
        q.w, q.x, q.y, q.z = q_cam_target
        nav.range_m = range_m
        nav.closing_speed_mps = closing_speed_mps
        nav.phase = pb.NavPhase.Value(phase) if isinstance(phase, str) else phase
        nav.confidence = confidence
        nav.valid = bool(valid)
        if not self.link_alive:
            return False
        try:
            self._send(packet)
        except LinkError as exc:
            _log.debug("nav update not sent: %s", exc)
            return False
        return True

    # -- request machinery -------------------------------------------------

    def _request(self, packet: Packet, *, handshake: bool = False) -> Packet:
        """Send ``packet`` as the one outstanding request; return its response packet."""
        if threading.current_thread() is self._reader_thread:
            raise LinkError("requests cannot be issued from a link callback")
        pending = _Pending()
        with self._cond:
            # Wait for our turn, but give up at once if the link goes down meanwhile:
            # the turn may belong to a re-handshake that can take a while.
            while True:
                if self._closed or self._stop.is_set():
                    raise LinkClosed("the link client is closed")
                if not handshake and not self._link_up:
                    raise LinkDown("the link is down; waiting for the MCU to answer again")
                if not self._request_busy:
                    break
                self._cond.wait()
            self._request_busy = True
            self._pending = pending
        try:
            return self._exchange(packet, pending)
        finally:
            with self._cond:
                self._request_busy = False
                if self._pending is pending:
                    self._pending = None
                self._cond.notify_all()

    def _exchange(self, packet: Packet, pending: _Pending) -> Packet:
        frame = self._send(packet, pending=pending, new_session=packet.HasField("handshake"))
        for attempt in range(self.max_retries + 1):
            if attempt:
                self._write_frame(frame)  # same bytes, same seq: the MCU answers from cache
                with self._cond:
                    self._counters.retransmissions += 1
                _log.debug("retransmission %d of seq %d", attempt, pending.seq)
            if pending.done.wait(self.retransmit_timeout_s):
                break
        else:
            with self._cond:
                self._counters.timeouts += 1
            kind = packet.WhichOneof("body")
            raise LinkTimeout(
                f"{kind} (seq {pending.seq}) got no response after {self.max_retries + 1} "
                f"attempts {self.retransmit_timeout_s:g} s apart"
            )
        if pending.error is not None:
            raise pending.error
        assert pending.response is not None
        response = pending.response
        if (
            not packet.HasField("handshake")
            and response.HasField("ack")
            and response.ack.reason == pb.NACK_NOT_CONNECTED
        ):
            # The MCU dropped our session (reset, or it saw a link loss we did not):
            # report this request as refused and let the supervisor handshake again.
            self._link_lost("the MCU answered NACK_NOT_CONNECTED")
        return response

    def _param_value(self, response: Packet, param_id: int) -> ParamValue:
        kind = response.WhichOneof("body")
        if kind == "ack":  # e.g. NACK_NOT_CONNECTED or NACK_UNKNOWN_MESSAGE
            return ParamValue(
                param_id, 0.0, 0.0, 0.0, 0.0, "", "", pb.enum_name(pb.NackReason, response.ack.reason)
            )
        if kind != "param_value":
            raise LinkError(f"unexpected {kind} in answer to a parameter request")
        v = response.param_value
        return ParamValue(
            param_id=v.param_id,
            value=v.value,
            min=v.min,
            max=v.max,
            default_value=v.default_value,
            name=v.name,
            unit=v.unit,
            reason=pb.enum_name(pb.NackReason, v.reason),
        )

    def _handshake(self) -> HandshakeInfo:
        """Open a new session: seq numbering restarts at 1 with the Handshake itself."""
        packet = Packet()
        packet.handshake.protocol_version = self.protocol_version
        packet.handshake.host_version = self.host_version
        response = self._request(packet, handshake=True)
        kind = response.WhichOneof("body")
        if kind == "ack":  # an MCU that does not know Handshake at all
            raise Nack(pb.enum_name(pb.NackReason, response.ack.reason), "handshake")
        if kind != "handshake_reply":
            raise LinkError(f"unexpected {kind} in answer to the handshake")
        reply = response.handshake_reply
        if reply.reason == pb.NACK_VERSION_MISMATCH or (
            reply.accepted and reply.protocol_version != self.protocol_version
        ):
            raise ProtocolVersionError(self.protocol_version, reply.protocol_version)
        if not reply.accepted:
            raise Nack(pb.enum_name(pb.NackReason, reply.reason), "handshake")
        info = HandshakeInfo(
            firmware_version=reply.firmware_version,
            build_id=reply.build_id,
            protocol_version=reply.protocol_version,
            reset_cause=pb.enum_name(pb.ResetCause, reply.reset_cause),
            uptime_ms=reply.uptime_ms,
        )
        with self._cond:
            self._handshake_info = info
            self._link_up = True
            self._last_rx_s = time.monotonic()
        _log.info(
            "link up on %s: firmware %s (build %s), protocol %d, reset cause %s",
            self.url, info.firmware_version, info.build_id, info.protocol_version, info.reset_cause,
        )
        return info

    # -- sending -----------------------------------------------------------

    def _send(
        self, packet: Packet, *, pending: _Pending | None = None, new_session: bool = False
    ) -> bytes:
        """Number ``packet``, frame it and write it; return the frame for retransmission.

        Numbering happens under the write lock so that seq order is wire order.
        """
        with self._write_lock:
            with self._cond:
                if new_session:
                    self._tx_seq = 0
                    self._peer_seq = None
                self._tx_seq = next_seq(self._tx_seq)
                packet.seq = self._tx_seq
                if pending is not None:
                    pending.seq = packet.seq
            frame = encode_frame(packet)
            failure = self._write_frame_locked(frame)
        if failure is not None:
            self._raise_write_failure(*failure)
        return frame

    def _write_frame(self, frame: bytes) -> None:
        with self._write_lock:
            failure = self._write_frame_locked(frame)
        if failure is not None:
            self._raise_write_failure(*failure)

    def _write_frame_locked(self, frame: bytes) -> tuple[Any, Exception] | None:
        """Write one frame; return (port, exception) on failure, to be handled after the
        write lock is released (closing a port can take a while)."""
        with self._cond:
            port = self._port
        if port is None:
            return None, LinkDown("the serial port is not open")
        try:
            port.write(frame)
        except Exception as exc:  # SerialException, OSError, or a port closed under us
            return port, exc
        with self._cond:
            self._counters.tx_packets += 1
        return None

    def _raise_write_failure(self, port: Any, exc: Exception) -> None:
        if port is None:
            raise exc
        self._port_failed(port, exc)
        raise LinkDown(f"writing to {self.url} failed: {exc}") from exc

    # -- threads -----------------------------------------------------------

    def _start_thread(self, role: str, target: Callable[[], None], reader: bool = False) -> None:
        thread = threading.Thread(target=target, name=f"oibar-link-{role}", daemon=True)
        if reader:
            self._reader_thread = thread
        self._threads.append(thread)
        thread.start()

    def _shutdown(self) -> None:
        """Stop and join the threads, fail the waiting request, close the port."""
        with self._cond:
            self._stop.set()
            self._link_up = False
            port, self._port = self._port, None
            if self._pending is not None:
                self._fail_pending_locked(LinkClosed("the link client was closed"))
            self._cond.notify_all()
        self._wake_supervisor.set()
        if port is not None:
            self._close_port_quietly(port)
        current = threading.current_thread()
        for thread in self._threads:
            if thread is not current:
                thread.join(_JOIN_TIMEOUT_S)
                if thread.is_alive():
                    _log.warning("thread %s did not stop within %.1f s", thread.name, _JOIN_TIMEOUT_S)
        self._threads = []
        self._reader_thread = None
        self._wake_supervisor.clear()

    def _reader_loop(self) -> None:
        """Feed the decoder with whatever the port delivers and dispatch the packets."""
        previous_port = None
        while True:
            with self._cond:
                while self._port is None and not self._stop.is_set():
                    self._cond.wait()
                if self._stop.is_set():
                    return
                port = self._port
            if port is not previous_port:
                self._decoder.reset()  # a frame cut by the old port's failure is not news
                previous_port = port
            try:
                data = port.read(1)  # blocks up to _READ_TIMEOUT_S
                if data:
                    waiting = port.in_waiting
                    if waiting:
                        data += port.read(waiting)
            except Exception as exc:  # unplugged device, socket closed, port closed by close()
                if self._stop.is_set():
                    return
                self._port_failed(port, exc)
                continue
            if data:
                for packet in self._decoder.feed(data):
                    self._dispatch(packet)

    def _heartbeat_loop(self) -> None:
        """Send a Heartbeat every period while the link is up."""
        while not self._stop.wait(self.heartbeat_period_s):
            if not self.link_alive:
                continue
            packet = Packet()
            packet.heartbeat.uptime_ms = self._host_clock_ms()
            try:
                self._send(packet)
            except LinkError as exc:
                _log.debug("heartbeat not sent: %s", exc)

    def _supervisor_loop(self) -> None:
        """Declare the link lost after link_timeout_s of silence; re-establish it.

        This thread also delivers every on_link_state change after connect(), so the
        callback never runs with a client lock held and a loss is always reported before
        the link comes back.
        """
        check_period_s = min(0.05, self.link_timeout_s / 4)
        next_attempt_s = 0.0
        while not self._stop.is_set():
            self._wake_supervisor.wait(check_period_s)
            self._wake_supervisor.clear()
            if self._stop.is_set():
                return
            now = time.monotonic()
            with self._cond:
                up, silent_s, port = self._link_up, now - self._last_rx_s, self._port
            if up and silent_s > self.link_timeout_s:
                self._link_lost(f"no valid packet for {silent_s:.2f} s")
                up = False
                next_attempt_s = now  # the port is still open: try a handshake at once
            self._sync_link_state()
            if up or now < next_attempt_s:
                continue
            try:
                if self._reestablish(port):
                    self._sync_link_state()
            finally:
                next_attempt_s = time.monotonic() + self.reconnect_period_s

    def _sync_link_state(self) -> None:
        with self._cond:
            alive = self._link_up
        if alive != self._notified_alive:
            self._notified_alive = alive
            self._notify_link_state(alive)

    def _reestablish(self, port: serial.SerialBase | None) -> bool:
        """One attempt: re-open the port if it failed, then handshake. True on success."""
        if port is None:
            try:
                port = self._open_port()
            except PortError as exc:
                self._retry_problem(logging.INFO, f"waiting for the port to come back: {exc}")
                return False
            with self._cond:
                if self._stop.is_set():
                    stale = True
                else:
                    stale = False
                    self._port = port
                    self._cond.notify_all()
            if stale:
                self._close_port_quietly(port)
                return False
            _log.info("re-opened %s", self.url)
        try:
            self._handshake()
        except ProtocolVersionError as exc:
            self._retry_problem(logging.ERROR, f"cannot re-establish the link: {exc}")
            return False
        except LinkError as exc:
            self._retry_problem(logging.INFO, f"handshake failed, retrying: {exc}")
            return False
        self._last_retry_problem = ""
        with self._cond:
            self._counters.reconnects += 1
        return True

    def _retry_problem(self, level: int, message: str) -> None:
        """Log a re-establishment problem at ``level`` once, then at DEBUG while it
        repeats every reconnect period."""
        kind = message.split(":", 1)[0]
        _log.log(level if kind != self._last_retry_problem else logging.DEBUG, "%s", message)
        self._last_retry_problem = kind

    # -- receiving ---------------------------------------------------------

    def _dispatch(self, packet: Packet) -> None:
        """Route one valid packet (reader thread)."""
        now = time.monotonic()
        kind = packet.WhichOneof("body")
        with self._cond:
            self._last_rx_s = now
            self._track_peer_seq_locked(packet.seq)
            if kind in _RESPONSE_BODIES:
                pending = self._pending
                if (
                    pending is not None
                    and packet.ack_seq != 0
                    and packet.ack_seq == pending.seq
                    and not pending.done.is_set()
                ):
                    pending.response = packet
                    pending.done.set()
                else:
                    # a late answer to a request that already timed out, or the cached
                    # answer to a retransmission after the first answer got through
                    self._counters.unmatched_responses += 1
                    _log.debug("unmatched %s ack_seq=%d", kind, packet.ack_seq)
                return
            if kind == "telemetry":
                self._telemetry = packet.telemetry
                self._telemetry_times_s.append(now)
                self._trim_telemetry_times(now)
            elif kind == "event":
                if len(self._events) == self._events.maxlen:
                    self._counters.events_dropped += 1
                self._events.append(packet.event)
                self._cond.notify_all()
        if kind == "telemetry":
            self._call_back(self._on_telemetry, packet.telemetry)
        elif kind == "event":
            self._call_back(self._on_event, packet.event)
        elif kind != "heartbeat":
            _log.debug("ignoring %s from the peer", kind)  # host-bound bodies, e.g. on loop://

    def _track_peer_seq_locked(self, seq: int) -> None:
        """Count gaps in the peer's numbering as lost packets (oibar.link.seq)."""
        self._peer_seq, lost = follow_peer_seq(self._peer_seq, seq)
        self._counters.lost_peer_packets += lost

    def _trim_telemetry_times(self, now: float) -> None:
        times = self._telemetry_times_s
        while times and now - times[0] > _TELEMETRY_RATE_WINDOW_S:
            times.popleft()

    # -- failures ----------------------------------------------------------

    def _link_lost(self, why: str) -> None:
        """Up -> down: fail the waiting request; the supervisor tells the user and
        re-establishes the link."""
        with self._cond:
            if not self._link_up:
                return
            self._link_up = False
            if self._pending is not None:
                self._fail_pending_locked(LinkDown(f"link lost: {why}"))
            self._cond.notify_all()  # queued requests fail fast
        _log.warning("link lost on %s: %s", self.url, why)
        self._wake_supervisor.set()

    def _port_failed(self, port: serial.SerialBase, exc: BaseException) -> None:
        """The port raised (unplugged, socket gone): drop it; the supervisor re-opens it."""
        with self._cond:
            if self._port is not port:
                return  # already handled, or an old port
            self._port = None
            self._link_up = False
            if self._pending is not None:
                self._fail_pending_locked(LinkDown(f"port failed: {exc}"))
            self._cond.notify_all()
        _log.warning("port %s failed: %s", self.url, exc)
        self._close_port_quietly(port)  # before the supervisor tries to re-open it
        self._wake_supervisor.set()

    def _fail_pending_locked(self, error: LinkError) -> None:
        pending = self._pending
        if pending is not None and not pending.done.is_set():
            pending.error = error
            pending.done.set()

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

    def _notify_link_state(self, alive: bool) -> None:
        self._call_back(self._on_link_state, alive)

    @staticmethod
    def _call_back(callback: Callable[[Any], None] | None, arg: Any) -> None:
        if callback is None:
            return
        try:
            callback(arg)
        except Exception:
            _log.exception("link callback %r failed", callback)

    def _host_clock_ms(self) -> int:
        return int((time.monotonic() - self._clock_origin_s) * 1000) & 0xFFFFFFFF
