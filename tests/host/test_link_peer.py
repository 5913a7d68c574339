"""Interop: the Python link client against the firmware's C link layer over a pseudo-terminal.

The peer (`oibar_link_peer`, built by `make firmware-host`) runs the real C link code with a
minimal application (no mechanism: NOOP accepted, other commands NACK_NOT_SUPPORTED, the link's
own timing parameters in its table). These tests exercise the contract end to end, across the
two implementations, in real time.
"""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import pytest

from oibar.link import LinkClient, LinkDown, ProtocolVersionError
from oibar.pb import oibar_pb2 as pb

ROOT = Path(__file__).resolve().parents[2]
PEER = Path(os.environ.get("OIBAR_FW_BUILD", ROOT / "build" / "fw-host")) / "link" / "oibar_link_peer"


class Peer:
    def __init__(self, *args: str) -> None:
        if not PEER.exists():
            pytest.fail(f"{PEER} not built: run `make firmware-host` (make test does it)")
        self.proc = subprocess.Popen(
            [str(PEER), *args], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
        line = self.proc.stdout.readline().strip()
        assert line.startswith("PTY "), f"unexpected peer banner {line!r}"
        self.pty = line.split(" ", 1)[1]

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=3)
        except subprocess.TimeoutExpired:
            self.proc.kill()


@pytest.fixture
def peer_factory():
    peers: list[Peer] = []

    def make(*args: str) -> Peer:
        peers.append(Peer(*args))
        return peers[-1]

    yield make
    for p in peers:
        p.stop()


def wait_until(predicate, timeout_s: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


def test_handshake_reports_build_and_reset_cause(peer_factory):
    peer = peer_factory("--build-id", "interop-42")
    with LinkClient(peer.pty) as link:
        info = link.connect()
        assert info.protocol_version == pb.PROTOCOL_VERSION
        assert info.build_id == "interop-42"
        assert info.firmware_version
        assert info.reset_cause.startswith("RESET_")


def test_telemetry_and_heartbeats_flow_at_the_contract_rate(peer_factory):
    peer = peer_factory()
    with LinkClient(peer.pty) as link:
        link.connect()
        assert wait_until(lambda: link.telemetry is not None)
        time.sleep(1.0)
        tm = link.telemetry
        assert tm.state == pb.STATE_IDLE
        assert tm.host_link_alive
        assert tm.link.rx_packets >= 3  # handshake + heartbeats, as counted by the C side
        assert 5.0 <= link.telemetry_rate_hz <= 15.0  # telemetry_period 100 ms
        stats = link.statistics
        assert stats.rx_crc_errors == stats.rx_framing_errors == stats.rx_decode_errors == 0
        assert stats.lost_peer_packets == 0


def test_commands_accepted_and_refused_with_reasons(peer_factory):
    peer = peer_factory()
    with LinkClient(peer.pty) as link:
        link.connect()
        ok = link.command("NOOP")
        assert ok.accepted and ok.reason == "NACK_NONE" and ok.state == "STATE_IDLE"
        refused = link.command("START_TRANSFER", target_pressure_kpa=1200.0)
        assert not refused.accepted and refused.reason == "NACK_NOT_SUPPORTED"
        unknown = link.command(999)
        assert not unknown.accepted and unknown.reason == "NACK_UNKNOWN_OPCODE"


def test_parameters_round_trip_with_bounds(peer_factory):
    peer = peer_factory()
    with LinkClient(peer.pty) as link:
        link.connect()
        pv = link.param_get(3)
        assert pv.ok and pv.name == "link_timeout_ms" and pv.unit == "ms"
        assert pv.min <= pv.value <= pv.max
        assert link.param_set(3, 2000.0).value == 2000.0
        assert link.param_get(3).value == 2000.0
        refused = link.param_set(3, pv.max * 10)
        assert refused.reason == "NACK_PARAM_OUT_OF_BOUNDS"
        assert link.param_get(3).value == 2000.0  # refusal changed nothing
        assert link.param_get(999).reason == "NACK_UNKNOWN_PARAM"


def test_protocol_version_mismatch_is_a_clear_error(peer_factory):
    peer = peer_factory("--protocol-version", "3")
    link = LinkClient(peer.pty)
    with pytest.raises(ProtocolVersionError) as err:
        link.connect()
    link.close()
    assert str(pb.PROTOCOL_VERSION) in str(err.value) and "3" in str(err.value)


def test_host_detects_a_silent_mcu(peer_factory):
    peer = peer_factory("--silent-after-ms", "800")
    states: list[bool] = []
    with LinkClient(peer.pty, on_link_state=states.append) as link:
        link.connect()
        assert link.link_alive
        assert wait_until(lambda: not link.link_alive, timeout_s=4.0)
        with pytest.raises(LinkDown):
            link.command("NOOP")
    assert False in states


def test_mcu_declares_link_loss_when_host_heartbeats_stop(peer_factory):
    peer = peer_factory()
    first = LinkClient(peer.pty)
    first.connect()
    first.close()  # the host dies: no more heartbeats
    time.sleep(1.6)  # > link_timeout 1 s on the MCU
    with LinkClient(peer.pty) as link:
        link.connect()
        assert wait_until(lambda: link.telemetry is not None)
        assert link.telemetry.link.link_losses == 1
        assert link.command("NOOP").accepted  # the new handshake re-opened the session
