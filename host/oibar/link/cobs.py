"""COBS (Consistent Overhead Byte Stuffing): removes every 0x00 so 0x00 can delimit frames.

The encoded form is a sequence of blocks, each a code byte ``n`` (1..255) followed by
``n - 1`` non-zero data bytes; a block with ``n < 255`` stands for its data followed by one
0x00, except the last block, whose implied zero is dropped. Overhead: one byte per started
254 bytes. The delimiter is not part of the encoding; framing adds it.

When the data ends exactly after a full 254-byte block no trailing ``0x01`` block is
emitted (the canonical form); the decoder accepts both forms. Link frames never reach 254
bytes, so the two forms never differ on the wire.
"""

from __future__ import annotations

_MAX_BLOCK_DATA = 254  # data bytes in a block whose code byte is 0xFF


class CobsDecodeError(ValueError):
    """The input is not a valid COBS encoding (zero byte, or a code byte past the end)."""


def encode(data: bytes | bytearray | memoryview) -> bytes:
    """Return the COBS encoding of ``data`` (no 0x00 in it, no delimiter appended)."""
    data = bytes(data)
    size = len(data)
    out = bytearray()
    start = 0
    while True:
        limit = min(size, start + _MAX_BLOCK_DATA)
        zero = data.find(0, start, limit)
        end = limit if zero < 0 else zero
        out.append(end - start + 1)
        out += data[start:end]
        if zero >= 0:
            start = zero + 1  # the zero is implied by the block's code byte
            continue
        if end == size:
            break
        start = end  # a full 254-byte block: no zero consumed, the next block follows
    return bytes(out)


def decode(encoded: bytes | bytearray | memoryview) -> bytes:
    """Return the data whose COBS encoding is ``encoded`` (without its delimiter).

    Raises :class:`CobsDecodeError` for empty input, a 0x00 byte, or a code byte that
    points past the end: those are the framing errors of docs/link.md.
    """
    encoded = bytes(encoded)
    size = len(encoded)
    if size == 0:
        raise CobsDecodeError("empty input: a COBS encoding has at least one code byte")
    zero = encoded.find(0)
    if zero >= 0:
        raise CobsDecodeError(f"0x00 at offset {zero}: COBS data never contains zeros")
    out = bytearray()
    index = 0
    while index < size:
        code = encoded[index]
        end = index + code
        if end > size:
            raise CobsDecodeError(f"code byte {code} at offset {index} points past the end ({size} bytes)")
        out += encoded[index + 1 : end]
        index = end
        if code != 0xFF and index < size:
            out.append(0)
    return bytes(out)
