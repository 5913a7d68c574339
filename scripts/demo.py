#!/usr/bin/env python3
"""OIBAR link demo: the host's link client against the firmware's link layer over a pty.

Starts the firmware link peer (C, built for this machine), connects the Python client to its
pseudo-terminal, and walks through the link contract: handshake, telemetry, commands accepted and
refused, parameters, and the MCU's reaction when the host's heartbeats stop.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from oibar.link.client import LinkClient
from oibar.pb import oibar_pb2 as pb


def start_peer(peer: Path) -> tuple[subprocess.Popen, str]:
    if not peer.exists():
        sys.exit(f"demo: firmware link peer not found at {peer} (run `make firmware-host`)")
    proc = subprocess.Popen([str(peer), "--build-id", "demo", "--log"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline().strip()
    if not line.startswith("PTY "):
        proc.kill()
        sys.exit(f"demo: unexpected first line from the peer: {line!r}")
    return proc, line.split(" ", 1)[1]


def name(enum, value: int) -> str:
    return enum.Name(value)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--peer", type=Path, required=True, help="path to oibar_link_peer")
    args = ap.parse_args()

    proc, pty = start_peer(args.peer)
    events: list = []
    try:
        print(f"1. firmware link peer running, serial port {pty}")
        client = LinkClient(pty, host_version="oibar-demo", on_event=events.append)
        info = client.connect()
        print(f"2. handshake: firmware {info.firmware_version}, build {info.build_id}, "
              f"protocol v{info.protocol_version}, reset cause {info.reset_cause}")
        time.sleep(0.5)
        tm = client.telemetry
        print(f"3. telemetry: state {name(pb.State, tm.state)}, uptime {tm.uptime_ms} ms, "
              f"rx packets {tm.link.rx_packets}, host link alive {tm.host_link_alive}")
        for opcode in (pb.CMD_NOOP, pb.CMD_START_TRANSFER):
            res = client.command(opcode, target_pressure_kpa=1200.0)
            verdict = "accepted" if res.accepted else f"refused ({res.reason})"
            print(f"4. command {name(pb.CommandOpcode, opcode)}: {verdict}, state {res.state}")
        pv = client.param_get(3)
        print(f"5. parameter {pv.param_id} {pv.name} = {pv.value:g} {pv.unit} "
              f"[{pv.min:g} .. {pv.max:g}]")
        pv = client.param_set(3, 50.0)
        print(f"   set it to 50: {pv.reason} (bounds hold; value still {client.param_get(3).value:g})")
        print("6. host stops its heartbeats (simulated host crash) ...")
        client.close()
        time.sleep(1.5)
        client = LinkClient(pty, host_version="oibar-demo", on_event=events.append)
        client.connect()
        time.sleep(0.3)
        losses = client.telemetry.link.link_losses if client.telemetry else "?"
        print(f"   after 1 s without heartbeats the MCU declared the link lost "
              f"(link losses counted by the MCU: {losses}); a new handshake re-opened it")
        stats = client.statistics
        client.close()
        print(f"7. link statistics (host side): {stats}")
        print("demo: done")
        return 0
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=2)
        except subprocess.TimeoutExpired:
            proc.kill()


if __name__ == "__main__":
    sys.exit(main())
