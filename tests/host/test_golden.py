"""Golden link frames: the Python side against the committed bytes.

host_to_mcu frames are *written* here (encode and compare with the committed bytes, which the C
decoder reads in tests/firmware/test_golden.c); mcu_to_host frames, written by the C encoder, are
*read* here and must decode to exactly the fields described in tests/golden/vectors.json.
Set OIBAR_GOLDEN_WRITE=1 to rewrite the host_to_mcu files on purpose (`make golden`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from google.protobuf import json_format

from oibar.link.framing import FrameDecoder, encode_frame
from oibar.pb import oibar_pb2 as pb

GOLDEN = Path(__file__).resolve().parents[1] / "golden"
VECTORS = json.loads((GOLDEN / "vectors.json").read_text())["vectors"]
WRITE = os.environ.get("OIBAR_GOLDEN_WRITE") == "1"


def _by_direction(direction: str) -> list[dict]:
    return [v for v in VECTORS if v["direction"] == direction]


def _hex_path(vec: dict) -> Path:
    return GOLDEN / vec["direction"] / f"{vec['name']}.hex"


def _packet(vec: dict) -> pb.Packet:
    return json_format.ParseDict(vec["packet"], pb.Packet())


def test_every_vector_has_its_file_and_no_file_is_orphaned():
    names = {(v["direction"], v["name"]) for v in VECTORS}
    assert len(names) == len(VECTORS), "duplicate vector names"
    files = {(p.parent.name, p.stem) for p in GOLDEN.glob("*/*.hex")}
    assert files == names
    assert all(v["description"].strip() for v in VECTORS)


@pytest.mark.parametrize("vec", _by_direction("host_to_mcu"), ids=lambda v: v["name"])
def test_python_encoder_writes_the_golden_host_to_mcu_frame(vec):
    wire = encode_frame(_packet(vec))
    path = _hex_path(vec)
    if WRITE:
        path.parent.mkdir(exist_ok=True)
        path.write_text(wire.hex() + "\n")
    assert wire.hex() == path.read_text().strip(), f"Python encoder drifted for {vec['name']}"


@pytest.mark.parametrize("vec", _by_direction("mcu_to_host"), ids=lambda v: v["name"])
def test_python_decoder_reads_the_golden_mcu_to_host_frame(vec):
    wire = bytes.fromhex(_hex_path(vec).read_text().strip())
    assert wire.endswith(b"\x00") and wire.count(0) == 1
    decoder = FrameDecoder()
    packets = decoder.feed(wire)
    assert len(packets) == 1, f"{vec['name']}: decoder counters {decoder.counters}"
    got = json_format.MessageToDict(packets[0], preserving_proto_field_name=True)
    assert got == vec["packet"]
    # Byte by byte, as a UART would deliver it, gives the same packet.
    decoder = FrameDecoder()
    one_by_one = [p for b in wire for p in decoder.feed(bytes([b]))]
    assert one_by_one == packets


@pytest.mark.parametrize("vec", _by_direction("mcu_to_host"), ids=lambda v: v["name"])
def test_python_encoder_agrees_with_the_c_encoder(vec):
    # Same packet, same bytes: both encoders emit fields in number order, so any difference is
    # a framing or encoding drift on one side.
    wire = bytes.fromhex(_hex_path(vec).read_text().strip())
    assert encode_frame(_packet(vec)) == wire
