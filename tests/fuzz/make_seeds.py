#!/usr/bin/env python3
"""Write the seed corpora of the libFuzzer targets from the golden link frames.

frame/    every golden wire frame (both directions) as raw bytes, and all of them in one stream
dispatch/ record programs for fuzz_dispatch.c (see its header): each golden host->MCU packet after
          a handshake, and one walk through the nominal docking command sequence with the plant
          events that let it progress, so the fuzzer starts from deep states.
Both also get the committed, minimised corpus of the long campaigns (tests/fuzz/corpus.py).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import corpus  # tests/fuzz/corpus.py, beside this script

from oibar.link import cobs
from oibar.pb import oibar_pb2 as pb

GOLDEN = Path(__file__).resolve().parents[1] / "golden"
REC_PACKET, REC_TIME, REC_RAW, REC_PLANT = 0x00, 0x40, 0x80, 0xC0
PLANT_PROBE_IN = 0


def packet_bytes_of(wire: bytes) -> bytes:
    raw = cobs.decode(wire.rstrip(b"\x00"))
    return raw[1:-4]  # strip the header byte and the CRC


def rec_packet(payload: bytes) -> bytes:
    assert len(payload) < 256
    return bytes([REC_PACKET, len(payload)]) + payload


def rec_time(ms: int) -> bytes:
    out = b""
    while ms > 0:
        step = min(ms, 1024)
        out += bytes([REC_TIME, step // 4 - 1])
        ms -= step
    return out


def heartbeat(seq: int) -> bytes:
    p = pb.Packet(seq=seq)
    p.heartbeat.uptime_ms = seq
    return p.SerializeToString()


class Walk:
    """A record program with the host's heartbeats kept going (the MCU's link timeout is 1 s)."""

    def __init__(self, start: bytes) -> None:
        self.data = start
        self.seq = 100

    def packet(self, payload_of_seq) -> None:
        self.seq += 1
        self.data += rec_packet(payload_of_seq(self.seq))

    def wait(self, ms: int) -> None:
        while ms > 0:
            step = min(ms, 200)
            self.data += rec_time(step)
            self.packet(heartbeat)
            ms -= step


def command(seq: int, opcode: int, target_kpa: float = 0.0) -> bytes:
    p = pb.Packet(seq=seq)
    p.command.opcode = opcode
    if target_kpa:
        p.command.target_pressure_kpa = target_kpa
    return p.SerializeToString()


def nav(seq: int) -> bytes:
    p = pb.Packet(seq=seq)
    n = p.nav_update
    n.q_cam_target.w = 1.0
    n.range_m, n.closing_speed_mps, n.confidence = 0.05, 0.01, 0.99
    n.phase = pb.NAV_PHASE_SOFT_DOCK
    return p.SerializeToString()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    frame_dir, dispatch_dir = args.out / "frame", args.out / "dispatch"
    frame_dir.mkdir(parents=True, exist_ok=True)
    dispatch_dir.mkdir(parents=True, exist_ok=True)

    vectors = json.loads((GOLDEN / "vectors.json").read_text())["vectors"]
    wires = {
        v["name"]: bytes.fromhex((GOLDEN / v["direction"] / f"{v['name']}.hex").read_text()) for v in vectors
    }
    for name, wire in wires.items():
        (frame_dir / name).write_bytes(wire)
    (frame_dir / "all_in_one_stream").write_bytes(b"\x00garbage".join(wires.values()))

    hello = rec_packet(packet_bytes_of(wires["handshake_v2"])) + rec_time(20)
    for v in vectors:
        if v["direction"] == "host_to_mcu":
            (dispatch_dir / v["name"]).write_bytes(
                hello + rec_packet(packet_bytes_of(wires[v["name"]])) + rec_time(40)
            )

    walk = Walk(hello)
    for opcode, wait_ms in (
        (pb.CMD_APPROACH_ARM, 200),
        (None, 0),
        (pb.CMD_DOCK, 1500),
        (pb.CMD_HARD_DOCK, 5000),
        (pb.CMD_ARM_TRANSFER, 200),
        (pb.CMD_START_TRANSFER, 3000),
        (pb.CMD_STOP_TRANSFER, 200),
        (pb.CMD_SEPARATE, 6000),
    ):
        walk.packet(nav)
        if opcode is None:  # the probe enters the drogue
            walk.data += bytes([REC_PLANT, PLANT_PROBE_IN])
            walk.wait(300)
            continue
        target_kpa = 1200.0 if opcode == pb.CMD_START_TRANSFER else 0.0
        walk.packet(lambda seq, opcode=opcode, target_kpa=target_kpa: command(seq, opcode, target_kpa))
        walk.wait(wait_ms)
    (dispatch_dir / "nominal_walk").write_bytes(walk.data)

    try:
        counts = corpus.unpack(args.out)
    except corpus.CorpusError as exc:
        sys.exit(f"make_seeds: error: {exc}")
    print("make_seeds: committed corpus:", ", ".join(f"{k} {n} units" for k, n in counts.items()))


if __name__ == "__main__":
    main()
