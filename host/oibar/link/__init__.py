"""The host side of the OIBAR link (docs/link.md): framing, CRC, COBS and the client.

The low-level pieces (:mod:`~oibar.link.crc`, :mod:`~oibar.link.cobs`,
:mod:`~oibar.link.framing`) have no threads and no I/O, so tests, tools and a simulated MCU
can reuse them; :class:`LinkClient` adds the serial port and the link rules.
"""

from oibar.link.client import LinkClient
from oibar.link.errors import (
    LinkClosed,
    LinkDown,
    LinkError,
    LinkTimeout,
    Nack,
    PacketTooLarge,
    PortError,
    ProtocolVersionError,
)
from oibar.link.framing import DecoderCounters, FrameDecoder, encode_frame
from oibar.link.results import CommandResult, HandshakeInfo, LinkStatistics, ParamValue, parse_opcode

__all__ = [
    "CommandResult",
    "DecoderCounters",
    "FrameDecoder",
    "HandshakeInfo",
    "LinkClient",
    "LinkClosed",
    "LinkDown",
    "LinkError",
    "LinkStatistics",
    "LinkTimeout",
    "Nack",
    "PacketTooLarge",
    "ParamValue",
    "PortError",
    "ProtocolVersionError",
    "encode_frame",
    "parse_opcode",
]
