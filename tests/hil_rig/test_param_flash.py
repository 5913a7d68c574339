"""Parameter persistence on the simulated MCU (issue 59, item 3): a parameter set and saved
over the link (CMD_SAVE_PARAMS) comes back after a power cycle (a new process on the same
flash image, ``--flash-image``); without an image every process starts from the defaults."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from oibar import pb
from oibar.link.session import LinkSession
from oibar_hil.rig.lockstep import DI, SimMcu
from oibar_hil.rig.wire import Wire

AT_HOME = (
    (1 << DI.index("LATCH_HOME")) | (1 << DI.index("PLANE_RETRACTED")) | (1 << DI.index("LATCH_NOT_ENGAGED"))
)
ADC_OK = [410 + 2400, 410 + 330, 410 + 1100, 0, 0]
NAV_MAX_AGE_MS = 5  # parameter id of nav_max_age_ms (no cross rule ties it)


def _session_run(mcu: SimMcu, steps: list) -> list:
    """Step the link on simulated time; run each request of ``steps`` (a callable taking the
    session and the time) once the previous one finished. Returns the finished requests."""
    wire = Wire(np.random.default_rng(0))
    s = LinkSession(wire.host_end, host_version="test")
    t, done, req = 0.0, [], None
    for _ in range(600):  # 6 s simulated
        data = wire.take_to_mcu()
        if data:
            mcu.write_uart(data)
        r = mcu.exchange(10, AT_HOME, ADC_OK, uart_rx_bytes=len(data))
        t += 0.01
        wire.deliver_to_host(mcu.read_uart(r.uart_tx_bytes))
        s.step(t)
        if req is not None and not s.busy:
            done.append(req)
            req = None
        if s.link_up and req is None and not s.busy and len(done) < len(steps):
            req = steps[len(done)](s, t)
        if len(done) == len(steps):
            return done
    raise AssertionError(f"only {len(done)} of {len(steps)} requests finished")


def _get(s: LinkSession, t: float):
    return s.param_get(NAV_MAX_AGE_MS, now_s=t)


def test_saved_parameter_survives_a_power_cycle(sim_mcu_path: Path, tmp_path: Path) -> None:
    image = tmp_path / "params_flash.bin"
    with SimMcu(sim_mcu_path, stderr_path=tmp_path / "mcu1.err", flash_image=image) as mcu:
        set_, save = _session_run(
            mcu,
            [
                lambda s, t: s.param_set(NAV_MAX_AGE_MS, 1234.0, now_s=t),
                lambda s, t: s.command(pb.CMD_SAVE_PARAMS, now_s=t),
            ],
        )
        assert set_.accepted and save.accepted, (set_.error, save.error)
    assert image.stat().st_size == 2 * 16384
    with SimMcu(sim_mcu_path, stderr_path=tmp_path / "mcu2.err", flash_image=image) as mcu:
        (got,) = _session_run(mcu, [_get])
        assert got.accepted and got.response.value == 1234.0


def test_without_an_image_every_process_starts_from_the_defaults(sim_mcu_path: Path, tmp_path: Path) -> None:
    with SimMcu(sim_mcu_path, stderr_path=tmp_path / "mcu1.err") as mcu:
        _session_run(
            mcu,
            [
                lambda s, t: s.param_set(NAV_MAX_AGE_MS, 1234.0, now_s=t),
                lambda s, t: s.command(pb.CMD_SAVE_PARAMS, now_s=t),
            ],
        )
    with SimMcu(sim_mcu_path, stderr_path=tmp_path / "mcu2.err") as mcu:
        (got,) = _session_run(mcu, [_get])
        assert got.response.value == got.response.default_value == 500.0
