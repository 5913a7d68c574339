"""The host's link rules, written once (docs/link.md): sans-IO, stepped by any clock.

:class:`LinkCore` owns no thread, no port and no clock. Bytes from the MCU go in with
``receive(data, now_s)``; timers run in ``step(now_s)``; the frames it wants written come out of
``take_output()``. Every rule of the host side lives here and nowhere else:

- framing (:mod:`oibar.link.framing`) and sequence numbers (:mod:`oibar.link.seq`);
- the handshake and its verdict (version mismatch, refusal), a new numbering session each time;
- one request outstanding (stop and wait), matched to its response by ``ack_seq``, retransmitted
  with the *same* seq after ``retransmit_timeout_s`` at most ``max_retries`` times;
- heartbeats: by the core every ``heartbeat_period_s`` (``auto_heartbeat``), or only when the
  caller asks (:meth:`LinkCore.heartbeat`; the navigation daemon does so once per cycle, so a hung
  navigation loop goes silent and the MCU sees it);
- link loss: no valid packet for ``link_timeout_s``, the transport failing (:meth:`port_lost`),
  the MCU answering NACK_NOT_CONNECTED, or the MCU having restarted (its uptime went back, or its
  telemetry says the host link is down); then a fresh handshake every ``reconnect_period_s``.

Two thin drivers use it: :class:`oibar.link.client.LinkClient` (a pyserial port, threads, the
wall clock: the program that flies) and :class:`oibar.link.session.LinkSession` (any
non-blocking transport, the caller's clock: the HIL rig on simulated time). Not thread-safe:
a driver that calls it from several threads holds one lock around every call.
"""

from __future__ import annotations

import collections
import logging
from dataclasses import dataclass
from typing import Any, cast

from oibar import pb
from oibar.link.errors import LinkDown, LinkError, LinkTimeout, Nack, ProtocolVersionError
from oibar.link.framing import FrameDecoder, Packet, check_link_settings, encode_frame
from oibar.link.seq import follow_peer_seq, next_seq

_log = logging.getLogger(__name__)

RESPONSE_BODIES = frozenset({"handshake_reply", "ack", "param_value"})


@dataclass
class Request:
    """One request on the wire. ``done`` once answered, timed out or failed."""

    kind: str  # "handshake", "command", "param_get", "param_set"
    packet: Packet
    sent_at_s: float = 0.0
    retries: int = 0
    done: bool = False
    response: Any = None  # the response body (HandshakeReply, Ack, ParamValue)
    response_kind: str = ""  # its body name ("ack" for an MCU that refused the message type)
    error: LinkError | None = None
    completed_at_s: float | None = None

    @property
    def seq(self) -> int:
        return self.packet.seq

    @property
    def accepted(self) -> bool:
        """Done, answered and accepted (Ack.accepted / HandshakeReply.accepted / reason NONE)."""
        if not self.done or self.response is None or self.error is not None:
            return False
        if hasattr(self.response, "accepted"):
            return bool(self.response.accepted)
        return bool(self.response.reason == pb.NACK_NONE)


@dataclass
class CoreCounters:
    tx_packets: int = 0
    retransmissions: int = 0
    timeouts: int = 0
    link_losses: int = 0
    handshakes: int = 0
    reconnects: int = 0  # successful handshakes after the first
    mcu_restarts: int = 0  # link losses because the MCU rebooted
    lost_peer_packets: int = 0
    unmatched_responses: int = 0
    events_dropped: int = 0


@dataclass
class Notice:
    """Something the driver may pass on: link up/down, a request finished, telemetry, an event."""

    t_s: float
    what: str  # "link_up", "link_down", "request_done", "telemetry", "event"
    request: Request | None = None
    detail: str = ""
    body: Any = None


class LinkCore:
    """Host side of the link as a state machine: bytes and time in, frames and notices out."""

    def __init__(
        self,
        *,
        host_version: str = "oibar-host",
        heartbeat_period_s: float = 0.2,
        link_timeout_s: float = 1.0,
        retransmit_timeout_s: float = 0.2,
        max_retries: int = 3,
        reconnect_period_s: float = 0.5,
        auto_connect: bool = True,
        auto_heartbeat: bool = True,
        protocol_version: int = pb.PROTOCOL_VERSION,
        event_queue_size: int = 1024,
    ) -> None:
        check_link_settings(
            host_version,
            max_retries,
            heartbeat_period_s,
            link_timeout_s,
            retransmit_timeout_s,
            reconnect_period_s,
        )
        self.host_version = host_version
        self.heartbeat_period_s = heartbeat_period_s
        self.link_timeout_s = link_timeout_s
        self.retransmit_timeout_s = retransmit_timeout_s
        self.max_retries = max_retries
        self.reconnect_period_s = reconnect_period_s
        self.auto_connect = auto_connect
        self.auto_heartbeat = auto_heartbeat
        self.protocol_version = protocol_version

        self.counters = CoreCounters()
        self.decoder = FrameDecoder()
        self.link_up = False
        self.handshake_info: pb.HandshakeReply | None = None  # the last accepted one
        self.telemetry: pb.Telemetry | None = None
        self.telemetry_at_s: float | None = None
        self.events: collections.deque[pb.Event] = collections.deque(maxlen=event_queue_size)
        self.notices: collections.deque[Notice] = collections.deque(maxlen=4096)
        self.port_open = True  # the driver says when its transport is gone (port_lost/port_opened)
        self._out: list[bytes] = []
        self._pending: Request | None = None
        self._tx_seq = 0
        self._peer_seq: int | None = None
        self._peer_uptime_ms: int | None = None
        self._last_rx_s = 0.0
        self._last_heartbeat_s = -1e18
        self._next_connect_s = 0.0
        self._ever_up = False
        self._caller_alive_s = -1e18  # last heartbeat() call, sent or not

    # -- state ------------------------------------------------------------

    @property
    def busy(self) -> bool:
        """A request is outstanding (stop and wait: submit the next one after it is done)."""
        return self._pending is not None

    @property
    def pending(self) -> Request | None:
        return self._pending

    def take_output(self) -> list[bytes]:
        """The frames to write, in order (seq order is wire order)."""
        out, self._out = self._out, []
        return out

    def take_events(self) -> list[pb.Event]:
        out = list(self.events)
        self.events.clear()
        return out

    def take_notices(self) -> list[Notice]:
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
        self._next_connect_s = now_s + self.reconnect_period_s
        return self._submit("handshake", packet, now_s, require_link=False)

    def command(self, opcode: int, target_pressure_kpa: float | None = None, *, now_s: float) -> Request:
        packet = Packet()
        packet.command.opcode = cast("pb.CommandOpcode", opcode)
        if target_pressure_kpa:
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

    def nav_update(self, nav: pb.NavUpdate, *, now_s: float) -> bool:
        """Queue a NavUpdate (not acknowledged; newest wins). False when the link is down."""
        if not self.link_up:
            return False
        packet = Packet()
        packet.nav_update.CopyFrom(nav)
        self._send(packet)
        return True

    def heartbeat(self, now_s: float, *, force: bool = False) -> bool:
        """Queue a Heartbeat if the link is up and one is due (or ``force``). With
        ``auto_heartbeat`` off this is the only way heartbeats go out: the caller's loop proves
        it is alive by calling it (every cycle, link up or not: without a call within
        ``link_timeout_s`` the core does not re-handshake either)."""
        self._caller_alive_s = now_s
        if not self.link_up:
            return False
        # 1 ms of slack: a caller on a fixed period must not skip a beat on float rounding
        if not force and now_s - self._last_heartbeat_s < self.heartbeat_period_s - 1e-3:
            return False
        packet = Packet()
        packet.heartbeat.uptime_ms = int(now_s * 1000.0) & 0xFFFFFFFF  # uint32 field
        self._send(packet)
        self._last_heartbeat_s = now_s
        return True

    # -- the clock and the transport ------------------------------------------

    def receive(self, data: bytes, now_s: float) -> None:
        """Bytes from the MCU (any split)."""
        if data:
            for packet in self.decoder.feed(data):
                self._dispatch(packet, now_s)

    def step(self, now_s: float) -> None:
        """Run every timer that is due at ``now_s``."""
        self._run_request_timer(now_s)
        if self.link_up and now_s - self._last_rx_s >= self.link_timeout_s:
            self._set_down(now_s, f"no valid packet from the MCU for {now_s - self._last_rx_s:.2f} s")
        if self.link_up and self.auto_heartbeat:
            self.heartbeat(now_s)
        # With caller heartbeats, the caller's loop must be alive to re-handshake too: a hung
        # navigation loop must not be revived on the MCU's side by the link alone.
        caller_alive = self.auto_heartbeat or now_s - self._caller_alive_s < self.link_timeout_s
        if (
            not self.link_up
            and self.auto_connect
            and self.port_open
            and self._pending is None
            and caller_alive
            and now_s >= self._next_connect_s
        ):
            self.connect(now_s)

    def port_lost(self, now_s: float, why: str) -> None:
        """The transport failed (unplugged, closed): the link is down until it is back."""
        self.port_open = False
        self._out.clear()
        self.decoder.reset()  # a frame cut by the failure is not news
        if self.link_up:
            self._set_down(now_s, f"port failed: {why}")
        elif self._pending is not None:
            self._finish(self._pending, now_s, error=LinkDown(f"port failed: {why}"))

    def port_opened(self, now_s: float) -> None:
        """The transport is (back) open: handshake at the next step."""
        self.port_open = True
        self.decoder.reset()
        self._next_connect_s = now_s

    def fail_pending(self, now_s: float, error: LinkError) -> None:
        """Fail the outstanding request (the driver is closing)."""
        if self._pending is not None:
            self._finish(self._pending, now_s, error=error)

    def drop(self, now_s: float) -> None:
        """Forget everything (a host process that died): no link, no request, new decoder."""
        self.fail_pending(now_s, LinkDown("host session dropped"))
        self.link_up = False
        self._out.clear()
        self.decoder.reset()

    # -- internals ----------------------------------------------------------

    def _submit(self, kind: str, packet: Packet, now_s: float, *, require_link: bool = True) -> Request:
        if self._pending is not None:
            raise LinkError(f"a {self._pending.kind} request is still outstanding (stop and wait)")
        if require_link and not self.link_up:
            raise LinkDown("the link is down; waiting for the MCU to answer again")
        req = Request(kind, packet)
        self._send(packet)
        req.sent_at_s = now_s
        self._pending = req
        return req

    def _send(self, packet: Packet, *, resend: bool = False) -> None:
        if not resend:
            self._tx_seq = next_seq(self._tx_seq)
            packet.seq = self._tx_seq
        self._out.append(encode_frame(packet))
        self.counters.tx_packets += 1

    def _run_request_timer(self, now_s: float) -> None:
        req = self._pending
        if req is None or now_s - req.sent_at_s < self.retransmit_timeout_s:
            return
        if req.retries >= self.max_retries:
            self.counters.timeouts += 1
            self._finish(
                req,
                now_s,
                error=LinkTimeout(
                    f"{req.kind} (seq {req.seq}) got no response after {req.retries + 1} attempts "
                    f"{self.retransmit_timeout_s:g} s apart"
                ),
            )
            if req.kind == "handshake":
                self._next_connect_s = now_s + self.reconnect_period_s
            return
        req.retries += 1
        req.sent_at_s = now_s
        self.counters.retransmissions += 1
        self._send(req.packet, resend=True)  # same seq: the MCU answers from its cache

    def _finish(
        self,
        req: Request,
        now_s: float,
        *,
        response: Any = None,
        kind: str = "",
        error: LinkError | None = None,
    ) -> None:
        req.done = True
        req.response = response
        req.response_kind = kind
        req.error = error
        req.completed_at_s = now_s
        if self._pending is req:
            self._pending = None
        self.notices.append(Notice(now_s, "request_done", req, str(error or "")))

    def _set_down(self, now_s: float, why: str, *, restart: bool = False) -> None:
        if not self.link_up:
            return
        self.link_up = False
        self.counters.link_losses += 1
        self.counters.mcu_restarts += restart
        self._next_connect_s = now_s
        if self._pending is not None:
            self._finish(self._pending, now_s, error=LinkDown(f"link lost: {why}"))
        self.notices.append(Notice(now_s, "link_down", detail=why))

    def _track_peer_seq(self, seq: int) -> None:
        self._peer_seq, lost = follow_peer_seq(self._peer_seq, seq)
        self.counters.lost_peer_packets += lost

    def _uptime_went_back(self, uptime_ms: int) -> bool:
        """The MCU's uptime is monotonic (it wraps after 49 days, far from any mission): going
        back means it restarted."""
        last, self._peer_uptime_ms = self._peer_uptime_ms, uptime_ms
        return last is not None and uptime_ms < last and (last - uptime_ms) < 0x80000000

    def _dispatch(self, packet: Packet, now_s: float) -> None:
        kind = packet.WhichOneof("body")
        if kind in RESPONSE_BODIES:
            self._on_response(packet, kind, now_s)
            return
        if kind == "telemetry":  # kept even while down: the user's best knowledge of the MCU
            self.telemetry = packet.telemetry
            self.telemetry_at_s = now_s
            self.notices.append(Notice(now_s, "telemetry", body=packet.telemetry))
        elif kind == "event":
            if len(self.events) == self.events.maxlen:
                self.counters.events_dropped += 1
            self.events.append(packet.event)
            self.notices.append(Notice(now_s, "event", body=packet.event))
        if not self.link_up:
            return  # an MCU we have not handshaken with (yet, or again)
        uptime = None
        if kind == "heartbeat":
            uptime = packet.heartbeat.uptime_ms
        elif kind == "telemetry" and packet.telemetry.uptime_ms:
            uptime = packet.telemetry.uptime_ms
        if uptime is not None and self._uptime_went_back(uptime):
            # the MCU rebooted (watchdog, brown-out): its link forgot us
            self._set_down(now_s, "the MCU restarted (its uptime went back)", restart=True)
            return
        if kind == "telemetry" and not packet.telemetry.host_link_alive:
            # The MCU dropped us (its link timeout, or a restart): handshake again.
            self._set_down(now_s, "the MCU reports the host link down", restart=True)
            return
        self._last_rx_s = now_s
        self._track_peer_seq(packet.seq)
        if kind not in ("telemetry", "event", "heartbeat"):
            _log.debug("ignoring %s from the peer", kind)  # host-bound bodies, e.g. on loop://

    def _on_response(self, packet: Packet, kind: str, now_s: float) -> None:
        req = self._pending
        if req is None or packet.ack_seq == 0 or packet.ack_seq != req.seq:
            # a late answer to a request that already timed out, or the cached answer to a
            # retransmission after the first answer got through: still proof of life
            self.counters.unmatched_responses += 1
            if self.link_up:
                self._last_rx_s = now_s
                self._track_peer_seq(packet.seq)
            return
        body = getattr(packet, kind)
        self._track_peer_seq(packet.seq)
        if req.kind == "handshake":
            self._on_handshake_reply(req, kind, body, now_s)
            return
        self._last_rx_s = now_s
        self._finish(req, now_s, response=body, kind=kind)
        if kind == "ack" and body.reason == pb.NACK_NOT_CONNECTED:
            # The MCU dropped our session (reset, or it saw a link loss we did not):
            # this request was refused; handshake again.
            self._set_down(now_s, "the MCU answered NACK_NOT_CONNECTED")

    def _on_handshake_reply(self, req: Request, kind: str, body: Any, now_s: float) -> None:
        if kind == "ack":  # an MCU that does not know Handshake at all
            self._finish(
                req,
                now_s,
                response=body,
                kind=kind,
                error=Nack(pb.enum_name(pb.NackReason, body.reason), "handshake"),
            )
            return
        if kind != "handshake_reply":
            self._finish(
                req,
                now_s,
                response=body,
                kind=kind,
                error=LinkError(f"unexpected {kind} in answer to the handshake"),
            )
            return
        if body.reason == pb.NACK_VERSION_MISMATCH or (
            body.accepted and body.protocol_version != self.protocol_version
        ):
            self._finish(
                req,
                now_s,
                response=body,
                kind=kind,
                error=ProtocolVersionError(self.protocol_version, body.protocol_version),
            )
            return
        if not body.accepted:
            self._finish(
                req,
                now_s,
                response=body,
                kind=kind,
                error=Nack(pb.enum_name(pb.NackReason, body.reason), "handshake"),
            )
            return
        self.handshake_info = body
        self.link_up = True
        self.counters.reconnects += self._ever_up
        self._ever_up = True
        self._peer_uptime_ms = body.uptime_ms if body.uptime_ms else None
        self._last_rx_s = now_s
        self._last_heartbeat_s = -1e18
        self._finish(req, now_s, response=body, kind=kind)
        self.notices.append(
            Notice(
                now_s,
                "link_up",
                detail=f"firmware {body.firmware_version}, reset cause "
                f"{pb.enum_name(pb.ResetCause, body.reset_cause)}",
            )
        )
