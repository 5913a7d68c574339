"""The rig reads firmware parameter names and ids from the simulated MCU (oibar_sim_mcu
--list-params), not from a copy: the table, what a scenario may name, and clear errors."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from oibar_hil.rig.fw_params import FirmwareParamsError, firmware_params, param_ids, parse_table
from oibar_hil.rig.scenario import Scenario

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
    """`--mcu` reaches the name check of a scenario file (the rig's CLI) and of a fault-matrix
    cell, as it does a campaign mission's: with no build at the default path, the given MCU's
    table is read (a campaign from a worktree without one lost mission 193 to this)."""
    from oibar_hil.rig.matrix import cell_scenario, expectation
    from oibar_hil.rig.scenario import load_scenario

    monkeypatch.setenv("OIBAR_SIM_MCU", str(tmp_path / "no_build_here"))
    path = tmp_path / "attack.yaml"
    path.write_text("faults:\n  - {type: param_attack, at_s: 1.0, values: {debounce_ms: 1}}\n")
    with pytest.raises(FirmwareParamsError):
        load_scenario(path)
    assert load_scenario(path, sim_mcu_path).faults[0].type == "param_attack"
    exp = expectation("param_attack", "hard_docked")
    assert not isinstance(exp, str)
    with pytest.raises(FirmwareParamsError):
        cell_scenario("param_attack", "hard_docked", exp)
    assert (
        cell_scenario("param_attack", "hard_docked", exp, mcu_path=sim_mcu_path).faults[0].type
        == "param_attack"
    )


def test_a_scenario_naming_a_parameter_the_firmware_lacks_is_refused(sim_mcu_path, monkeypatch):
    monkeypatch.setenv("OIBAR_SIM_MCU", str(sim_mcu_path))
    ok = Scenario.from_dict({"firmware_params": {"nav_max_age_ms": 300}})
    assert ok.firmware_params == {"nav_max_age_ms": 300}
    with pytest.raises(ValueError, match=r"unknown firmware parameter.*nav_max_age_s") as e:
        Scenario.from_dict({"firmware_params": {"nav_max_age_s": 0.3}})
    assert "nav_max_age_ms" in str(e.value)  # the firmware's names are listed
    with pytest.raises(ValueError, match=r"unknown firmware parameter.*overpressure_bar"):
        Scenario.from_dict(
            {"faults": [{"type": "param_attack", "at_s": 1.0, "values": {"overpressure_bar": 30}}]}
        )
    assert param_ids(["debounce_ms", "fill_stall_ms"], sim_mcu_path) == {
        "debounce_ms": 6,
        "fill_stall_ms": 37,
    }


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
