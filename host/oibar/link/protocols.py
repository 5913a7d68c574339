"""What navigation needs of the link and of the MCU's telemetry, as ``typing.Protocol`` types.

The navigation daemon (oibar.nav.daemon) and guidance (oibar.nav.guidance) never name a link
class: the program that flies hands them a :class:`~oibar.link.client.LinkClient` (its own I/O
thread, wall clock), the HIL rig a :class:`~oibar.link.session.SessionLink` (simulated time),
the benchmark and the tests their own stubs. Each fits :class:`NavLink` structurally; mypy
checks that the two real ones do (the block at the end of this file).

:class:`Telemetry` and :class:`Event` are the fields guidance reads of ``pb.Telemetry`` and
``pb.Event``: a test can hand it a plain object with just those.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

from oibar import pb
from oibar.link.core import Request

__all__ = ["Connectable", "Event", "NavLink", "Telemetry"]


class Telemetry(Protocol):
    """The MCU telemetry fields guidance and the daemon read (all in ``pb.Telemetry``)."""

    @property
    def state(self) -> int: ...  # pb.State
    @property
    def fault_flags(self) -> int: ...
    @property
    def tv_tank_kpa(self) -> float: ...
    @property
    def contact(self) -> bool: ...
    @property
    def latch_engaged(self) -> bool: ...
    @property
    def sv_valve_open(self) -> bool: ...
    @property
    def tv_valve_open(self) -> bool: ...
    @property
    def sv_valve_cmd_open(self) -> bool: ...
    @property
    def tv_valve_cmd_open(self) -> bool: ...


class Event(Protocol):
    """The MCU event fields guidance reads (all in ``pb.Event``)."""

    @property
    def id(self) -> int: ...  # pb.EventId
    @property
    def fault(self) -> int: ...  # pb.FaultCode


class NavLink(Protocol):
    """The link as the navigation daemon uses it: never blocking, requests as handles.

    ``submit_*`` return a :class:`~oibar.link.core.Request` at once; the cycle reads its
    ``done``, ``error``, ``response`` and ``response_kind`` in a later cycle (stop and wait is the
    link's business, not the cycle's)."""

    @property
    def link_alive(self) -> bool: ...
    @property
    def telemetry(self) -> Telemetry | None: ...
    # (positional-only: the daemon passes these by position, so an implementation names them freely)
    def next_event(self, timeout_s: float | None = ..., /) -> Event | None: ...
    def send_nav_update(self, nav: pb.NavUpdate, /) -> bool: ...
    def heartbeat(self, *, force: bool = False) -> bool: ...
    def submit_command(self, opcode: int, target_pressure_kpa: float | None = None, /) -> Request: ...
    def submit_param_set(self, param_id: int, value: float, /) -> Request: ...


class Connectable(Protocol):
    """A link the daemon can (re)connect in the background (oibar.nav.daemon.connect_in_background)."""

    def connect(self) -> object: ...


if TYPE_CHECKING:  # mypy proves the two real links fit; nothing runs here
    from oibar.link.client import LinkClient
    from oibar.link.session import SessionLink

    def _links_fit(client: LinkClient, rig: SessionLink) -> tuple[NavLink, NavLink, Connectable]:
        return client, rig, client
