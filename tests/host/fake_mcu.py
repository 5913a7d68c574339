"""A small scriptable MCU-side link peer, for testing the host client without hardware.

It implements the MCU rules of docs/link.md on top of the host's own framing module:
handshake with version check, requests refused with NACK_NOT_CONNECTED before it,
duplicate suppression (the last request's seq and body, and its cached response), the
replay window (seq 0 or at or behind the newest request: NACK_STALE_SEQ; the last seq
with another body: NACK_SEQ_REUSED; a handshake starts a new window), NACK_UNKNOWN_MESSAGE
for packets without a known body, heartbeats, periodic telemetry and a link-loss timeout.

The "serial line" is a TCP socket on 127.0.0.1 (ephemeral port), which the client opens
as ``socket://127.0.0.1:PORT``. One thread runs an event loop (select with timers), so
all socket work happens on it; the test thread turns the fault knobs:

- :meth:`drop_responses` -- the next N responses are not sent (the request still runs);
- :meth:`go_silent` / :meth:`resume` -- send nothing at all (a cut TX wire);
- ``protocol_version`` -- answer handshakes as another protocol version;
- :meth:`disappear` / :meth:`reappear` -- close and re-open the listening socket, like a
  USB serial device that is unplugged and plugged back in;
- ``response_delay_s``, ``opcode_nacks``, :meth:`skip_seq`, :meth:`forget_host`,
  :meth:`send_raw`, :meth:`emit_event`.
"""

from __future__ import annotations

import heapq
import select
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from oibar import pb
from oibar.link.framing import FrameDecoder, Packet, encode_frame

SEQ_MAX = 0xFFFFFFFF
_STALE_SEQ_WINDOW = 1024
_CALL_TIMEOUT_S = 5.0


def _seq_is_newer(newest: int, seq: int) -> bool:
    """The MCU's replay window (docs/link.md): ``seq`` is ahead of ``newest`` by 1 .. SEQ_MAX // 2
    along the numbering that wraps SEQ_MAX -> 1. No request yet (0): anything is newer."""
    if newest == 0:
        return True
    return 1 <= (seq - newest) % SEQ_MAX <= SEQ_MAX // 2


def _body_bytes(packet: Packet) -> bytes:
    """A request's body type and content, which a retransmission repeats exactly."""
    kind = packet.WhichOneof("body")
    return kind.encode() + b":" + getattr(packet, kind).SerializeToString(deterministic=True)


@dataclass
class Param:
    name: str
    unit: str
    value: float
    min: float
    max: float
    default_value: float


def wait_for(predicate: Callable[[], object], timeout_s: float = 3.0, interval_s: float = 0.005) -> bool:
    """Poll ``predicate()`` until it is true or ``timeout_s`` passes (test helper)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval_s)
    return bool(predicate())


def default_params() -> dict[int, Param]:
    """A handful of parameters; ids 1..12 exist, 99 does not."""
    params = {
        1: Param("transfer_target_kpa", "kPa", 200.0, 0.0, 500.0, 200.0),
        2: Param("overpressure_kpa", "kPa", 550.0, 100.0, 700.0, 550.0),
        3: Param("latch_speed_sps", "steps/s", 400.0, 50.0, 1000.0, 400.0),
    }
    for param_id in range(4, 13):
        params[param_id] = Param(f"spare_{param_id}", "", float(param_id), 0.0, 1000.0, 0.0)
    return params


class FakeMcu:
    """MCU-side link peer over a local TCP socket. Use as a context manager or call
    :meth:`start` / :meth:`stop`."""

    def __init__(
        self,
        *,
        protocol_version: int = pb.PROTOCOL_VERSION,
        telemetry_period_s: float = 0.05,
        heartbeat_period_s: float = 0.1,
        link_timeout_s: float = 1.0,
        firmware_version: str = "fake-1.2.3",
        build_id: str = "fake-build-0001",
        reset_cause: int = pb.RESET_POWER_ON,
    ) -> None:
        self.protocol_version = protocol_version
        self.telemetry_period_s = telemetry_period_s
        self.telemetry_muted = False
        self.heartbeat_period_s = heartbeat_period_s
        self.link_timeout_s = link_timeout_s
        self.firmware_version = firmware_version
        self.build_id = build_id
        self.reset_cause = reset_cause
        self.response_delay_s = 0.0
        self.opcode_nacks: dict[int, int] = {}  # opcode -> NackReason to answer with
        self.params = default_params()

        # Observations (appended on the loop thread; read them after wait_until()).
        self.received: list[Packet] = []
        self.executed: list[int] = []  # opcodes actually executed
        self.nav_updates: list = []
        self.rx_duplicates = 0
        self.dropped_responses = 0
        self.handshakes_accepted = 0
        self.link_losses = 0
        self.unplanned_link_losses = 0  # losses without an accepted CMD_END_SESSION (the MCU faults)
        self.session_ended = False  # CMD_END_SESSION accepted since the last handshake
        self.lost_host_packets = 0
        self.connections = 0

        self.state = pb.STATE_IDLE
        self.connected = False
        self.silent = False
        self._drop_count = 0
        self._seq = 0
        self._boot_s = time.monotonic()
        self._last_rx_s = 0.0
        self._last_request_seq = 0
        self._last_request_body = b""
        self._cached_response: Packet | None = None
        self.rx_stale = 0
        self._host_seq: int | None = None

        self._decoder = FrameDecoder(on_unknown_type=self._on_unknown_type)
        self._lock = threading.Lock()
        self._calls: list[tuple[Callable[[], object], threading.Event, list]] = []
        self._delayed: list[tuple[float, int, Packet]] = []  # heap of (due, order, packet)
        self._delayed_order = 0
        self._wake_r, self._wake_w = socket.socketpair()
        self._listener: socket.socket | None = None
        self._conn: socket.socket | None = None
        self._stopping = False
        self._thread: threading.Thread | None = None
        self.port = 0

    # -- lifecycle ---------------------------------------------------------

    def start(self) -> FakeMcu:
        self._listen()
        self._thread = threading.Thread(target=self._run, name="fake-mcu", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._thread is None:
            return
        self._call(self._stop_now)
        self._thread.join(_CALL_TIMEOUT_S)
        self._thread = None
        self._wake_r.close()
        self._wake_w.close()

    def __enter__(self) -> FakeMcu:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    # -- knobs -------------------------------------------------------------

    def drop_responses(self, count: int) -> None:
        """Do not send the next ``count`` responses (requests are still executed)."""
        self._call(lambda: setattr(self, "_drop_count", count))

    def go_silent(self) -> None:
        """Stop sending anything; keep receiving."""
        self._call(lambda: setattr(self, "silent", True))

    def resume(self) -> None:
        self._call(lambda: setattr(self, "silent", False))

    def disappear(self) -> None:
        """Close the connection and the listening socket: the port is gone."""
        self._call(self._disappear_now)

    def reappear(self) -> None:
        """Listen again on the same port."""
        self._call(self._listen)

    def skip_seq(self, count: int) -> None:
        """Advance our seq without sending: the host should count ``count`` lost packets."""
        self._call(lambda: setattr(self, "_seq", self._seq + count))

    def forget_host(self) -> None:
        """Drop back to unconnected without telling the host (as after a quick reset)."""
        self._call(self._forget_host_now)

    def mute_telemetry(self, muted: bool) -> None:
        """Send no telemetry (heartbeats and answers go on) while `muted`."""
        self._call(lambda: setattr(self, "telemetry_muted", muted))

    def reboot(self) -> None:
        """Restart as after a watchdog reset: uptime and seq from zero, host forgotten, the
        connection kept (a USB-serial adapter outlives the MCU behind it)."""

        def now() -> None:
            self._forget_host_now()
            self._boot_s = time.monotonic()
            self._seq = 0
            self._host_seq = None

        self._call(now)

    def send_raw(self, data: bytes) -> None:
        """Write arbitrary bytes to the host."""
        self._call(lambda: self._transmit(data))

    def emit_event(self, event_id: int, **fields: object) -> None:
        self._call(lambda: self._send_event(event_id, **fields))

    def wait_until(self, predicate: Callable[[FakeMcu], bool], timeout_s: float = 3.0) -> bool:
        """Poll ``predicate(self)`` until true or timeout (test helper)."""
        return wait_for(lambda: predicate(self), timeout_s)

    def requests(self, kind: str) -> list[Packet]:
        """Received packets whose body is ``kind`` (e.g. "command"), retransmissions included."""
        return [p for p in list(self.received) if p.WhichOneof("body") == kind]

    @property
    def counters(self):
        return self._decoder.counters

    # -- loop --------------------------------------------------------------

    def _call(self, fn: Callable[[], object]) -> object:
        """Run ``fn`` on the loop thread and wait for it (or run it now if not started)."""
        if self._thread is None or threading.current_thread() is self._thread:
            return fn()
        done = threading.Event()
        result: list = []
        with self._lock:
            self._calls.append((fn, done, result))
        self._wake_w.send(b"x")
        if not done.wait(_CALL_TIMEOUT_S):
            raise TimeoutError("fake MCU loop did not answer")
        return result[0] if result else None

    def _run(self) -> None:
        now = time.monotonic()
        next_telemetry_s = now
        next_heartbeat_s = now
        while True:
            with self._lock:
                calls, self._calls = self._calls, []
            for fn, done, result in calls:
                try:
                    result.append(fn())
                finally:
                    done.set()
            if self._stopping:
                return
            now = time.monotonic()
            if now >= next_telemetry_s:
                self._send_telemetry()
                next_telemetry_s = now + self.telemetry_period_s
            if now >= next_heartbeat_s:
                self._send_heartbeat()
                next_heartbeat_s = now + self.heartbeat_period_s
            while self._delayed and self._delayed[0][0] <= now:
                self._send_packet(heapq.heappop(self._delayed)[2])
            if self.connected and now - self._last_rx_s > self.link_timeout_s:
                self.connected = False
                self.link_losses += 1
                if not self.session_ended:
                    self.unplanned_link_losses += 1
                self._send_event(pb.EVT_LINK_LOST, severity=pb.SEVERITY_WARNING_HI)
            due = [next_telemetry_s, next_heartbeat_s, now + 0.05]
            if self._delayed:
                due.append(self._delayed[0][0])
            timeout_s = max(0.0, min(due) - time.monotonic())
            sockets = [self._wake_r] + [s for s in (self._listener, self._conn) if s is not None]
            readable, _, _ = select.select(sockets, [], [], timeout_s)
            if self._wake_r in readable:
                self._wake_r.recv(4096)
            if self._listener is not None and self._listener in readable:
                self._accept()
            if self._conn is not None and self._conn in readable:
                self._receive()

    def _stop_now(self) -> None:
        self._stopping = True
        self._disappear_now()

    def _listen(self) -> None:
        if self._listener is not None:
            return
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", self.port))
        listener.listen(4)
        self.port = listener.getsockname()[1]
        self._listener = listener

    def _disappear_now(self) -> None:
        self._drop_connection()
        if self._listener is not None:
            self._listener.close()
            self._listener = None

    def _accept(self) -> None:
        conn, _ = self._listener.accept()
        conn.settimeout(2.0)
        self._drop_connection()  # a newer host connection replaces an older one
        self._conn = conn
        self._decoder.reset()
        self.connections += 1

    def _drop_connection(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except OSError:
                pass
            self._conn = None

    def _receive(self) -> None:
        try:
            data = self._conn.recv(4096)
        except OSError:
            data = b""
        if not data:
            self._drop_connection()
            return
        for packet in self._decoder.feed(data):
            self._on_packet(packet)

    def _transmit(self, frame: bytes) -> None:
        if self._conn is None or self.silent:
            return
        try:
            self._conn.sendall(frame)
        except OSError:
            self._drop_connection()

    # -- MCU link rules ----------------------------------------------------

    def _packet(self, ack_seq: int = 0) -> Packet:
        """A packet to fill; it gets its seq when first sent, so seq order is wire order
        even for delayed responses."""
        return Packet(ack_seq=ack_seq)

    def _send_packet(self, packet: Packet) -> None:
        if packet.seq == 0:
            self._seq = self._seq % SEQ_MAX + 1
            packet.seq = self._seq
        self._transmit(encode_frame(packet))

    def _uptime_ms(self) -> int:
        return int((time.monotonic() - self._boot_s) * 1000) & 0xFFFFFFFF

    def _on_packet(self, packet: Packet) -> None:
        self._last_rx_s = time.monotonic()
        self.received.append(packet)
        self._track_host_seq(packet.seq)
        kind = packet.WhichOneof("body")
        if kind == "handshake":
            self._handshake(packet)
        elif kind in ("command", "param_get", "param_set"):
            self._request(packet, kind)
        elif kind == "nav_update":
            self.nav_updates.append(packet.nav_update)

    def _on_unknown_type(self, packet: Packet) -> None:
        self._last_rx_s = time.monotonic()
        if packet.seq != 0:
            reply = self._packet(packet.seq)
            reply.ack.accepted = False
            reply.ack.reason = pb.NACK_UNKNOWN_MESSAGE
            reply.ack.state = self.state
            self._respond(reply)

    def _track_host_seq(self, seq: int) -> None:
        if seq == 0:
            return
        last = self._host_seq
        if last is not None:
            behind = (last - seq) % SEQ_MAX
            if seq == last or behind <= _STALE_SEQ_WINDOW:
                return  # a retransmission
            ahead = (seq - (last % SEQ_MAX + 1)) % SEQ_MAX
            if ahead < SEQ_MAX // 2:
                self.lost_host_packets += ahead
        self._host_seq = seq

    def _handshake(self, packet: Packet) -> None:
        # A handshake is always handled (never answered from the cache): it has no side
        # effect except resetting the duplicate memory, which a repeat may do again.
        reply = self._packet(packet.seq)
        hr = reply.handshake_reply
        hr.protocol_version = self.protocol_version
        hr.firmware_version = self.firmware_version
        hr.build_id = self.build_id
        hr.reset_cause = self.reset_cause
        hr.uptime_ms = self._uptime_ms()
        if packet.handshake.protocol_version != self.protocol_version:
            hr.accepted = False
            hr.reason = pb.NACK_VERSION_MISMATCH
            self.connected = False
            self._respond(reply)
            return
        hr.accepted = True
        self.connected = True
        self.session_ended = False  # a new session: its loss faults again
        self.handshakes_accepted += 1
        self._host_seq = packet.seq
        self._last_request_seq = packet.seq
        self._last_request_body = _body_bytes(packet)
        self._cached_response = reply
        self._respond(reply)
        self._send_event(pb.EVT_LINK_UP, severity=pb.SEVERITY_ACTIVITY_HI)

    def _request(self, packet: Packet, kind: str) -> None:
        if not self.connected:
            reply = self._packet(packet.seq)
            reply.ack.accepted = False
            reply.ack.reason = pb.NACK_NOT_CONNECTED
            reply.ack.state = self.state
            self._respond(reply)
            return
        body = _body_bytes(packet)
        if packet.seq != 0 and packet.seq == self._last_request_seq and self._cached_response:
            if body == self._last_request_body:
                self.rx_duplicates += 1
                self._respond(self._cached_response)  # the very same packet, same seq once sent
                return
            self._refuse_seq(packet, pb.NACK_SEQ_REUSED)
            return
        if packet.seq == 0 or not _seq_is_newer(self._last_request_seq, packet.seq):
            self._refuse_seq(packet, pb.NACK_STALE_SEQ)  # a replay or a reordered request
            return
        if kind == "command":
            reply = self._command(packet)
        else:
            reply = self._param(packet, kind)
        self._last_request_seq = packet.seq
        self._last_request_body = body
        self._cached_response = reply
        self._respond(reply)

    def _refuse_seq(self, packet: Packet, reason: int) -> None:
        """The replay window's refusal: never executed, never cached."""
        self.rx_stale += 1
        reply = self._packet(packet.seq)
        reply.ack.accepted = False
        reply.ack.reason = reason
        reply.ack.state = self.state
        self._respond(reply)

    def _respond(self, reply: Packet) -> None:
        if self._drop_count > 0:
            self._drop_count -= 1
            self.dropped_responses += 1
            return
        if self.response_delay_s > 0:
            self._delayed_order += 1
            due = time.monotonic() + self.response_delay_s
            heapq.heappush(self._delayed, (due, self._delayed_order, reply))
        else:
            self._send_packet(reply)

    def _command(self, packet: Packet) -> Packet:
        opcode = packet.command.opcode
        reply = self._packet(packet.seq)
        reason = self.opcode_nacks.get(opcode, pb.NACK_NONE)
        new_state = self.state
        if reason == pb.NACK_NONE:
            if opcode not in pb.CommandOpcode.values() or opcode == pb.CMD_UNSPECIFIED:
                reason = pb.NACK_UNKNOWN_OPCODE
            elif opcode == pb.CMD_APPROACH_ARM:
                if self.state == pb.STATE_IDLE:
                    new_state = pb.STATE_APPROACH_READY
                else:
                    reason = pb.NACK_INVALID_IN_STATE
            elif opcode == pb.CMD_ABORT:
                new_state = pb.STATE_IDLE
            elif opcode == pb.CMD_END_SESSION:  # planned end: the firmware holds or safes (state_table.md)
                if self.state == pb.STATE_APPROACH_READY:
                    new_state = pb.STATE_IDLE
            elif opcode == pb.CMD_START_TRANSFER and packet.command.target_pressure_kpa <= 0:
                reason = pb.NACK_BAD_ARGUMENT
        reply.ack.accepted = reason == pb.NACK_NONE
        reply.ack.reason = reason
        if reply.ack.accepted:
            self.executed.append(opcode)
            if opcode == pb.CMD_END_SESSION:
                self.session_ended = True
            elif opcode != pb.CMD_NOOP:
                self.session_ended = False
            if new_state != self.state:
                old_state, self.state = self.state, new_state
                self._send_event(
                    pb.EVT_STATE_CHANGE,
                    from_state=old_state,
                    to_state=new_state,
                    severity=pb.SEVERITY_ACTIVITY_LO,
                )
        reply.ack.state = self.state
        return reply

    def _param(self, packet: Packet, kind: str) -> Packet:
        request = packet.param_get if kind == "param_get" else packet.param_set
        reply = self._packet(packet.seq)
        value = reply.param_value
        value.param_id = request.param_id
        param = self.params.get(request.param_id)
        if param is None:
            value.reason = pb.NACK_UNKNOWN_PARAM
            return reply
        if kind == "param_set":
            if not param.min <= packet.param_set.value <= param.max:
                value.reason = pb.NACK_PARAM_OUT_OF_BOUNDS
            else:
                param.value = packet.param_set.value
        value.value = param.value
        value.min = param.min
        value.max = param.max
        value.default_value = param.default_value
        value.name = param.name
        value.unit = param.unit
        return reply

    def _forget_host_now(self) -> None:
        self.connected = False
        self._last_request_seq = 0
        self._last_request_body = b""
        self._cached_response = None

    def _send_event(self, event_id: int, **fields: object) -> None:
        packet = self._packet()
        packet.event.uptime_ms = self._uptime_ms()
        packet.event.id = event_id
        for name, value in fields.items():
            setattr(packet.event, name, value)
        self._send_packet(packet)

    def _send_heartbeat(self) -> None:
        if self._conn is None:
            return
        packet = self._packet()
        packet.heartbeat.uptime_ms = self._uptime_ms()
        self._send_packet(packet)

    def _send_telemetry(self) -> None:
        if self._conn is None or self.telemetry_muted:
            return
        packet = self._packet()
        t = packet.telemetry
        t.uptime_ms = self._uptime_ms()
        t.state = self.state
        t.sv_tank_kpa = 2000.0
        t.tv_tank_kpa = 150.0
        t.host_link_alive = self.connected
        counters = self._decoder.counters
        for name in (
            "rx_packets",
            "rx_crc_errors",
            "rx_framing_errors",
            "rx_oversize",
            "rx_bad_header",
            "rx_decode_errors",
            "rx_unknown_type",
        ):
            setattr(t.link, name, getattr(counters, name))
        t.link.rx_duplicates = self.rx_duplicates
        t.link.rx_stale = self.rx_stale
        t.link.link_losses = self.link_losses
        self._send_packet(packet)


class PtyBridge:
    """Expose a FakeMcu as a pseudo-terminal device (``/dev/pts/N``), so the client can
    use pyserial's real posix Serial class (termios, TIOCINQ) instead of socket://."""

    def __init__(self, mcu: FakeMcu) -> None:
        import os
        import tty

        self._os = os
        self._master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line discipline: bytes pass unchanged
        self.device = os.ttyname(slave)
        self._slave = slave  # kept open so the pty survives the client re-opening it
        self._sock = socket.create_connection(("127.0.0.1", mcu.port))
        self._stop_r, self._stop_w = socket.socketpair()
        self._thread = threading.Thread(target=self._run, name="fake-mcu-pty", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        os = self._os
        while True:
            readable, _, _ = select.select([self._master, self._sock, self._stop_r], [], [])
            if self._stop_r in readable:
                return
            try:
                if self._master in readable:
                    self._sock.sendall(os.read(self._master, 4096))
                if self._sock in readable:
                    data = self._sock.recv(4096)
                    if not data:
                        return
                    os.write(self._master, data)
            except OSError:
                return

    def close(self) -> None:
        self._stop_w.send(b"x")
        self._thread.join(2.0)
        for fd in (self._master, self._slave):
            self._os.close(fd)
        for sock in (self._sock, self._stop_r, self._stop_w):
            sock.close()
