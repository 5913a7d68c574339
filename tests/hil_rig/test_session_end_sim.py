"""The host's planned end of a session (CMD_END_SESSION, issue 60 item 4) against the real
firmware (the simulated MCU in lockstep, the Python link session over its pty): the MCU accepts
it, disarms, and the silence that follows is no FAULT_HOST_LINK_LOSS; the same silence without
it still faults. The per-state semantics are in tests/firmware/test_app_session_end.c."""

import numpy as np
import pytest

from oibar import pb
from oibar.link.session import LinkSession
from oibar_hil.rig.lockstep import DI, SimMcu
from oibar_hil.rig.wire import Wire

AT_HOME = (
    (1 << DI.index("LATCH_HOME")) | (1 << DI.index("PLANE_RETRACTED")) | (1 << DI.index("LATCH_NOT_ENGAGED"))
)
ADC_OK = [410 + 2400, 410 + 330, 410 + 1100, 0, 0]
LINK_LOSS_BIT = 1 << (pb.FAULT_HOST_LINK_LOSS - 1)


@pytest.fixture
def mcu(sim_mcu_path, tmp_path):
    with SimMcu(sim_mcu_path, stderr_path=tmp_path / "mcu.err") as m:
        yield m


def _run(mcu, wire, session, t, seconds, host_alive=True):
    """Step MCU and host together for ``seconds``; a dead host neither sends nor steps."""
    r = None
    for _ in range(int(round(seconds / 0.01))):
        data = wire.take_to_mcu() if host_alive else b""
        if data:
            mcu.write_uart(data)
        r = mcu.exchange(10, AT_HOME, ADC_OK, uart_rx_bytes=len(data))
        t += 0.01
        rx = mcu.read_uart(r.uart_tx_bytes)
        if host_alive:
            wire.deliver_to_host(rx)
            session.step(t)
    return t, r


def _command(mcu, wire, session, t, opcode):
    req = session.command(opcode, now_s=t)
    for _ in range(100):
        t, _ = _run(mcu, wire, session, t, 0.01)
        if req.done:
            break
    assert req.done and req.error is None
    return t, req


def _armed_session(mcu):
    wire = Wire(np.random.default_rng(0))
    s = LinkSession(wire.host_end, host_version="test")
    t, _ = _run(mcu, wire, s, 0.0, 0.5)
    assert s.link_up
    t, req = _command(mcu, wire, s, t, pb.CMD_APPROACH_ARM)
    assert req.accepted and req.response.state == pb.STATE_APPROACH_READY
    return wire, s, t


def test_planned_end_then_silence_is_no_fault_on_the_real_firmware(mcu):
    wire, s, t = _armed_session(mcu)
    t, req = _command(mcu, wire, s, t, pb.CMD_END_SESSION)
    assert req.accepted and req.response.state == pb.STATE_IDLE
    t, r = _run(mcu, wire, s, t, 2.5, host_alive=False)  # the host closed its port
    assert pb.enum_name(pb.State, r.app_state) == "STATE_IDLE"


def test_silence_without_a_planned_end_still_faults_on_the_real_firmware(mcu):
    wire, s, t = _armed_session(mcu)
    t, r = _run(mcu, wire, s, t, 2.5, host_alive=False)
    assert pb.enum_name(pb.State, r.app_state) == "STATE_FAULT"
