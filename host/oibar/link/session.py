"""The link core on a caller's clock and a non-blocking transport (docs/link.md, docs/hil.md).

:class:`LinkSession` is :class:`~oibar.link.core.LinkCore` (every host link rule) plus a
transport: ``step(now_s)`` reads what arrived, runs the core's timers and writes what the core
queued. It owns no thread and no clock, so the HIL rig moves it on simulated time, where the MCU
runs faster than real time and a wall-clock timeout would be meaningless. The program that
flies uses the same core through :class:`~oibar.link.client.LinkClient`.

The transport is anything with ``write(bytes)`` and ``read() -> bytes`` that never blocks.
Requests return a :class:`~oibar.link.core.Request` handle at once; ``step()`` completes it
(``done``, ``response`` or ``error``) when the answer arrives, the retries run out, or the link
drops.

Typical use (simulated time)::

    session = LinkSession(wire.host_end, host_version="rig")
    while running:
        session.step(t_s)
        if session.link_up and not session.busy:
            req = session.command(pb.CMD_NOOP, now_s=t_s)
"""

from __future__ import annotations

from typing import Any, Protocol

from oibar import pb
from oibar.link.core import CoreCounters, LinkCore, Notice, Request
from oibar.link.framing import Packet

# Names kept for the callers of the first LinkSession.
SessionCounters = CoreCounters
SessionNotice = Notice

__all__ = ["LinkSession", "Request", "SessionCounters", "SessionLink", "SessionNotice", "Transport"]


class Transport(Protocol):
    def write(self, data: bytes) -> None: ...

    def read(self) -> bytes: ...


class LinkSession(LinkCore):
    """Host side of the link, stepped by its user's clock. Not thread-safe by design."""

    def __init__(self, transport: Transport, *, host_version: str = "oibar-session", **settings: Any) -> None:
        settings.setdefault("protocol_version", pb.PROTOCOL_VERSION)
        super().__init__(host_version=host_version, **settings)
        self.transport = transport
        self.now_s = 0.0

    def step(self, now_s: float) -> None:
        """Read what arrived, run every timer that is due at ``now_s``, write what is queued."""
        self.now_s = now_s
        self.receive(self.transport.read(), now_s)
        super().step(now_s)
        self.flush()

    def flush(self) -> None:
        """Write the frames the core queued (requests and nav updates go out at once)."""
        for frame in self.take_output():
            self.transport.write(frame)

    def _submit(self, kind: str, packet: Packet, now_s: float, *, require_link: bool = True) -> Request:
        req = super()._submit(kind, packet, now_s, require_link=require_link)
        self.flush()
        return req

    def nav_update(self, nav: pb.NavUpdate, *, now_s: float) -> bool:
        sent = super().nav_update(nav, now_s=now_s)
        self.flush()
        return sent

    def heartbeat(self, now_s: float, *, force: bool = False) -> bool:
        sent = super().heartbeat(now_s, force=force)
        self.flush()
        return sent


class SessionLink:
    """A :class:`LinkSession` seen through the calls the navigation daemon makes on a
    :class:`~oibar.link.client.LinkClient` (oibar.nav.daemon), at the session's last ``step``
    time. The rig drives ``NavDaemon.cycle`` with it on simulated time."""

    def __init__(self, session: LinkSession) -> None:
        self.session = session

    @property
    def link_alive(self) -> bool:
        return self.session.link_up

    @property
    def telemetry(self) -> pb.Telemetry | None:
        return self.session.telemetry

    def next_event(self, timeout_s: float | None = 0) -> pb.Event | None:
        events = self.session.events
        return events.popleft() if events else None

    def send_nav_update(self, nav: pb.NavUpdate) -> bool:
        return self.session.nav_update(nav, now_s=self.session.now_s)

    def heartbeat(self, *, force: bool = False) -> bool:
        return self.session.heartbeat(self.session.now_s, force=force)

    def submit_command(self, opcode: int, target_pressure_kpa: float | None = None) -> Request:
        return self.session.command(opcode, target_pressure_kpa, now_s=self.session.now_s)

    def submit_param_set(self, param_id: int, value: float) -> Request:
        return self.session.param_set(param_id, value, now_s=self.session.now_s)
