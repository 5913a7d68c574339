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

# Names kept for the callers of the first LinkSession.
SessionCounters = CoreCounters
SessionNotice = Notice

__all__ = ["LinkSession", "Request", "SessionCounters", "SessionNotice", "Transport"]


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

    def _submit(self, kind, packet, now_s, *, require_link=True):  # noqa: ANN001 (same as the core)
        req = super()._submit(kind, packet, now_s, require_link=require_link)
        self.flush()
        return req

    def nav_update(self, nav: Any, *, now_s: float) -> bool:
        sent = super().nav_update(nav, now_s=now_s)
        self.flush()
        return sent

    def heartbeat(self, now_s: float, *, force: bool = False) -> bool:
        sent = super().heartbeat(now_s, force=force)
        self.flush()
        return sent
