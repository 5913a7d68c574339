"""Exceptions raised by the host side of the link.

Everything derives from :class:`LinkError`, so a caller that only wants "the link did not
work" catches one type, while the CLI and guidance can tell the cases apart.
A refused request is normally a *result* (``CommandResult.accepted`` is False);
:class:`Nack` exists for callers that prefer an exception.
"""

from __future__ import annotations


class LinkError(Exception):
    """Base class of every link failure."""


class PortError(LinkError):
    """The serial port (or socket:// / loop:// URL) could not be opened or failed."""


class LinkTimeout(LinkError):
    """A request got no response after the original and every retransmission."""


class LinkDown(LinkError):
    """The link is down (no valid packet within the link timeout, or no port); requests
    fail fast with this instead of waiting for a timeout."""


class LinkClosed(LinkDown):
    """The client was closed (possibly while the request was waiting)."""


class ProtocolVersionError(LinkError):
    """The MCU speaks another link protocol version; nothing can be exchanged safely."""

    def __init__(self, host_version: int, mcu_version: int) -> None:
        self.host_version = host_version
        self.mcu_version = mcu_version
        super().__init__(
            f"link protocol version mismatch: this host speaks version {host_version}, "
            f"the MCU speaks version {mcu_version}; update the host or the firmware"
        )


class Nack(LinkError):
    """The MCU refused a request; ``reason`` is the NackReason name (e.g.
    ``"NACK_INVALID_IN_STATE"``)."""

    def __init__(self, reason: str, what: str = "request", state: str | None = None) -> None:
        self.reason = reason
        self.what = what
        self.state = state
        detail = f" (MCU state {state})" if state else ""
        super().__init__(f"{what} refused by the MCU: {reason}{detail}")


class PacketTooLarge(LinkError, ValueError):
    """A packet to send encodes to more than PROTOCOL_MAX_PACKET_BYTES; it cannot be framed."""
