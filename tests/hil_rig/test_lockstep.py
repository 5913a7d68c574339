"""The lockstep contract: frames in order, lost or repeated exchanges refused, outputs and
step pulses accounted, the pty carrying the link, the watchdog resetting the MCU."""

import re
from pathlib import Path

import numpy as np
import pytest

from oibar import pb
from oibar.link.session import LinkSession
from oibar_hil.rig import lockstep as ls
from oibar_hil.rig.lockstep import DI, LockstepError, SimMcu
from oibar_hil.rig.wire import Wire

# At home the latch switch's NC contact is closed (a changeover pair: exactly one of two).
AT_HOME = (
    (1 << DI.index("LATCH_HOME")) | (1 << DI.index("PLANE_RETRACTED")) | (1 << DI.index("LATCH_NOT_ENGAGED"))
)
ADC_OK = [410 + 2400, 410 + 330, 410 + 1100, 0, 0]


@pytest.fixture
def mcu(sim_mcu_path, tmp_path):
    with SimMcu(sim_mcu_path, stderr_path=tmp_path / "mcu.err") as m:
        yield m


def test_reply_echoes_frame_and_time_advances(mcu):
    r = mcu.exchange(10, AT_HOME, ADC_OK)
    assert r.frame == 1 and r.status == 0 and r.sim_time_ms == 10 and r.uptime_ms == 10
    for _ in range(20):
        r = mcu.exchange(10, AT_HOME, ADC_OK)
    assert r.sim_time_ms == 210
    assert pb.enum_name(pb.State, r.app_state) == "STATE_IDLE"  # boot settled at 100 ms
    assert r.do_bits == 0 and r.watchdog_kicks > 0


def test_repeated_frame_is_refused_and_runs_nothing(mcu):
    mcu.exchange(10, AT_HOME, ADC_OK)
    r = mcu.send_raw(ls.encode_plant(1, 10, AT_HOME, ADC_OK))  # frame 1 again
    assert ls.STATUS_NAMES[r.status] == "ERR_FRAME" and r.expected_frame == 2
    assert r.sim_time_ms == 10  # nothing ran


def test_lost_frame_is_refused(mcu):
    mcu.exchange(10, AT_HOME, ADC_OK)
    r = mcu.send_raw(ls.encode_plant(3, 10, AT_HOME, ADC_OK))  # frame 2 never arrived
    assert ls.STATUS_NAMES[r.status] == "ERR_FRAME" and r.expected_frame == 2
    # The plant's own wrapper turns such a refusal into an error.
    mcu.frame = 2
    with pytest.raises(LockstepError, match="ERR_FRAME"):
        mcu.exchange(10, AT_HOME, ADC_OK)


def test_bad_magic_and_advance_are_refused(mcu):
    r = mcu.send_raw(ls.encode_plant(1, 10, AT_HOME, ADC_OK, magic=0x12345678))
    assert ls.STATUS_NAMES[r.status] == "ERR_MAGIC"
    r = mcu.send_raw(ls.encode_plant(1, ls.MAX_ADVANCE_MS + 1, AT_HOME, ADC_OK))
    assert ls.STATUS_NAMES[r.status] == "ERR_ADVANCE"
    assert mcu.exchange(5, AT_HOME, ADC_OK).sim_time_ms == 5  # frame 1 still expected


def test_step_count_mismatch_is_detected(mcu):
    mcu.exchange(10, AT_HOME, ADC_OK)
    mcu.steps_seen += 1  # as if the plant had received a pulse the MCU never sent
    with pytest.raises(LockstepError, match="step pulses"):
        mcu.exchange(10, AT_HOME, ADC_OK)


def test_host_session_over_the_pty_on_simulated_time(mcu):
    """Handshake and a command through the pty, the session stepped on simulated time."""
    wire = Wire(np.random.default_rng(0))
    s = LinkSession(wire.host_end, host_version="test")
    t, req = 0.0, None
    for _ in range(100):  # 1 s
        data = wire.take_to_mcu()
        if data:
            mcu.write_uart(data)
        r = mcu.exchange(10, AT_HOME, ADC_OK, uart_rx_bytes=len(data))
        t += 0.01
        wire.deliver_to_host(mcu.read_uart(r.uart_tx_bytes))
        s.step(t)
        if s.link_up and req is None and not s.busy:
            req = s.command(pb.CMD_NOOP, now_s=t)
    assert req is not None and req.accepted and req.error is None
    assert s.telemetry is not None and s.telemetry.host_link_alive
    assert s.handshake_info.reset_cause == pb.RESET_POWER_ON


def _board_watchdog_ms() -> int:
    """HAL_WATCHDOG_TIMEOUT_MS (firmware/hal/include/oibar/hal.h): the board's number."""
    hal_h = Path(__file__).resolve().parents[2] / "firmware" / "hal" / "include" / "oibar" / "hal.h"
    m = re.search(r"#define\s+HAL_WATCHDOG_TIMEOUT_MS\s+(\d+)u", hal_h.read_text(encoding="utf-8"))
    assert m, "HAL_WATCHDOG_TIMEOUT_MS not in oibar/hal.h"
    return int(m.group(1))


def test_hung_main_loop_trips_the_watchdog(mcu):
    # The simulated MCU's watchdog (the fixture passes no --watchdog-ms) is the board's.
    wdg_ms = _board_watchdog_ms()
    assert wdg_ms == 250
    r = mcu.exchange(50, AT_HOME, ADC_OK)
    kicks = r.watchdog_kicks
    for _ in range(4):  # hung for wdg_ms - 50: not yet expired (an exchange advances <= 100 ms)
        r = mcu.exchange((wdg_ms - 50) // 4, AT_HOME, ADC_OK, flags=ls.FLAG_HANG_MAIN_LOOP)
    assert r.watchdog_kicks == kicks and r.resets == 0
    r = mcu.exchange(60, AT_HOME, ADC_OK)
    assert r.resets == 1 and ls.RESET_CAUSES[r.reset_cause] == "WATCHDOG"
    assert r.uptime_ms < 60 and r.do_bits == 0
    r = mcu.exchange(100, AT_HOME, ADC_OK)
    assert pb.enum_name(pb.State, r.app_state) == "STATE_FAULT"
    assert r.fault_flags >> (pb.FAULT_WATCHDOG_RESET - 1) & 1
