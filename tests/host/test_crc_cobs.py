"""CRC-32C and COBS: the two primitives under every frame."""

from __future__ import annotations

import random

import pytest

from oibar.link import cobs
from oibar.link.crc import CHECK_VALUE, crc32c


def reference_crc32c(data: bytes) -> int:
    """Bit-at-a-time CRC-32C straight from the definition, to check the table version."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def test_crc_check_value():
    assert CHECK_VALUE == 0xE3069283
    assert crc32c(b"123456789") == 0xE3069283


def test_crc_of_empty_input_is_zero():
    assert crc32c(b"") == 0


def test_crc_known_vectors():
    # RFC 3720 (iSCSI) B.4 test patterns
    assert crc32c(bytes(32)) == 0x8A9136AA
    assert crc32c(b"\xff" * 32) == 0x62A8AB43
    assert crc32c(bytes(range(32))) == 0x46DD794E


def test_crc_matches_bitwise_reference_on_random_data():
    rng = random.Random(1234)
    for size in (1, 2, 3, 7, 64, 245, 1000):
        data = rng.randbytes(size)
        assert crc32c(data) == reference_crc32c(data)


def test_crc_can_be_computed_in_pieces():
    data = b"OIBAR docking and refuelling"
    assert crc32c(data[10:], crc32c(data[:10])) == crc32c(data)


def test_crc_accepts_bytearray_and_memoryview():
    assert crc32c(bytearray(b"123456789")) == CHECK_VALUE
    assert crc32c(memoryview(b"123456789")) == CHECK_VALUE


# Canonical COBS examples (one code byte per block, no trailing block after a full one).
COBS_VECTORS = [
    (b"", b"\x01"),
    (b"\x00", b"\x01\x01"),
    (b"\x00\x00", b"\x01\x01\x01"),
    (b"\x00\x11\x00", b"\x01\x02\x11\x01"),
    (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
    (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
    (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
    (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255))),
    (bytes(range(0, 255)), b"\x01\xff" + bytes(range(1, 255))),
    (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff"),
    (bytes(range(2, 256)) + b"\x00", b"\xff" + bytes(range(2, 256)) + b"\x01\x01"),
    (bytes(range(3, 256)) + b"\x00\x01", b"\xfe" + bytes(range(3, 256)) + b"\x02\x01"),
]


@pytest.mark.parametrize(
    "data,encoded", COBS_VECTORS, ids=lambda v: v[:6].hex() if isinstance(v, bytes) else v
)
def test_cobs_vectors(data, encoded):
    assert cobs.encode(data) == encoded
    assert cobs.decode(encoded) == data


@pytest.mark.parametrize("size", [0, 1, 253, 254, 255, 256, 507, 508, 509, 1000])
@pytest.mark.parametrize("fill", ["nonzero", "zeros", "random"])
def test_cobs_round_trip_and_overhead(size, fill):
    if fill == "nonzero":
        data = bytes((i % 255) + 1 for i in range(size))
    elif fill == "zeros":
        data = bytes(size)
    else:
        data = random.Random(size).randbytes(size)
    encoded = cobs.encode(data)
    assert 0 not in encoded
    assert cobs.decode(encoded) == data
    # one overhead byte per started 254 bytes (at least one)
    assert len(encoded) <= size + max(1, -(-size // 254))


def test_cobs_254_and_255_byte_runs():
    run_254 = b"\x42" * 254
    assert cobs.encode(run_254) == b"\xff" + run_254
    run_255 = b"\x42" * 255
    assert cobs.encode(run_255) == b"\xff" + run_254 + b"\x02\x42"
    for data in (run_254, run_255, run_254 + b"\x00", b"\x00" + run_254):
        assert cobs.decode(cobs.encode(data)) == data


def test_cobs_all_zeros():
    assert cobs.encode(bytes(5)) == b"\x01" * 6
    assert cobs.decode(b"\x01" * 6) == bytes(5)


def test_cobs_decode_accepts_trailing_block_after_full_block():
    # Some encoders emit a final 0x01 after a full 254-byte block; same data.
    run_254 = b"\x42" * 254
    assert cobs.decode(b"\xff" + run_254 + b"\x01") == run_254


@pytest.mark.parametrize(
    "encoded",
    [
        b"",  # no code byte at all
        b"\x05\x11\x22",  # code points past the end
        b"\x02",  # code needs one data byte, none left
        b"\x01\x03\x11",  # second block runs past the end
        b"\x03\x11\x00",  # a zero inside
        b"\x00",  # a zero as code byte
    ],
)
def test_cobs_decode_rejects_invalid_input(encoded):
    with pytest.raises(cobs.CobsDecodeError):
        cobs.decode(encoded)


def test_cobs_decode_error_is_a_value_error():
    assert issubclass(cobs.CobsDecodeError, ValueError)
