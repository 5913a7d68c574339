"""What the link's requests answer: the handshake, a command's verdict, a parameter, the link's
counters; and the completed request handles of :mod:`oibar.link.core` turned into them (the
client's blocking calls and the navigation daemon's non-blocking ones share these)."""

from __future__ import annotations

from dataclasses import dataclass

from oibar import pb
from oibar.link.core import Request
from oibar.link.errors import LinkError, Nack

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

    def raise_for_nack(self, what: str = "command") -> CommandResult:
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

    def raise_for_nack(self, what: str = "parameter request") -> ParamValue:
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
    link_losses: int = 0
    mcu_restarts: int = 0  # link losses because the MCU rebooted (uptime back, host link down)


def parse_opcode(opcode: int | str) -> int:
    """Accept a CommandOpcode value or a name with or without ``CMD_`` (any case)."""
    if isinstance(opcode, int):
        return opcode
    name = opcode.strip().upper()
    if not name.startswith("CMD_"):
        name = "CMD_" + name
    try:
        return int(pb.CommandOpcode.Value(name))
    except ValueError:
        known = ", ".join(n[4:] for n in pb.CommandOpcode.keys() if n != "CMD_UNSPECIFIED")  # noqa: SIM118  (protobuf enum)
        raise ValueError(f"unknown command {opcode!r}; known commands: {known}") from None


# ---------------------------------------------------------------------------
# Request handles -> results (shared with the navigation daemon)


def info_from_reply(reply: pb.HandshakeReply) -> HandshakeInfo:
    """A handshake reply as HandshakeInfo."""
    return HandshakeInfo(
        firmware_version=reply.firmware_version,
        build_id=reply.build_id,
        protocol_version=reply.protocol_version,
        reset_cause=pb.enum_name(pb.ResetCause, reply.reset_cause),
        uptime_ms=reply.uptime_ms,
    )


def command_result(req: Request) -> CommandResult:
    """The verdict in a completed command handle (raises its link error, if any)."""
    if req.error is not None:
        raise req.error
    if req.response_kind != "ack":
        raise LinkError(f"unexpected {req.response_kind} in answer to a command")
    ack = req.response
    return CommandResult(
        accepted=ack.accepted,
        reason=pb.enum_name(pb.NackReason, ack.reason),
        state=pb.enum_name(pb.State, ack.state),
    )


def param_value(req: Request, param_id: int) -> ParamValue:
    """The answer in a completed parameter handle (raises its link error, if any)."""
    if req.error is not None:
        raise req.error
    if req.response_kind == "ack":  # e.g. NACK_NOT_CONNECTED or NACK_UNKNOWN_MESSAGE
        return ParamValue(
            param_id, 0.0, 0.0, 0.0, 0.0, "", "", pb.enum_name(pb.NackReason, req.response.reason)
        )
    if req.response_kind != "param_value":
        raise LinkError(f"unexpected {req.response_kind} in answer to a parameter request")
    v = req.response
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
