"""The rig reads firmware parameter names and ids from the simulated MCU (oibar_sim_mcu
--list-params), not from a copy: the table, what a scenario may name, and clear errors."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from oibar_hil.rig.fw_params import (
    FirmwareParamsError,
    UnknownFirmwareParam,
    firmware_params,
    param_ids,
    parse_table,
)
from oibar_hil.rig.runner import Rig
from oibar_hil.rig.scenario import Scenario, load_scenario

ROOT = Path(__file__).resolve().parents[2]


def test_the_mcu_prints_its_parameter_table(sim_mcu_path):
    table = firmware_params(sim_mcu_path)
    ids = sorted(p.id for p in table.values())
    assert ids == list(range(1, len(ids) + 1)) and len(ids) >= 37  # ids are append-only, from 1
    p = table["fill_stall_ms"]
    assert (p.unit, p.default, p.min, p.max, p.integer) == ("ms", 3000.0, 500.0, 30000.0, True)
    assert table["nav_min_confidence"].integer is False
    # every name the firmware's source declares, and no other (params.c: P_INT / P_REAL rows)
    src = (ROOT / "firmware/app/src/params.c").read_text()
    declared = {
        line.split('"')[1] for line in src.splitlines() if line.strip().startswith(("P_INT(", "P_REAL("))
    }
    assert declared == set(table)


def test_scenario_files_and_matrix_cells_check_names_against_the_mcu_that_flies(
    sim_mcu_path, tmp_path, monkeypatch
):
    """The rig checks a scenario's parameter names against the MCU it flies (`--mcu`), not the
    default path: with no build there, a scenario file and a fault-matrix cell load (the loaders
    check only the shape) and fly with the given MCU (a campaign from a worktree without a build
    lost mission 193 to a loader's check against the default path)."""
    from oibar_hil.rig.matrix import cell_scenario, expectation

    monkeypatch.setenv("OIBAR_SIM_MCU", str(tmp_path / "no_build_here"))
    path = tmp_path / "attack.yaml"
    path.write_text("faults:\n  - {type: param_attack, at_s: 1.0, values: {debounce_ms: 1}}\n")
    sc = load_scenario(path)
    exp = expectation("param_attack", "hard_docked")
    assert not isinstance(exp, str)
    cell = cell_scenario("param_attack", "hard_docked", exp)
    for scenario in (sc, cell):
        assert scenario.faults[0].type == "param_attack" and scenario.param_names()
        with pytest.raises(FirmwareParamsError):  # the default MCU is read only when no other is given
            Rig(scenario)
        Rig(scenario, mcu_path=sim_mcu_path)


def test_a_scenario_naming_a_parameter_the_firmware_lacks_is_refused_before_it_flies(sim_mcu_path, tmp_path):
    ok = Scenario.from_dict({"firmware_params": {"nav_max_age_ms": 300}})
    assert ok.firmware_params == {"nav_max_age_ms": 300}
    Rig(ok, mcu_path=sim_mcu_path)
    bad = Scenario.from_dict({"firmware_params": {"nav_max_age_s": 0.3}})
    with pytest.raises(UnknownFirmwareParam, match=r"unknown firmware parameter.*nav_max_age_s") as e:
        Rig(bad, mcu_path=sim_mcu_path)
    assert "nav_max_age_ms" in str(e.value)  # the firmware's names are listed
    attack = Scenario.from_dict(
        {"faults": [{"type": "param_attack", "at_s": 1.0, "values": {"overpressure_bar": 30}}]}
    )
    assert attack.param_names() == ["overpressure_bar"]
    with pytest.raises(UnknownFirmwareParam, match=r"unknown firmware parameter.*overpressure_bar"):
        Rig(attack, mcu_path=sim_mcu_path)
    assert param_ids(["debounce_ms", "fill_stall_ms"], sim_mcu_path) == {
        "debounce_ms": 6,
        "fill_stall_ms": 37,
    }


def test_the_rig_and_sim_mcu_clis_refuse_an_unknown_name_with_a_clear_error(sim_mcu_path, tmp_path, capsys):
    """Both command lines say which name and which scenario, exit 2, and fly nothing."""
    from oibar_hil import sim_mcu
    from oibar_hil.rig import cli

    path = tmp_path / "typo.yaml"
    path.write_text("firmware_params: {debounce_s: 0.01}\n")
    out = tmp_path / "reports"
    assert cli.main(["--mcu", str(sim_mcu_path), "--out", str(out), "--no-progress", "run", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"scenario {path}" in err and "debounce_s" in err and "debounce_ms" in err
    assert not out.exists()
    assert sim_mcu.main(["--pty", "--mcu", str(sim_mcu_path), "--scenario", str(path)]) == sim_mcu.EXIT_ERROR
    err = capsys.readouterr().err
    assert err.startswith("sim-mcu: error: scenario") and "debounce_s" in err


def test_a_missing_or_old_mcu_is_a_clear_error(tmp_path):
    with pytest.raises(FirmwareParamsError, match="make firmware-host"):
        firmware_params(tmp_path / "nothing_here")
    old = tmp_path / "old_mcu"  # an MCU built before the flag: prints its usage, exits 2
    old.write_text("#!/bin/sh\necho 'usage: oibar_sim_mcu --lockstep-fd N' >&2\nexit 2\n")
    old.chmod(old.stat().st_mode | stat.S_IEXEC)
    with pytest.raises(FirmwareParamsError, match="exited 2.*make firmware-host"):
        firmware_params(old)


@pytest.mark.parametrize(
    "text,why",
    [
        ("", "empty"),
        ("1\tdebounce_ms\tms\t10\t1\t100\n", "7 tab-separated"),
        ("x\tdebounce_ms\tms\t10\t1\t100\t1\n", "line 1"),
        ("1\ta\tms\t1\t0\t2\t1\n1\tb\tms\t1\t0\t2\t1\n", "listed twice"),
    ],
)
def test_a_damaged_table_is_refused(text, why):
    with pytest.raises(FirmwareParamsError, match=why):
        parse_table(text)
