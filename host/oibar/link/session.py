"""A non-threaded, clock-driven host link session (docs/link.md rules, docs/hil.md).

:class:`LinkSession` does what :class:`~oibar.link.client.LinkClient` does (handshake, one
outstanding request retransmitted with the same seq, heartbeats, link-loss detection and
re-handshake) but owns no thread, no port and no clock. The caller moves it forward with
``step(now_s)`` on whatever clock it likes: the wall clock on a real port, or simulated time
in the HIL rig, where the MCU runs faster than real time and a wall-clock timeout would be
meaningless.

The transport is anything with ``write(bytes)`` and ``read() -> bytes`` that never blocks.
Requests return a :class:`Request` handle at once; ``step()`` completes it (``done``,
``response`` or ``error``) when the answer arrives, the retries run out, or the link drops.

Typical use (simulated time)::

    session = LinkSession(wire.host_end, host_version="rig")
    while running:
        session.step(t_s)
        if session.link_up and not session.busy:
            req = session.command(pb.CMD_NOOP, now_s=t_s)
"""

from __future__ import annotations

import collections
import logging
from dataclasses import dataclass
from typing import Any, Protocol

from oibar import pb
from oibar.link.errors import LinkDown, LinkError, LinkTimeout, ProtocolVersionError
from oibar.link.framing import FrameDecoder, Packet, check_link_settings, encode_frame
from oibar.link.seq import follow_peer_seq, next_seq

_log = logging.getLogger(__name__)

_RESPONSE_BODIES = frozenset({"handshake_reply", "ack", "param_value"})


class Transport(Protocol):
    def write(self, data: bytes) -> None: ...

    def read(self) -> bytes: ...


@dataclass
class Request:
    """One request on the wire. ``done`` once answered, timed out or failed."""

    kind: str  # "handshake", "command", "param_get", "param_set"
    packet: Packet
    sent_at_s: float = 0.0
    retries: int = 0
    done: bool = False
    response: Any = None  # the response body (HandshakeReply, Ack, ParamValue)
    error: LinkError | None = None
    completed_at_s: float | None = None

    @property
    def seq(self) -> int:
        return self.packet.seq

    @property
    def accepted(self) -> bool:
        """Done, answered and accepted (Ack.accepted / HandshakeReply.accepted / reason NONE)."""
        if not self.done or self.response is None:
            return False
        if hasattr(self.response, "accepted"):
            return bool(self.response.accepted)
        return self.response.reason == pb.NACK_NONE


@dataclass
class SessionCounters:
    tx_packets: int = 0
    retransmissions: int = 0
    timeouts: int = 0
    link_losses: int = 0
    handshakes: int = 0
    lost_peer_packets: int = 0
    unmatched_responses: int = 0


@dataclass
class SessionNotice:
    """Something the session's user may want to log: link up/down, a request finished."""

    t_s: float
    what: str  # "link_up", "link_down", "request_done"
    request: Request | None = None
    detail: str = ""


class LinkSession:
    """Host side of the link, stepped by its user's clock. Not thread-safe by design."""

    def __init__(
        self,
        transport: Transport,
        *,
        host_version: str = "oibar-session",
        heartbeat_period_s: float = 0.2,
        link_timeout_s: float = 1.0,
        retransmit_timeout_s: float = 0.2,
        max_retries: int = 3,
        reconnect_period_s: float = 0.5,
        auto_connect: bool = True,
        protocol_version: int = pb.PROTOCOL_VERSION,
    ) -> None:
        check_link_settings(host_version, max_retries, heartbeat_period_s, link_timeout_s,
                            retransmit_timeout_s, reconnect_period_s)
        self.transport = transport
        self.host_version = host_version
        self.heartbeat_period_s = heartbeat_period_s
        self.link_timeout_s = link_timeout_s
        self.retransmit_timeout_s = retransmit_timeout_s
        self.max_retries = max_retries
        self.reconnect_period_s = reconnect_period_s
        self.auto_connect = auto_connect
        self.protocol_version = protocol_version

        self.counters = SessionCounters()
        self.decoder = FrameDecoder()
        self.link_up = False
        self.handshake_info: Any = None  # the last accepted HandshakeReply
        self.telemetry: Any = None
        self.telemetry_at_s: float | None = None
        self.events: collections.deque[Any] = collections.deque(maxlen=1024)
        self.notices: collections.deque[SessionNotice] = collections.deque(maxlen=1024)
        self._pending: Request | None = None
        self._tx_seq = 0
        self._peer_seq: int | None = None
        self._peer_uptime_ms: int | None = None
        self._last_rx_s = 0.0
        self._last_heartbeat_s = -1e9
        self._next_connect_s = 0.0
        self._now_s = 0.0

    # -- state ------------------------------------------------------------

    @property
    def busy(self) -> bool:
        """A request is outstanding (stop and wait: submit the next one after it is done)."""
        return self._pending is not None

    @property
    def pending(self) -> Request | None:
        return self._pending

    def take_events(self) -> list[Any]:
        out = list(self.events)
        self.events.clear()
        return out

    def take_notices(self) -> list[SessionNotice]:
        out = list(self.notices)
        self.notices.clear()
        return out

    # -- requests -----------------------------------------------------------

    def connect(self, now_s: float) -> Request:
        """Send a Handshake now (a new seq numbering session)."""
        packet = Packet()
        packet.handshake.protocol_version = self.protocol_version
        packet.handshake.host_version = self.host_version
        self._tx_seq = 0
        self._peer_seq = None
        self.counters.handshakes += 1
        return self._submit("handshake", packet, now_s, require_link=False)

    def command(self, opcode: int, target_pressure_kpa: float = 0.0, *, now_s: float) -> Request:
        packet = Packet()
        packet.command.opcode = opcode
        packet.command.target_pressure_kpa = float(target_pressure_kpa)
        return self._submit("command", packet, now_s)

    def param_get(self, param_id: int, *, now_s: float) -> Request:
        packet = Packet()
        packet.param_get.param_id = param_id
        return self._submit("param_get", packet, now_s)

    def param_set(self, param_id: int, value: float, *, now_s: float) -> Request:
        packet = Packet()
        packet.param_set.param_id = param_id
        packet.param_set.value = float(value)
        return self._submit("param_set", packet, now_s)

    def nav_update(self, nav: Any, *, now_s: float) -> bool:
        """Send a NavUpdate (not acknowledged; newest wins). False when the link is down."""
        if not self.link_up:
            return False
        packet = Packet()
        packet.nav_update.CopyFrom(nav)
        self._send(packet, now_s)
        return True

    # -- the clock ----------------------------------------------------------

    def step(self, now_s: float) -> None:
        """Read what arrived, then run every timer that is due at ``now_s``."""
        self._now_s = now_s
        data = self.transport.read()
        if data:
            for packet in self.decoder.feed(data):
                self._dispatch(packet, now_s)
        self._run_request_timer(now_s)
        if self.link_up and now_s - self._last_rx_s >= self.link_timeout_s:
            self._set_down(now_s, "no valid packet from the MCU within the link timeout")
        if self.link_up and now_s - self._last_heartbeat_s >= self.heartbeat_period_s:
            packet = Packet()
            packet.heartbeat.uptime_ms = int(now_s * 1000.0) & 0xFFFFFFFF   # uint32 field
            self._send(packet, now_s)
            self._last_heartbeat_s = now_s
        if (not self.link_up and self.auto_connect and self._pending is None
                and now_s >= self._next_connect_s):
            self._next_connect_s = now_s + self.reconnect_period_s
            self.connect(now_s)

    def drop(self, now_s: float) -> None:
        """Forget everything (a host process that died): no link, no request, new decoder."""
        if self._pending is not None:
            self._finish(self._pending, now_s, error=LinkDown("host session dropped"))
        self.link_up = False
        self.decoder.reset()

    # -- internals ----------------------------------------------------------

    def _submit(self, kind: str, packet: Packet, now_s: float, *, require_link: bool = True) -> Request:
        if self._pending is not None:
            raise LinkError(f"a {self._pending.kind} request is still outstanding (stop and wait)")
        if require_link and not self.link_up:
            raise LinkDown("the link is down; wait for the session to re-handshake")
        req = Request(kind, packet)
        self._send(packet, now_s)
        req.sent_at_s = now_s
        self._pending = req
        return req

    def _send(self, packet: Packet, now_s: float, *, resend: bool = False) -> None:
        if not resend:
            self._tx_seq = next_seq(self._tx_seq)
            packet.seq = self._tx_seq
        self.transport.write(encode_frame(packet))
        self.counters.tx_packets += 1

    def _run_request_timer(self, now_s: float) -> None:
        req = self._pending
        if req is None or now_s - req.sent_at_s < self.retransmit_timeout_s:
            return
        if req.retries >= self.max_retries:
            self.counters.timeouts += 1
            self._finish(req, now_s, error=LinkTimeout(
                f"{req.kind} seq {req.seq}: no response after {req.retries} retransmissions"))
            if req.kind == "handshake":
                self._next_connect_s = now_s + self.reconnect_period_s
            return
        req.retries += 1
        req.sent_at_s = now_s
        self.counters.retransmissions += 1
        self._send(req.packet, now_s, resend=True)  # same seq: the MCU answers from its cache

    def _finish(self, req: Request, now_s: float, *, response: Any = None,
                error: LinkError | None = None) -> None:
        req.done = True
        req.response = response
        req.error = error
        req.completed_at_s = now_s
        if self._pending is req:
            self._pending = None
        self.notices.append(SessionNotice(now_s, "request_done", req, str(error or "")))

    def _set_down(self, now_s: float, why: str) -> None:
        self.link_up = False
        self.counters.link_losses += 1
        self._next_connect_s = now_s
        if self._pending is not None:
            self._finish(self._pending, now_s, error=LinkDown(why))
        self.notices.append(SessionNotice(now_s, "link_down", detail=why))

    def _track_peer_seq(self, seq: int) -> None:
        self._peer_seq, lost = follow_peer_seq(self._peer_seq, seq)
        self.counters.lost_peer_packets += lost

    def _dispatch(self, packet: Packet, now_s: float) -> None:
        kind = packet.WhichOneof("body")
        req = self._pending
        if kind in _RESPONSE_BODIES:
            if req is None or packet.ack_seq != req.seq:
                self.counters.unmatched_responses += 1
                # Still proof of life for a connected link.
                if self.link_up:
                    self._last_rx_s = now_s
                return
            body = getattr(packet, kind)
            if req.kind == "handshake":
                self._on_handshake_reply(req, kind, body, now_s)
                self._track_peer_seq(packet.seq)
                return
            self._last_rx_s = now_s
            self._track_peer_seq(packet.seq)
            self._finish(req, now_s, response=body)
            return
        if kind == "telemetry":  # kept even while down: the user's best knowledge of the MCU
            self.telemetry = packet.telemetry
            self.telemetry_at_s = now_s
        if not self.link_up:
            return  # an MCU we have not handshaken with yet
        if kind == "heartbeat":
            uptime_ms = packet.heartbeat.uptime_ms
            restarted = self._peer_uptime_ms is not None and uptime_ms < self._peer_uptime_ms
            self._peer_uptime_ms = uptime_ms
            if restarted:  # the MCU rebooted (watchdog, brown-out): its link forgot us
                self._set_down(now_s, "MCU restarted (its uptime went backwards)")
                return
        if kind == "telemetry" and not packet.telemetry.host_link_alive:
            # The MCU dropped us (its link timeout, or a restart): handshake again.
            self._set_down(now_s, "MCU reports the host link down")
            return
        self._last_rx_s = now_s
        self._track_peer_seq(packet.seq)
        if kind == "event":
            self.events.append(packet.event)

    def _on_handshake_reply(self, req: Request, kind: str, body: Any, now_s: float) -> None:
        if kind != "handshake_reply":
            self._finish(req, now_s, response=body, error=LinkError(f"{kind} in answer to a handshake"))
            return
        if body.reason == pb.NACK_VERSION_MISMATCH or (
                body.accepted and body.protocol_version != self.protocol_version):
            self._finish(req, now_s, response=body,
                         error=ProtocolVersionError(self.protocol_version, body.protocol_version))
            self.auto_connect = False  # retrying cannot help
            return
        if not body.accepted:
            self._finish(req, now_s, response=body, error=LinkError("handshake refused"))
            return
        self.handshake_info = body
        self.link_up = True
        self._peer_uptime_ms = None
        self._last_rx_s = now_s
        self._last_heartbeat_s = -1e9
        self._finish(req, now_s, response=body)
        self.notices.append(SessionNotice(
            now_s, "link_up",
            detail=f"firmware {body.firmware_version}, reset cause "
                   f"{pb.enum_name(pb.ResetCause, body.reset_cause)}"))

