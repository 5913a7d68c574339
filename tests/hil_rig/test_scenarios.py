"""Every scenario in hil/scenarios: the short nominal, one per fault, and the 10 m nominal
mission of `make demo`. Each must reach its declared outcome and pass every check."""

from pathlib import Path

import numpy as np
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


def test_the_navigation_metrics_below_5_m_take_only_the_near_cycles():
    """Issue 15's closed-loop target is read below 5 m: the far cycles (larger errors that matter
    less) and the held ones stay out of those figures, and the whole-mission figures keep them."""
    from types import SimpleNamespace

    from oibar_hil.rig.runner import NEAR_RANGE_M, Rig

    def row(rng_m, lat_err_m, mis_est_deg, valid=True, off_axis_m=0.1):
        return {
            "t_s": 0.0,
            "valid": valid,
            "hold_reason": "" if valid else "no_fix",
            "range_true_m": rng_m,
            "true_x_m": 0.6 * off_axis_m,
            "true_y_m": -0.8 * off_axis_m,
            "range_est_m": rng_m,
            "lateral_err_m": lat_err_m,
            "misalign_true_deg": 2.5,
            "misalign_est_deg": mis_est_deg,
        }

    far = [row(8.0, 0.30, 5.0) for _ in range(50)]
    near = [row(NEAR_RANGE_M * k / 21, 0.01 * k, 2.5 + 0.01 * k) for k in range(1, 21)]
    far = far + [row(8.0, 0.30, 5.0, off_axis_m=1.5)]  # far out the path may be wide
    held = [row(2.0, 9.0, 90.0, valid=False, off_axis_m=0.4)]  # a held cycle's path counts: it is the truth
    inside = [row(-0.05, 0.5, 2.5, off_axis_m=0.7)]  # probe inside the drogue: not an approach cycle
    m = Rig.nav_metrics(SimpleNamespace(nav_log=far + near + held + inside, nav=SimpleNamespace(name="cnn")))
    lat = 0.01 * np.arange(1, 21)
    assert m["nav_lateral_err_m_max_below_5m"] == pytest.approx(0.20)
    assert m["nav_lateral_err_m_p95_below_5m"] == pytest.approx(np.percentile(lat, 95))
    assert m["nav_misalign_err_deg_p95_below_5m"] == pytest.approx(np.percentile(0.01 * np.arange(1, 21), 95))
    assert m["nav_lateral_err_m_p99"] > 0.29  # the whole mission's figure still sees the far cycles
    assert m["nav_hold_cycles"] == 1
    assert m["approach_off_axis_m_max_below_5m"] == pytest.approx(0.4)


def test_the_rigs_json_says_which_scene_and_model_the_camera_flew(tmp_path, monkeypatch):
    """A judge reads the demo's JSON: it refuses a test sequence and pairs two models' flights only
    on one scene, so the JSON must say what was flown (and nothing for ground-truth navigation)."""
    import json
    import types

    import oibar_hil.rig.cli as cli

    seen = []

    def fake_run(sc, **kw):
        seen.append(kw["nav_options"])
        return types.SimpleNamespace(
            scenario=sc, outcome="completed", passed=True, sim_time_s=1.0, wall_time_s=1.0,
            speed_factor=1.0, metrics={"nav": kw["nav"]}, capture={}, checks=[], report_path=tmp_path,
        )  # fmt: skip

    monkeypatch.setattr(cli, "run_scenario", fake_run)
    monkeypatch.setattr(cli, "_print_nav", lambda r: None)
    monkeypatch.setattr(cli, "_print_checks", lambda r: None)
    monkeypatch.setattr(cli, "print_summary", lambda rs: None)
    out = tmp_path / "demo.json"
    scene, model = "models/scenes/val.json:va000", tmp_path / "m.onnx"
    assert cli.main(["--model", str(model), "--scene", scene, "--json", str(out), "demo"]) == 0
    (r,) = json.loads(out.read_text())
    assert (r["nav"], r["scene"], r["model"]) == ("cnn", scene, str(model))
    assert seen[-1] == {"model_path": model, "scene": scene}
    assert cli.main(["--nav", "truth", "--json", str(out), "demo"]) == 0
    (r,) = json.loads(out.read_text())
    assert (r["nav"], r["scene"], r["model"]) == ("truth", None, None)
