"""Every scenario in hil/scenarios: the short nominal, one per fault, and the 10 m nominal
mission of `make demo`. Each must reach its declared outcome and pass every check."""

from pathlib import Path

import pytest

from oibar_hil.rig.cli import SCENARIO_DIR, run_scenario
from oibar_hil.rig.runner import Rig
from oibar_hil.rig.scenario import load_scenario

SCENARIOS = sorted(SCENARIO_DIR.glob("*.yaml"))


def test_there_is_one_scenario_per_fault_type():
    from oibar_hil.rig.faults import FAULT_TYPES

    covered = {f.type for p in SCENARIOS for f in load_scenario(p).faults}
    assert covered == set(FAULT_TYPES)


@pytest.mark.parametrize("path", SCENARIOS, ids=[p.stem for p in SCENARIOS])
def test_scenario_meets_its_declared_outcome(path: Path, sim_mcu_path, tmp_path):
    with_report = path.stem == "nominal_short"
    r = run_scenario(path, out_root=tmp_path if with_report else None, mcu_path=sim_mcu_path)
    failed = [f"{c.id}: {c.text} (measured {c.measured})" for c in r.checks if c.ok is False]
    assert not failed, f"{path.stem}: " + "; ".join(failed)
    assert r.outcome == r.scenario.expect["outcome"]
    assert r.speed_factor > 5.0  # the 20x figure is measured on an idle machine (docs/hil.md)
    if with_report:
        assert r.report_path.exists() and (r.report_path.parent / "fluid.png").exists()


def test_run_progress_in_a_log_is_plain_lines_not_carriage_returns(sim_mcu_path, capsys):
    # `make demo > log` used to get a carriage-return progress line per simulated second (tqdm
    # writes "\r" whatever the stream); in a log it is now a plain line every few seconds.
    import dataclasses

    sc = load_scenario(SCENARIO_DIR / "nominal_short.yaml")
    sc = dataclasses.replace(sc, rig=dataclasses.replace(sc.rig, max_time_s=4.0))
    Rig(sc, mcu_path=sim_mcu_path, progress=True).run()
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("nominal_short:")]
    assert len(lines) >= 2, err  # the start and the end (and one per 5 s of wall time between)
    assert lines[0].startswith("nominal_short: 0/4 sim s") and "/4 sim s" in lines[-1]
