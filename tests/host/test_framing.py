"""Framing: encode_frame byte layout and every bad-input row of the docs/link.md table.

Each bad input is followed by a valid frame: the decoder must count the right thing,
nothing else, and still deliver the valid frame (it resynchronises at the next 0x00).
"""

from __future__ import annotations

import pytest
import serial

from oibar import pb
from oibar.link import cobs
from oibar.link.crc import crc32c
from oibar.link.errors import LinkError, PacketTooLarge
from oibar.link.framing import (
    MAX_ENCODED_FRAME_BYTES,
    MAX_FRAME_BYTES,
    MAX_PACKET_BYTES,
    DecoderCounters,
    FrameDecoder,
    encode_frame,
)

COUNTER_NAMES = list(DecoderCounters.__dataclass_fields__)


def heartbeat(seq: int = 7, uptime_ms: int = 123456) -> pb.Packet:
    packet = pb.Packet(seq=seq)
    packet.heartbeat.uptime_ms = uptime_ms
    return packet


def raw_frame(payload: bytes, header: int = 0x01, crc: int | None = None) -> bytes:
    """Build a wire frame by hand, with any header/CRC, to make specific bad frames."""
    raw = bytes([header]) + payload
    raw += (crc32c(raw) if crc is None else crc).to_bytes(4, "little")
    return cobs.encode(raw) + b"\x00"


def packet_of_size(size: int) -> pb.Packet:
    """A ParamValue packet whose encoding is exactly ``size`` bytes."""
    packet = pb.Packet(seq=1, ack_seq=2)
    for length in range(size):
        packet.param_value.name = "n" * length
        if packet.ByteSize() >= size:
            break
    if packet.ByteSize() != size:  # a length prefix grew by one byte: pad with another field
        packet.param_value.name = "n" * (length - 2)
        packet.param_value.param_id = 1
    assert packet.ByteSize() == size, packet.ByteSize()
    return packet


def only(counters: DecoderCounters, **expected: int) -> bool:
    return all(getattr(counters, name) == expected.get(name, 0) for name in COUNTER_NAMES)


# -- encoding -------------------------------------------------------------------------------


def test_wire_layout_is_cobs_of_header_packet_crc_then_delimiter():
    packet = heartbeat(seq=1, uptime_ms=0)
    payload = packet.SerializeToString()
    assert payload == bytes.fromhex("08012a00")  # seq=1, empty heartbeat body
    raw = b"\x01" + payload
    crc = crc32c(raw)
    assert crc == reference_crc(raw) == 0xEBBCF855
    # raw = 01 08 01 2a 00 | 55 f8 bc eb: COBS turns the zero after 2a into a code byte.
    assert encode_frame(packet) == bytes.fromhex("05 01 08 01 2a 05 55 f8 bc eb 00")


def reference_crc(data: bytes) -> int:
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def test_round_trip_single_frame():
    packet = heartbeat()
    decoder = FrameDecoder()
    assert decoder.feed(encode_frame(packet)) == [packet]
    assert only(decoder.counters, rx_packets=1)


def test_max_size_packet_is_accepted_and_fits_the_max_frame():
    packet = packet_of_size(MAX_PACKET_BYTES)
    wire = encode_frame(packet)
    assert len(wire) <= MAX_FRAME_BYTES
    decoder = FrameDecoder()
    assert decoder.feed(wire) == [packet]


def test_max_frame_length_is_reached_by_a_zero_free_raw_frame():
    # A 240-byte packet whose raw frame has no zero gives the longest wire frame: 247.
    for filler in range(1000):
        packet = packet_of_size(MAX_PACKET_BYTES)
        packet.seq = 1 + filler
        wire = encode_frame(packet)
        if len(wire) == MAX_FRAME_BYTES:
            break
    assert len(wire) == MAX_FRAME_BYTES
    assert FrameDecoder().feed(wire) == [packet]


def test_oversize_packet_raises_on_encode():
    packet = packet_of_size(MAX_PACKET_BYTES + 1)
    with pytest.raises(PacketTooLarge, match="241 bytes.*240"):
        encode_frame(packet)
    assert issubclass(PacketTooLarge, LinkError) and issubclass(PacketTooLarge, ValueError)


def test_protocol_limits_come_from_the_schema():
    assert MAX_PACKET_BYTES == pb.Protocol.Value("PROTOCOL_MAX_PACKET_BYTES") == 240
    assert MAX_FRAME_BYTES == pb.Protocol.Value("PROTOCOL_MAX_FRAME_BYTES") == 247
    assert MAX_ENCODED_FRAME_BYTES == 246


# -- the docs/link.md table, row by row -------------------------------------------------------

GOOD = heartbeat(seq=99)


def _truncated() -> bytes:
    wire = encode_frame(packet_of_size(40))  # one COBS block: cutting it leaves a dangling code
    return wire[:20] + b"\x00"


def _bad_crc() -> bytes:
    payload = heartbeat().SerializeToString()
    good_crc = crc32c(b"\x01" + payload)
    return raw_frame(payload, crc=good_crc ^ 0x00010000)


def _flipped_payload_bit() -> bytes:
    payload = bytearray(heartbeat().SerializeToString())
    raw = b"\x01" + bytes(payload)
    crc = crc32c(raw)
    payload[-1] ^= 0x04
    return raw_frame(bytes(payload), crc=crc)


BAD_INPUTS = {
    # row: bytes, then 0x00 with nothing wrong -> covered by test_round_trip_single_frame
    "idle_zeros": (b"\x00\x00\x00", {}),
    "oversize": (b"\x55" * 300 + b"\x00", {"rx_oversize": 1}),
    "oversize_by_one": (b"\x55" * (MAX_ENCODED_FRAME_BYTES + 1) + b"\x00", {"rx_oversize": 1}),
    "cobs_code_past_end": (b"\x09\x01\x02\x00", {"rx_framing_errors": 1}),
    "truncated": (_truncated(), {"rx_framing_errors": 1}),
    "raw_shorter_than_5": (cobs.encode(b"\x01\x08\x01\x2a") + b"\x00", {"rx_framing_errors": 1}),
    "bad_header": (raw_frame(heartbeat().SerializeToString(), header=0x02), {"rx_bad_header": 1}),
    "bad_crc": (_bad_crc(), {"rx_crc_errors": 1}),
    "flipped_payload_bit": (_flipped_payload_bit(), {"rx_crc_errors": 1}),
    "protobuf_not_decodable": (raw_frame(b"\x1a\x05\x08"), {"rx_decode_errors": 1}),
    "empty_packet_no_body": (raw_frame(b""), {"rx_unknown_type": 1}),
    "seq_but_no_body": (raw_frame(b"\x08\x05"), {"rx_unknown_type": 1}),
    "unknown_body_field": (raw_frame(b"\x08\x05\x72\x02\x08\x01"), {"rx_unknown_type": 1}),
    "garbage_then_delimiter": (b"\x13\x37\xde\xad\xbe\xef\x00", {"rx_framing_errors": 1}),
}


@pytest.mark.parametrize("name", list(BAD_INPUTS))
def test_bad_input_is_counted_and_the_next_frame_decodes(name):
    bad, expected = BAD_INPUTS[name]
    decoder = FrameDecoder()
    assert decoder.feed(bad) == []
    assert only(decoder.counters, **expected), decoder.counters
    assert decoder.feed(encode_frame(GOOD)) == [GOOD]
    assert only(decoder.counters, rx_packets=1, **expected), decoder.counters


@pytest.mark.parametrize("name", list(BAD_INPUTS))
def test_bad_input_in_one_read_with_good_frames_around_it(name):
    bad, expected = BAD_INPUTS[name]
    first, last = heartbeat(seq=1), heartbeat(seq=2)
    decoder = FrameDecoder()
    assert decoder.feed(encode_frame(first) + bad + encode_frame(last)) == [first, last]
    assert only(decoder.counters, rx_packets=2, **expected), decoder.counters


def test_oversize_is_counted_once_however_long_and_however_split():
    decoder = FrameDecoder()
    for _ in range(50):
        assert decoder.feed(b"\x77" * 100) == []
    assert decoder.counters.rx_oversize == 1
    assert decoder.feed(b"\x00" + encode_frame(GOOD)) == [GOOD]
    assert only(decoder.counters, rx_packets=1, rx_oversize=1)


def test_frame_of_exactly_max_encoded_length_is_not_oversize():
    decoder = FrameDecoder()
    decoder.feed(b"\x55" * MAX_ENCODED_FRAME_BYTES + b"\x00")
    assert decoder.counters.rx_oversize == 0
    assert decoder.counters.frames == 1  # judged on content (here: bad COBS), not length


def test_garbage_touching_a_frame_costs_only_that_frame():
    # No 0x00 between garbage and the frame: they merge and that frame is lost, the next is not.
    decoder = FrameDecoder()
    stream = b"\x01\x02\x03" + encode_frame(heartbeat(seq=1)) + encode_frame(heartbeat(seq=2))
    assert decoder.feed(stream) == [heartbeat(seq=2)]
    assert decoder.counters.rx_packets == 1
    assert decoder.counters.errors == 1


def test_garbage_between_frames_separated_by_a_delimiter_costs_nothing():
    decoder = FrameDecoder()
    a, b = heartbeat(seq=1), heartbeat(seq=2)
    stream = encode_frame(a) + b"\xde\xad\xbe\xef\x00" + b"\x00" * 4 + encode_frame(b)
    assert decoder.feed(stream) == [a, b]
    assert decoder.counters.rx_packets == 2 and decoder.counters.errors == 1


def test_frames_split_byte_by_byte():
    packets = [heartbeat(seq=i, uptime_ms=i * 1000) for i in range(1, 6)]
    packets.append(packet_of_size(MAX_PACKET_BYTES))
    stream = b"".join(encode_frame(p) for p in packets)
    decoder = FrameDecoder()
    out = []
    for byte in stream:
        out += decoder.feed(bytes([byte]))
    assert out == packets
    assert only(decoder.counters, rx_packets=len(packets))


@pytest.mark.parametrize("chunk", [2, 3, 5, 7, 13, 64, 246, 247, 1000])
def test_frames_split_across_many_reads(chunk):
    packets = [heartbeat(seq=i) for i in range(1, 4)] + [packet_of_size(200)]
    stream = b"\x00".join(encode_frame(p) for p in packets)  # extra idle zeros between frames
    decoder = FrameDecoder()
    out = []
    for start in range(0, len(stream), chunk):
        out += decoder.feed(stream[start : start + chunk])
    assert out == packets


def test_bad_frames_split_byte_by_byte_still_count_and_resync():
    bad_stream = b"".join(bad for bad, _ in BAD_INPUTS.values())
    decoder = FrameDecoder()
    out = []
    for byte in bad_stream + encode_frame(GOOD):
        out += decoder.feed(bytes([byte]))
    assert out == [GOOD]
    expected = {name: 0 for name in COUNTER_NAMES}
    for _, counts in BAD_INPUTS.values():
        for name, n in counts.items():
            expected[name] += n
    expected["rx_packets"] = 1
    assert decoder.counters == DecoderCounters(**expected)


def test_reset_drops_a_partial_frame_but_keeps_counters():
    decoder = FrameDecoder()
    decoder.feed(b"\x02\x00")  # one framing error
    wire = encode_frame(GOOD)
    decoder.feed(wire[:5])
    decoder.reset()
    assert decoder.feed(wire) == [GOOD]
    assert only(decoder.counters, rx_packets=1, rx_framing_errors=1)


def test_unknown_type_hook_sees_the_packet_for_a_nack():
    seen = []
    decoder = FrameDecoder(on_unknown_type=seen.append)
    decoder.feed(raw_frame(b"\x08\x05\x72\x02\x08\x01"))
    assert [p.seq for p in seen] == [5]


def test_a_failing_unknown_type_hook_does_not_escape():
    def boom(packet):
        raise RuntimeError("hook bug")

    decoder = FrameDecoder(on_unknown_type=boom)
    assert decoder.feed(raw_frame(b"\x08\x05") + encode_frame(GOOD)) == [GOOD]
    assert decoder.counters.rx_unknown_type == 1


def test_frames_through_a_pyserial_loop_port():
    """The decoder works on whatever serial read() returns (loop:// echoes our writes)."""
    port = serial.serial_for_url("loop://", timeout=0.05)
    try:
        packets = [heartbeat(seq=i) for i in range(1, 4)]
        for packet in packets:
            port.write(encode_frame(packet))
        decoder = FrameDecoder()
        out = []
        while len(out) < len(packets):
            data = port.read(7)
            assert data, "loop port ran dry"
            out += decoder.feed(data)
        assert out == packets
    finally:
        port.close()
