"""What the navigation daemon asks of the MCU over the link, apart from the navigation update:
the verdict of guidance's mechanism requests, and the planned end of the session.

Mechanism requests are stop and wait (one at a time, up to the link's retry budget): the daemon
submits them without waiting and reads the handle's verdict in a later cycle
(``request_result``). The planned end of the session (``end_session``, ``CMD_END_SESSION``)
is what every stop of ``oibar nav`` does before it closes the link.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from oibar import pb
from oibar.link.core import Request
from oibar.link.protocols import NavLink
from oibar.nav.guidance import MechRequest, RequestResult


@dataclass
class SessionEnd:
    """How the planned end of the MCU session went (NavDaemon.end_session)."""

    sent: bool  # CMD_END_SESSION reached the MCU and was answered
    accepted: bool  # the MCU accepted it: safe, and its link timeout will not fault
    state: str | None = None  # the MCU's state after it
    detail: str = ""

    @property
    def safe(self) -> bool:
        return self.accepted


def request_result(req: MechRequest, handle: Request) -> RequestResult:
    """Guidance's view of a completed link request handle (oibar.link.core.Request)."""
    if handle.error is not None:  # LinkDown, LinkTimeout, closed: guidance hears it and retries
        return RequestResult(req, False, type(handle.error).__name__)
    body = handle.response
    reason = pb.enum_name(pb.NackReason, body.reason)
    if handle.response_kind == "ack":
        return RequestResult(req, bool(body.accepted), reason, pb.enum_name(pb.State, body.state))
    return RequestResult(req, body.reason == pb.NACK_NONE, reason)


def end_session(link: NavLink, in_flight: Request | None, timeout_s: float) -> SessionEnd:
    """The planned end of the MCU session on ``link``: wait (boundedly) for the request still
    ``in_flight`` (stop and wait: one at a time), then send ``CMD_END_SESSION`` and wait for its
    answer, heartbeating meanwhile, all within ``timeout_s``. Never raises."""
    deadline = time.monotonic() + timeout_s

    def beat() -> None:
        try:
            link.heartbeat()
        except Exception:
            pass
        time.sleep(0.01)

    try:
        while in_flight is not None and not in_flight.done and time.monotonic() < deadline:
            beat()
        if not link.link_alive:
            return SessionEnd(False, False, None, "link down: the MCU takes the silence for a host link loss")
        handle = link.submit_command(pb.CMD_END_SESSION, None)
        while not handle.done and time.monotonic() < deadline:
            beat()
        if not handle.done:
            return SessionEnd(False, False, None, "no answer from the MCU")
        if handle.error is not None:
            return SessionEnd(False, False, None, f"{type(handle.error).__name__}: {handle.error}")
        body = handle.response
        state = pb.enum_name(pb.State, body.state) if handle.response_kind == "ack" else None
        accepted = bool(getattr(body, "accepted", False))
        reason = pb.enum_name(pb.NackReason, body.reason)
        return SessionEnd(True, accepted, state, "accepted" if accepted else f"refused: {reason}")
    except Exception as exc:  # LinkDown, closed, another request out: reported, never raised
        return SessionEnd(False, False, None, f"{type(exc).__name__}: {exc}")
