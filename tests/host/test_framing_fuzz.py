"""Property tests: the decoder never raises, its counters add up, and every valid packet
survives encode_frame -> arbitrary splitting -> surrounding garbage -> feed."""

from __future__ import annotations

from google.protobuf.descriptor import FieldDescriptor as FD
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from oibar import pb
from oibar.link import cobs
from oibar.link.framing import MAX_ENCODED_FRAME_BYTES, MAX_PACKET_BYTES, FrameDecoder, encode_frame

# -- strategies -------------------------------------------------------------------------------

_SCALARS = {
    FD.TYPE_UINT32: st.integers(0, 2**32 - 1),
    FD.TYPE_INT32: st.integers(-(2**31), 2**31 - 1),
    FD.TYPE_FLOAT: st.floats(width=32, allow_nan=False),
    FD.TYPE_BOOL: st.booleans(),
    FD.TYPE_STRING: st.text(max_size=16),
}


def _field_strategy(field) -> st.SearchStrategy:
    if field.type == FD.TYPE_ENUM:
        return st.sampled_from([v.number for v in field.enum_type.values])
    if field.type == FD.TYPE_MESSAGE:
        return message_strategy(field.message_type)
    return _SCALARS[field.type]


def message_strategy(descriptor) -> st.SearchStrategy:
    """Any message of ``descriptor``'s type, built from the schema so new fields are covered."""
    cls = getattr(pb, descriptor.name)
    fields = {f.name: _field_strategy(f) for f in descriptor.fields if f.containing_oneof is None}

    def build(values: dict):
        message = cls()
        for name, value in values.items():
            if hasattr(value, "DESCRIPTOR"):  # a nested message
                getattr(message, name).CopyFrom(value)
            else:
                setattr(message, name, value)
        return message

    return st.fixed_dictionaries({}, optional=fields).map(build)


def _with_body(field):
    def attach(args):
        seq, ack_seq, body = args
        packet = pb.Packet(seq=seq, ack_seq=ack_seq)
        getattr(packet, field.name).CopyFrom(body)
        return packet

    return st.tuples(
        _SCALARS[FD.TYPE_UINT32], _SCALARS[FD.TYPE_UINT32], message_strategy(field.message_type)
    ).map(attach)


_BODY_FIELDS = pb.Packet.DESCRIPTOR.oneofs_by_name["body"].fields
packets = st.one_of([_with_body(f) for f in _BODY_FIELDS])

_garbage = st.binary(max_size=40)

# No deadline: the first examples pay for imports and a loaded CI machine is slow; 150
# examples per property keep the whole file around 3 s.
fuzz_settings = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _counts_from_segments(stream: bytes) -> int:
    """Frames the decoder must account for: each non-empty 0x00-terminated segment, plus a
    trailing unterminated one only if it already overflowed."""
    *done, tail = stream.split(b"\x00")
    return sum(1 for seg in done if seg) + (1 if len(tail) > MAX_ENCODED_FRAME_BYTES else 0)


# -- properties -------------------------------------------------------------------------------


@fuzz_settings
@given(stream=st.binary(max_size=3000), cuts=st.lists(st.integers(0, 3000), max_size=20))
def test_decoder_never_raises_and_counters_add_up_on_arbitrary_bytes(stream, cuts):
    decoder = FrameDecoder()
    out = []
    previous = 0
    for cut in sorted(set(c for c in cuts if c <= len(stream))) + [len(stream)]:
        out += decoder.feed(stream[previous:cut])
        previous = cut
    counters = decoder.counters
    assert counters.rx_packets == len(out)
    assert counters.frames == _counts_from_segments(stream)
    assert all(value >= 0 for value in vars(counters).values())


# Streams made of valid frames, damaged frames, zeros and noise: exercises every counter far
# more often than uniformly random bytes do.
def _damage(data: st.DataObject, wire: bytes) -> bytes:
    kind = data.draw(st.sampled_from(["keep", "flip", "cut", "header", "noise"]))
    if kind == "keep":
        return wire
    if kind == "flip":
        i = data.draw(st.integers(0, len(wire) - 2))
        bit = 1 << data.draw(st.integers(0, 7))
        return wire[:i] + bytes([wire[i] ^ bit]) + wire[i + 1 :]
    if kind == "cut":
        i = data.draw(st.integers(0, len(wire) - 1))
        return wire[:i] + b"\x00"
    if kind == "header":
        raw = cobs.decode(wire[:-1])
        return cobs.encode(bytes([data.draw(st.integers(2, 255))]) + raw[1:]) + b"\x00"
    return data.draw(st.binary(min_size=1, max_size=300))


@fuzz_settings
@given(data=st.data(), items=st.lists(packets, max_size=6))
def test_counters_add_up_on_streams_of_damaged_frames(data, items):
    pieces = []
    for packet in items:
        assume(packet.ByteSize() <= MAX_PACKET_BYTES)
        pieces.append(_damage(data, encode_frame(packet)))
    pieces.append(data.draw(_garbage))
    stream = b"".join(pieces)
    chunk = data.draw(st.integers(1, 64))
    decoder = FrameDecoder()
    out = []
    for start in range(0, len(stream), chunk):
        out += decoder.feed(stream[start : start + chunk])
    assert decoder.counters.rx_packets == len(out)
    assert decoder.counters.frames == _counts_from_segments(stream)


@fuzz_settings
@given(packet=packets)
def test_every_valid_packet_round_trips(packet):
    assume(packet.ByteSize() <= MAX_PACKET_BYTES)
    wire = encode_frame(packet)
    assert len(wire) <= pb.MAX_FRAME_BYTES
    assert wire.count(0) == 1 and wire.endswith(b"\x00")
    assert FrameDecoder().feed(wire) == [packet]


@fuzz_settings
@given(
    first=packets,
    second=packets,
    before=_garbage,
    between=_garbage,
    after=_garbage,
    cuts=st.lists(st.integers(0, 1000), max_size=30),
)
def test_packets_survive_arbitrary_splits_and_surrounding_garbage(
    first, second, before, between, after, cuts
):
    assume(first.ByteSize() <= MAX_PACKET_BYTES and second.ByteSize() <= MAX_PACKET_BYTES)
    # Garbage is closed by a 0x00 (as a sender's leading delimiter would), so it costs at
    # most its own "frame" and never the packets.
    stream = before + b"\x00" + encode_frame(first) + between + b"\x00" + encode_frame(second) + after
    decoder = FrameDecoder()
    out = []
    previous = 0
    for cut in sorted(set(c for c in cuts if c <= len(stream))) + [len(stream)]:
        out += decoder.feed(stream[previous:cut])
        previous = cut
    # Random garbage passing COBS, header and a 32-bit CRC is practically impossible:
    assert out == [first, second]
    assert decoder.counters.frames == _counts_from_segments(stream)
