"""Frames on the wire, exactly as docs/link.md specifies them.

::

    raw frame  = [0x01 header] [Packet bytes, <= PROTOCOL_MAX_PACKET_BYTES] [CRC-32C, LE]
    wire frame = COBS(raw frame) 0x00

:func:`encode_frame` builds one wire frame; :class:`FrameDecoder` turns an arbitrarily
split byte stream back into packets, counting every frame it drops under the same names
as the schema's ``LinkCounters`` so host and MCU statistics read alike.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass

from oibar import pb
from oibar.link import cobs
from oibar.link.crc import crc32c
from oibar.link.errors import PacketTooLarge

_log = logging.getLogger(__name__)

FRAME_HEADER = 0x01
"""Framing format byte; any other value is a frame this decoder does not understand."""

DELIMITER = 0x00
CRC_BYTES = 4
MAX_PACKET_BYTES = pb.MAX_PACKET_BYTES
MAX_FRAME_BYTES = pb.MAX_FRAME_BYTES
MIN_RAW_FRAME_BYTES = 1 + CRC_BYTES
"""Header and CRC around an empty packet: anything shorter is a framing error."""

MAX_RAW_FRAME_BYTES = 1 + MAX_PACKET_BYTES + CRC_BYTES
MAX_ENCODED_FRAME_BYTES = MAX_FRAME_BYTES - 1
"""COBS bytes allowed before the delimiter; one more means the frame is oversize."""

Packet = pb.Packet

# proto/oibar.options: Handshake.host_version has max_size 17 (16 bytes + NUL) on the MCU, which
# drops a longer one as undecodable; both host link implementations refuse it up front.
MAX_HOST_VERSION_BYTES = 16


def check_link_settings(host_version: str, max_retries: int, *periods_s: float) -> None:
    """Refuse settings that cannot work, before anything is opened (shared by LinkClient and
    LinkSession): non-positive periods or timeouts, negative retries, a host version the MCU
    could not decode (nanopb's static size: it would stay silent)."""
    if min(periods_s) <= 0:
        raise ValueError("periods and timeouts must be positive")
    if max_retries < 0:
        raise ValueError("max_retries must be >= 0")
    if len(host_version.encode()) > MAX_HOST_VERSION_BYTES:
        raise ValueError(f"host_version is limited to {MAX_HOST_VERSION_BYTES} bytes")


def encode_frame(packet: Packet) -> bytes:
    """Return the wire bytes of ``packet``: COBS(0x01 + packet + CRC-32C LE) + 0x00.

    Raises :class:`PacketTooLarge` if the packet encodes to more than
    PROTOCOL_MAX_PACKET_BYTES: the peer would drop it as oversize, so failing here, where
    the caller can see why, is better than a silent loss on the wire.
    """
    payload = packet.SerializeToString()
    if len(payload) > MAX_PACKET_BYTES:
        body = packet.WhichOneof("body") or "no body"
        raise PacketTooLarge(
            f"packet ({body}) encodes to {len(payload)} bytes, more than the "
            f"PROTOCOL_MAX_PACKET_BYTES limit of {MAX_PACKET_BYTES}"
        )
    raw = bytes((FRAME_HEADER,)) + payload
    raw += crc32c(raw).to_bytes(CRC_BYTES, "little")
    return cobs.encode(raw) + bytes((DELIMITER,))


@dataclass(frozen=True)
class DecoderCounters:
    """What the decoder did with each frame; named like the schema's ``LinkCounters``.

    Every non-empty frame ends in exactly one of these counters, so their sum is the
    number of frames seen (an oversize frame is counted as soon as it overflows).
    """

    rx_packets: int = 0
    rx_crc_errors: int = 0
    rx_framing_errors: int = 0
    rx_oversize: int = 0
    rx_bad_header: int = 0
    rx_decode_errors: int = 0
    rx_unknown_type: int = 0

    @property
    def frames(self) -> int:
        """All frames seen, valid or not."""
        return sum(asdict(self).values())

    @property
    def errors(self) -> int:
        """Frames dropped for any reason."""
        return self.frames - self.rx_packets


class FrameDecoder:
    """Streaming decoder: feed it whatever ``read()`` returned, get whole packets back.

    It never raises on bytes-like input and resynchronises at the next 0x00, so garbage
    costs at most the frame it touched. Not thread-safe: one reader feeds it.

    ``on_unknown_type`` receives packets that decoded but have no known body. The host
    just drops them; an MCU-side peer needs them to answer ``NACK_UNKNOWN_MESSAGE``.
    """

    def __init__(self, on_unknown_type: Callable[[Packet], None] | None = None) -> None:
        self._on_unknown_type = on_unknown_type
        self._buffer = bytearray()
        self._discarding = False  # inside an oversize frame, waiting for its 0x00
        self._counts = dict.fromkeys(DecoderCounters.__dataclass_fields__, 0)

    @property
    def counters(self) -> DecoderCounters:
        """A consistent snapshot of the counters."""
        return DecoderCounters(**self._counts)

    def reset(self) -> None:
        """Forget a partly received frame (e.g. after re-opening the port); keep counters."""
        self._buffer.clear()
        self._discarding = False

    def feed(self, data: bytes | bytearray | memoryview) -> list[Packet]:
        """Consume ``data`` and return the packets completed by it, in order."""
        packets: list[Packet] = []
        data = bytes(data)
        start = 0
        size = len(data)
        while start < size:
            zero = data.find(DELIMITER, start)
            if zero < 0:
                self._append(data, start, size)
                break
            self._append(data, start, zero)
            self._end_of_frame(packets)
            start = zero + 1
        return packets

    def _append(self, data: bytes, start: int, end: int) -> None:
        if self._discarding or start == end:
            return
        self._buffer += data[start:end]
        if len(self._buffer) > MAX_ENCODED_FRAME_BYTES:
            self._counts["rx_oversize"] += 1
            self._buffer.clear()
            self._discarding = True

    def _end_of_frame(self, packets: list[Packet]) -> None:
        if self._discarding:
            self._discarding = False
            return
        if not self._buffer:
            return  # idle line / frame start marker
        encoded = bytes(self._buffer)
        self._buffer.clear()
        try:
            outcome = self._decode(encoded)
        except Exception:  # a bug here must not take the reader thread down
            _log.exception("unexpected error decoding a %d-byte frame", len(encoded))
            outcome = "rx_decode_errors"
        if isinstance(outcome, str):
            self._counts[outcome] += 1
            return
        self._counts["rx_packets"] += 1
        packets.append(outcome)

    def _decode(self, encoded: bytes) -> Packet | str:
        """Return the packet, or the name of the counter that explains why not."""
        try:
            raw = cobs.decode(encoded)
        except cobs.CobsDecodeError:
            return "rx_framing_errors"
        if len(raw) < MIN_RAW_FRAME_BYTES:
            return "rx_framing_errors"
        if raw[0] != FRAME_HEADER:
            return "rx_bad_header"
        body, crc_bytes = raw[:-CRC_BYTES], raw[-CRC_BYTES:]
        if crc32c(body) != int.from_bytes(crc_bytes, "little"):
            return "rx_crc_errors"
        packet = Packet()
        try:
            packet.ParseFromString(body[1:])
        except Exception:  # DecodeError, or anything else the runtime throws on bad input
            return "rx_decode_errors"
        if packet.WhichOneof("body") is None:
            if self._on_unknown_type is not None:
                try:
                    self._on_unknown_type(packet)
                except Exception:
                    _log.exception("on_unknown_type callback failed")
            return "rx_unknown_type"
        return packet
