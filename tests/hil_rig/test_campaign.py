"""Monte Carlo dispersion campaigns (issue 62, hil/oibar_hil/campaign): the draws, the bounds,
Clopper-Pearson, and a tiny campaign of short truth-navigation missions flown in one process
and on Ray with a worker killed mid-mission: same table, no mission lost, none twice."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from oibar_hil.campaign.dispersion import (
    INPUTS,
    ConfigError,
    draw_fault,
    draw_mission,
    load_config,
    parse_config,
    read_toml,
)
from oibar_hil.campaign.stats import missions_for_claim, rate
from oibar_hil.rig.matrix import expectation

ROOT = Path(__file__).resolve().parents[2]
DEFAULT = ROOT / "hil" / "campaigns" / "default.toml"
SHORT = ROOT / "hil" / "campaigns" / "short.toml"
TINY_MISSIONS = 3


# -- the dispersion model -------------------------------------------------------------------


def test_draws_are_reproducible_and_inside_their_stated_bounds():
    cfg = load_config(DEFAULT)
    assert cfg.inputs, "the default model disperses nothing"
    seen: dict[str, list[float]] = {n: [] for n in cfg.inputs}
    for i in range(200):
        a, b = draw_mission(cfg, i), draw_mission(cfg, i)
        assert a == b, f"mission {i} drew differently twice"
        for name, dist in cfg.inputs.items():
            v = a.values[name]
            lo, hi = dist.bounds
            assert lo <= v <= hi, f"mission {i}: {name} = {v} outside [{lo}, {hi}]"
            ilo, ihi = INPUTS[name].valid
            assert ilo <= v <= ihi
            if dist.kind == "choice":
                assert v in dist.values
            if INPUTS[name].integer:
                assert v == int(v)
            seen[name].append(v)
        for name in set(INPUTS) - set(cfg.inputs):
            assert a.values[name] == INPUTS[name].nominal  # not dispersed: the rig's nominal
    for name, dist in cfg.inputs.items():
        if dist.dispersed:  # a dispersed input does vary, and spreads over its range
            vals = np.array(seen[name])
            lo, hi = dist.bounds
            assert np.ptp(vals) > 0.3 * (hi - lo), f"{name} barely varies: {np.ptp(vals)} of {hi - lo}"
    # another mission, another seed: other draws
    assert draw_mission(cfg, 0).values != draw_mission(cfg, 1).values
    other = dataclasses.replace(cfg, seed=cfg.seed + 1)
    assert draw_mission(other, 0).values != draw_mission(cfg, 0).values


def test_an_input_draw_does_not_depend_on_the_other_inputs():
    data = read_toml(DEFAULT)
    full = parse_config(data)
    data["inputs"].pop("start_range_m")
    fewer = parse_config(data)
    for i in range(20):
        a, b = draw_mission(full, i), draw_mission(fewer, i)
        assert b.values["start_range_m"] == INPUTS["start_range_m"].nominal
        assert a.values["start_lateral_x_m"] == b.values["start_lateral_x_m"]
        assert (a.fault, a.fault_phase, a.rig_seed) == (b.fault, b.fault_phase, b.rig_seed)
    assert full.identity() != fewer.identity()


def test_faults_are_drawn_with_the_stated_probability():
    cfg = load_config(DEFAULT)
    n = 2000
    draws = [draw_fault(cfg, i) for i in range(n)]
    k = sum(bool(fault) for fault, _ in draws)
    p = cfg.fault_probability
    assert abs(k - n * p) < 4 * math.sqrt(n * p * (1 - p)), f"{k} faulted of {n}, expected ~{n * p:.0f}"
    for fault, phase in draws:
        assert bool(fault) == bool(phase)
        if fault:
            assert fault in cfg.fault_weights and phase in cfg.fault_phases
            assert not isinstance(expectation(fault, phase), str)  # never a not-applicable cell
    assert len({fault for fault, _ in draws if fault}) > 15  # every type can come up
    assert draw_mission(cfg, 7).fault == draws[7][0]
    never = dataclasses.replace(cfg, fault_probability=0.0)
    assert not any(draw_fault(never, i)[0] for i in range(50))


def test_the_short_model_inherits_the_default_one():
    short, default = load_config(SHORT), load_config(DEFAULT)
    assert short.inputs["start_range_m"].bounds == (1.2, 1.6)
    assert short.inputs["chaser_mass_kg"] == default.inputs["chaser_mass_kg"]
    assert short.fault_probability == 0.3 and short.mission == default.mission


@pytest.mark.parametrize(
    "inputs, why",
    [
        ({"start_range_m": {"dist": "uniform", "low": 8.0, "high": 30.0}}, "outside what the rig accepts"),
        ({"warp_drive": {"dist": "fixed", "value": 1.0}}, "unknown input"),
        ({"start_range_m": {"dist": "gauss", "low": 8.0, "high": 9.0}}, "dist must be one of"),
        ({"start_range_m": {"dist": "uniform", "low": 9.0, "high": 8.0}}, "low 9.0 > high 8.0"),
        ({"start_range_m": {"dist": "normal", "mean": 9.0, "sigma": 1.0}}, "missing 'low'"),
        ({"start_range_m": {"dist": "uniform", "low": 8.0, "high": 9.0, "sigma": 1}}, "do not belong"),
        ({"approach_port": {"dist": "uniform", "low": 1, "high": 6}}, "integer input"),
        ({"link_ber": {"dist": "loguniform", "low": 0.0, "high": 1e-6}}, "low > 0"),
    ],
)
def test_an_invalid_model_is_refused_with_its_reason(inputs, why):
    with pytest.raises(ConfigError, match=why):
        parse_config({"campaign": {"seed": 1}, "inputs": inputs})


def test_a_bad_campaign_table_is_refused():
    with pytest.raises(ConfigError, match="seed"):
        parse_config({"campaign": {"seed": -1}})
    with pytest.raises(ConfigError, match="nav"):
        parse_config({"campaign": {"seed": 1, "nav": "lidar"}})
    with pytest.raises(ConfigError, match="unknown fault type"):
        parse_config({"campaign": {"seed": 1}, "faults": {"probability": 0.1, "weights": {"meteor": 1}}})
    with pytest.raises(ConfigError, match="MissionParams"):
        parse_config({"campaign": {"seed": 1}, "mission": {"warp_kpa": 1}})


def test_a_draw_lands_where_the_model_says(sim_mcu_path):
    """The new rig hooks carry the draw into the world, the wire, the plant and the camera's
    scene; a scenario that does not use them starts exactly as before."""
    from oibar_hil.campaign.mission import build_scenario, make_nav, scene_of
    from oibar_hil.rig.runner import Rig
    from oibar_hil.rig.scenario import Scenario

    cfg = load_config(DEFAULT)
    d = draw_mission(cfg, 3)
    v = d.values
    rig = Rig(build_scenario(cfg, d), mcu_path=sim_mcu_path, nav=make_nav(cfg, d))
    s = rig.world.s
    assert s.r_D_m.tolist() == [v["start_lateral_x_m"], v["start_lateral_y_m"], v["start_range_m"]]
    assert s.v_D_mps.tolist() == [
        v["start_lateral_speed_x_mps"],
        v["start_lateral_speed_y_mps"],
        -v["start_closing_speed_mps"],
    ]
    assert np.degrees(s.att_rad).tolist() == pytest.approx(
        [v["start_pitch_deg"], v["start_yaw_deg"], v["start_roll_deg"]]
    )
    assert np.degrees(s.w_rad_s).tolist() == pytest.approx(
        [v["start_rate_x_deg_s"], v["start_rate_y_deg_s"], v["start_rate_z_deg_s"]]
    )
    assert rig.wire.ber == v["link_ber"] > 0
    assert rig.world.p.mass_kg == v["chaser_mass_kg"]
    assert rig.world.p.accel_bias_mps2 == (
        v["thrust_bias_x_mps2"],
        v["thrust_bias_y_mps2"],
        v["thrust_bias_z_mps2"],
    )
    assert rig.mech.p.press_zero_counts == pytest.approx(410.0 + v["pressure_offset_counts"])
    assert rig.mech.p.valve_stroke_s == v["valve_stroke_s"]
    assert rig.nav.name == "truth" and rig.nav.bias_m[:2].tolist() == [v["nav_bias_x_m"], v["nav_bias_y_m"]]
    spec = scene_of(d)
    assert spec.port == v["approach_port"] and spec.noise_sigma_dn == v["camera_noise_dn"]
    spec.validate()
    # the push acts: a world with a bias and no noise drifts by a t^2 / 2
    from oibar_hil.rig.world import VehicleParams, World, WorldState

    quiet = dict(accel_noise_mps2=0.0, ang_noise_rad_s2=0.0, odometry=False, velocity_tau_s=1e9)
    w = World(
        VehicleParams(**quiet, accel_bias_mps2=(1e-3, 0.0, 0.0)), WorldState(), np.random.default_rng(0)
    )
    for _ in range(100):
        w.step(0.01, np.zeros(3))
    assert w.s.r_D_m[0] == pytest.approx(0.5 * 1e-3 * 1.0**2, rel=0.02)
    # no new keys: the start and the wire as before the hooks
    plain = Rig(
        Scenario.from_dict({"name": "plain", "start": {"closing_speed_mps": 0.01}}), mcu_path=sim_mcu_path
    )
    assert plain.world.s.v_D_mps.tolist() == [0.0, 0.0, -0.01] and not plain.world.s.w_rad_s.any()
    assert plain.world.s.att_rad[2] == 0.0 and plain.wire.ber == 0.0


# -- Clopper-Pearson ------------------------------------------------------------------------


def test_a_param_attack_checks_its_names_against_the_mcu_that_flies(sim_mcu_path, tmp_path, monkeypatch):
    """A mission's param_attack names are checked against the simulated MCU the campaign flies
    (`--mcu`), not the default path: cnn_300 flown from a worktree without a build of its own
    ended mission 193 (param_attack when hard-docked) as an error before it flew, counted as a
    failure. The check is the rig's, and run_mission gives the rig the campaign's MCU."""
    from oibar_hil.campaign import mission
    from oibar_hil.rig import runner
    from oibar_hil.rig.fw_params import FirmwareParamsError
    from oibar_hil.rig.runner import Rig

    cfg = load_config(DEFAULT)
    d = draw_mission(cfg, 193)
    assert d.fault == "param_attack"
    monkeypatch.setenv("OIBAR_SIM_MCU", str(tmp_path / "no_build_here"))  # the default path, empty
    sc = mission.build_scenario(cfg, d)
    assert [f.type for f in sc.faults] == ["param_attack"] and sc.param_names()
    with pytest.raises(FirmwareParamsError):
        Rig(sc)
    flown = []

    class Stop(Exception):
        pass

    class CheckedRig(Rig):  # the rig run_mission builds, stopped before it flies
        def run(self):
            flown.append(self.mcu_path)
            raise Stop

    monkeypatch.setattr(runner, "Rig", CheckedRig)
    row = mission.run_mission(cfg, 193, mcu_path=str(sim_mcu_path)).row
    assert flown == [Path(sim_mcu_path)] and row["outcome"] == "error" and "Stop" in row["error"]


def test_clopper_pearson_figures():
    r = rate(300, 300)
    assert r.lower_bound == pytest.approx(0.05 ** (1 / 300), abs=1e-9)  # the 0.990
    assert round(r.lower_bound, 3) == 0.990
    assert r.low == pytest.approx(0.025 ** (1 / 300), abs=1e-9) and r.high == 1.0
    z = rate(0, 20)
    assert z.low == 0.0 and z.high == pytest.approx(1 - 0.025 ** (1 / 20), abs=1e-9)
    # a general case against the beta quantiles that define the exact interval
    from scipy.stats import beta

    g = rate(87, 100)
    assert g.low == pytest.approx(beta.ppf(0.025, 87, 14), abs=1e-9)
    assert g.high == pytest.approx(beta.ppf(0.975, 88, 13), abs=1e-9)
    assert g.lower_bound == pytest.approx(beta.ppf(0.05, 87, 14), abs=1e-9)
    assert missions_for_claim(0.99) == 299
    with pytest.raises(ValueError):
        rate(5, 4)


def test_outcome_drivers_name_the_input_that_moves_an_outcome():
    """A campaign without failures still has drivers: an outcome made to follow one input, and
    one made to depend on the approach port, are traced to that input, the rest far behind."""
    from oibar_hil.campaign.report import outcome_drivers

    cfg = dataclasses.replace(load_config(DEFAULT), nav="cnn")
    rng = np.random.default_rng(7)
    rows = []
    for i in range(150):
        v = draw_mission(cfg, i).values
        row: dict = {f"in_{k}": x for k, x in v.items()}
        row["contact_closing_speed_mps"] = 0.02 + 0.1 * v["valve_stroke_s"] + rng.normal(0, 2e-4)
        nav = 0.05 + 0.15 * (v["approach_port"] == 4) + rng.normal(0, 0.01)
        row["nav_lateral_err_m_p95_below_5m"] = None if i % 15 == 0 else nav  # not measured: skipped
        row["peak_force_n"] = 22.9  # the same in every mission: nothing to trace
        rows.append(row)
    speed = outcome_drivers(rows, cfg, "contact_closing_speed_mps")
    assert speed[0]["input"] == "valve_stroke_s" and speed[0]["rho"] > 0.9 and speed[0]["p"] < 1e-6
    assert all(abs(d["rho"]) < 0.5 for d in speed[1:] if d["medians"] == {})
    nav = outcome_drivers(rows, cfg, "nav_lateral_err_m_p95_below_5m")
    assert nav[0]["input"] == "approach_port" and nav[0]["p"] < 1e-6
    assert nav[0]["medians"][4] > max(m for port, m in nav[0]["medians"].items() if port != 4) + 0.1
    assert nav[1]["p"] > 1e-4  # no other input follows the port
    assert outcome_drivers(rows, cfg, "peak_force_n") == []


# -- a tiny campaign ----------------------------------------------------------------------------


def _deterministic(rows):
    from oibar_hil.campaign.mission import VOLATILE_COLUMNS

    # code_sha: the same unless someone edits the shared checkout between two campaigns
    return [{k: v for k, v in r.items() if k not in (*VOLATILE_COLUMNS, "code_sha")} for r in rows]


@pytest.fixture(scope="module")
def serial_campaign(tmp_path_factory, sim_mcu_path):
    """The short model's first missions flown in this one process (2, then extended to 4)."""
    pytest.importorskip("pyarrow")
    from oibar_hil.campaign import fingerprint
    from oibar_hil.campaign.execute import run_missions
    from oibar_hil.campaign.store import open_campaign, read_rows

    folder = tmp_path_factory.mktemp("serial")
    cfg = dataclasses.replace(load_config(SHORT), missions=2)
    code = fingerprint.code_fingerprint(cfg.nav, mcu_path=sim_mcu_path)
    with pytest.MonkeyPatch.context() as mp:  # this checkout's, held: others may edit the tree meanwhile
        mp.setattr(fingerprint, "code_fingerprint", lambda *a, **k: code)
        open_campaign(folder, cfg, mcu_path=sim_mcu_path)
        first = run_missions(cfg, folder, executor="serial", mcu_path=str(sim_mcu_path), progress=False)
        assert (first.already_done, first.finished) == (0, 2)
        cfg = dataclasses.replace(cfg, missions=TINY_MISSIONS)
        assert open_campaign(folder, cfg, mcu_path=sim_mcu_path).status == "same"  # longer: accepted
        more = run_missions(cfg, folder, executor="serial", mcu_path=str(sim_mcu_path), progress=False)
    assert (more.already_done, more.finished) == (2, TINY_MISSIONS - 2), "the resume flew done missions again"
    return folder, cfg, read_rows(folder)


def test_serial_campaign_rows(serial_campaign):
    folder, cfg, rows = serial_campaign
    assert [r["index"] for r in rows] == list(range(TINY_MISSIONS))
    code = json.loads((folder / "campaign.json").read_text())["code"]
    assert [r["code_sha"] for r in rows] == [code["short"]] * TINY_MISSIONS  # the code that flew them
    for r in rows:
        assert r["outcome"] in ("completed", "aborted", "safed"), r["error"]
        assert r["success"], f"mission {r['index']}: {r['failed_checks']}"
        assert r["sim_time_s"] > 0 and r["wall_time_s"] > 0 and r["cpu_time_s"] > 0
        if not r["fault"]:
            assert r["captured"] and r["contact_lateral_m"] < 0.05 and r["fuel_transferred_kg"] > 0.02
            # the true path inside 5 m: inside guidance's corridor there (0.5 m), and not nothing
            assert 0.0 < r["approach_off_axis_m_max_below_5m"] < 0.5
        assert (
            r["nav_attitude_replaced"] == 0 and r["nav_att_check_deg_max"] is None
        )  # truth: nothing checked
        d = draw_mission(cfg, r["index"])
        assert r["in_start_range_m"] == d.values["start_range_m"] and r["fault"] == d.fault


def test_another_campaign_in_the_same_folder_is_refused(serial_campaign):
    from oibar_hil.campaign.store import CampaignFolderError, open_campaign

    folder, cfg, _ = serial_campaign
    with pytest.raises(CampaignFolderError, match="another campaign"):
        open_campaign(folder, dataclasses.replace(cfg, seed=cfg.seed + 1))


@pytest.mark.slow
def test_ray_campaign_with_a_killed_worker_gives_the_same_table(serial_campaign, tmp_path, sim_mcu_path):
    """Two Ray workers; the worker flying mission 1 is killed (SIGKILL) in the middle of it.
    Ray runs the mission again; the table has every mission once, equal to the serial one."""
    pytest.importorskip("ray")
    import pyarrow.parquet as pq

    _, cfg, serial_rows = serial_campaign
    out, pids = tmp_path / "ray", tmp_path / "pids"
    pids.mkdir()
    env = {**os.environ, "OIBAR_CAMPAIGN_PID_DIR": str(pids), "PYTHONPATH": f"{ROOT / 'hil'}:{ROOT / 'host'}"}
    cmd = [sys.executable, "-m", "oibar_hil.campaign", "run", "--config", str(SHORT), "--no-progress",
           "--missions", str(TINY_MISSIONS), "--workers", "2", "--out", str(out),
           "--mcu", str(sim_mcu_path)]  # fmt: skip
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    killed = None
    try:
        deadline = time.monotonic() + 90
        while killed is None and time.monotonic() < deadline and proc.poll() is None:
            started = sorted(pids.glob("1.*"))
            if started and not (out / "parts" / "mission_000001.parquet").exists():
                killed = int(started[0].suffix[1:])
                os.kill(killed, signal.SIGKILL)
            time.sleep(0.05)
        output, _ = proc.communicate(timeout=150)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert killed is not None, "mission 1 never started on a worker"
    assert proc.returncode == 0, output
    attempts = sorted(p.name for p in pids.glob("1.*"))
    assert len(attempts) >= 2, f"mission 1 was not run again after its worker died: {attempts}"
    parts = sorted(p.name for p in (out / "parts").glob("*.parquet"))
    assert parts == [f"mission_{i:06d}.parquet" for i in range(TINY_MISSIONS)]
    table = pq.read_table(out / "missions.parquet").to_pylist()
    assert [r["index"] for r in table] == list(range(TINY_MISSIONS)), "a mission lost or duplicated"
    assert _deterministic(table) == _deterministic(serial_rows), "Ray's table differs from one process's"
    assert len({r["worker"] for r in table}) >= 2  # the missions did spread over workers
    code = json.loads((out / "campaign.json").read_text())["code"]
    assert {r["code_sha"] for r in table} == {code["short"]}  # each worker's own: the campaign's
    report = (out / "report.md").read_text()
    assert f"{TINY_MISSIONS}/{TINY_MISSIONS}" in report and "Clopper-Pearson" in report
    assert (out / "figures" / "inputs_success.png").exists()
    nav_figure = out / "figures" / "inputs_vs_nav_lateral_err_m_p95_below_5m.png"  # what drives nav error
    assert nav_figure.exists()
    assert (out / "figures" / "inputs_vs_approach_off_axis_m_max_below_5m.png").exists()  # and the path


def test_replay_reproduces_a_stored_mission(serial_campaign, capsys):
    from oibar_hil.campaign.cli import main

    folder, _, rows = serial_campaign
    index = next((r["index"] for r in rows if r["fault"]), 1)  # a faulted one when there is one
    assert main(["replay", str(folder), str(index)]) == 0
    out = capsys.readouterr().out
    assert "reproduced" in out
    assert (folder / "replay" / f"{index:06d}" / "report.html").exists()
    assert main(["replay", str(folder), "99"]) == 2  # not in the campaign


# -- one version of the code per campaign ------------------------------------------------------


@pytest.fixture
def code_tree(tmp_path, monkeypatch):
    """A source tree of the fingerprint's groups (fingerprint.SOURCE_ROOT points at it) and a
    stand-in simulated MCU binary; -> (root, mcu path)."""
    from oibar_hil.campaign import fingerprint

    root = tmp_path / "src"
    files = {
        "host/oibar/nav/guidance.py": "GATE = 5\n",
        "host/oibar/_generated/oibar_pb2.py": "generated\n",
        "firmware/app/fsm.c": "int x;\n",
        "firmware/app/fsm.h": "#pragma once\n",
        "proto/oibar.proto": 'syntax = "proto3";\n',
        "hil/oibar_hil/rig/runner.py": "RIG = 1\n",
        "models/oibarnet.onnx": "weights",
        "models/oibarnet.int8.onnx": "not shipped",
        "build/oibar_sim_mcu": "ELF 1",
    }
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    monkeypatch.setattr(fingerprint, "SOURCE_ROOT", root)
    return root, root / "build" / "oibar_sim_mcu"


def test_the_code_fingerprint_covers_what_flies(code_tree):
    from oibar_hil.campaign.fingerprint import changed_groups, code_fingerprint

    root, mcu = code_tree
    a = code_fingerprint("cnn", mcu_path=mcu)
    assert a == code_fingerprint("cnn", mcu_path=mcu) and a["short"] == a["sha256"][:12]
    assert set(a["groups"]) == {"host", "firmware", "proto", "hil", "models", "sim_mcu"}
    assert a["groups"]["firmware"]["files"] == 2 and a["groups"]["models"]["files"] == 1
    assert "models" not in code_fingerprint("truth", mcu_path=mcu)["groups"]  # truth flies no model
    (root / "host/oibar/_generated/oibar_pb2.py").write_text("regenerated\n")  # not hashed
    (root / "models/oibarnet.int8.onnx").write_text("requantised")
    (root / "host/oibar/nav/__pycache__").mkdir()
    (root / "host/oibar/nav/__pycache__/guidance.py").write_text("cache\n")
    assert code_fingerprint("cnn", mcu_path=mcu) == a
    edits = {
        "host": "host/oibar/nav/guidance.py",
        "firmware": "firmware/app/fsm.h",
        "proto": "proto/oibar.proto",
        "hil": "hil/oibar_hil/rig/runner.py",
        "models": "models/oibarnet.onnx",
        "sim MCU binary": "build/oibar_sim_mcu",
    }
    for group, rel in edits.items():
        before = code_fingerprint("cnn", mcu_path=mcu)
        (root / rel).write_text((root / rel).read_text() + " ")
        after = code_fingerprint("cnn", mcu_path=mcu)
        assert changed_groups(before, after) == [group] and after["sha256"] != before["sha256"]
    # a file's path is hashed with its contents: a move is a change
    before = code_fingerprint("cnn", mcu_path=mcu)
    (root / "firmware/app/fsm.c").rename(root / "firmware/app/fsm2.c")
    assert changed_groups(before, code_fingerprint("cnn", mcu_path=mcu)) == ["firmware"]


def _fake_mission(calls):
    """run_mission without the rig: a fault-free success row, the index noted in ``calls``."""
    import socket

    from oibar_hil.campaign.mission import MissionRun, complete_row

    def run(cfg, index, *, mcu_path=None, model_path=None, out_dir=None):
        calls.append(index)
        d = draw_mission(cfg, index)
        row = {"index": index, "campaign": cfg.name, "campaign_seed": cfg.seed, "config_id": cfg.identity(),
               "nav": cfg.nav,
               "fault": "", "fault_phase": "", "outcome": "completed", "success": True,
               "wall_time_s": 0.01, "cpu_time_s": 0.01, "sim_time_s": 1.0,
               "worker": f"{socket.gethostname()}:{os.getpid()}",
               **{f"in_{k}": v for k, v in d.values.items()}}  # fmt: skip
        return MissionRun(complete_row(row))

    return run


def test_a_campaign_flies_one_version_of_the_code(code_tree, tmp_path, monkeypatch, capsys):
    """A resume with the same code proceeds; changed code is refused (exit 3, one line naming
    the groups) unless --allow-code-change gives the reason, which campaign.json, the rows'
    code_sha and the report keep."""
    pytest.importorskip("pyarrow")
    from oibar_hil.campaign import execute
    from oibar_hil.campaign.cli import EXIT_FOLDER, main
    from oibar_hil.campaign.report import code_lines
    from oibar_hil.campaign.store import read_rows

    root, mcu = code_tree
    calls: list[int] = []
    monkeypatch.setattr(execute, "run_mission", _fake_mission(calls))
    folder = tmp_path / "camp"

    def run(n, *extra):
        calls.clear()
        rc = main(["run", "--config", str(SHORT), "--missions", str(n), "--out", str(folder),
                   "--executor", "serial", "--mcu", str(mcu), "--no-progress", "--no-report", *extra])  # fmt: skip
        return rc, list(calls), capsys.readouterr().err

    assert run(2)[:2] == (0, [0, 1])
    meta = json.loads((folder / "campaign.json").read_text())
    first = meta["code"]
    assert set(first["groups"]) == {"host", "firmware", "proto", "hil", "sim_mcu"}  # truth: no models
    assert first["git"] is None and first["time"]  # the tree is not a git checkout
    assert run(3)[:2] == (0, [2])  # unchanged code: the resume proceeds
    assert [r["code_sha"] for r in read_rows(folder)] == [first["short"]] * 3
    meta = json.loads((folder / "campaign.json").read_text())
    assert meta["code"] == first and "code_changes" not in meta

    (root / "host/oibar/nav/guidance.py").write_text("GATE = 4\n")
    (root / "build/oibar_sim_mcu").write_text("ELF 2")
    rc, flown, err = run(4)
    assert (rc, flown) == (EXIT_FOLDER, [])
    assert len(err.strip().splitlines()) == 1, err
    assert "host, sim MCU binary changed" in err and "--allow-code-change REASON" in err
    assert first["short"] in err and f"exit {EXIT_FOLDER}" in err and "--name" in err
    assert json.loads((folder / "campaign.json").read_text()) == meta  # nothing recorded

    rc, flown, err = run(4, "--allow-code-change", "gate fix: guidance only")
    assert (rc, flown) == (0, [3]) and "resumed anyway" in err
    meta = json.loads((folder / "campaign.json").read_text())
    (change,) = meta["code_changes"]
    assert change["reason"] == "gate fix: guidance only" and change["time"]
    assert change["changed"] == ["host", "sim MCU binary"] and change["missions_before"] == 3
    assert change["old"]["sha256"] == first["sha256"] and meta["code"] == first
    second = change["new"]["short"]
    assert second != first["short"]
    assert [r["code_sha"] for r in read_rows(folder)] == [first["short"]] * 3 + [second]
    assert run(5)[:2] == (0, [4])  # the accepted code is the campaign's now
    report = "\n".join(code_lines(folder, read_rows(folder)))
    assert first["short"] in report and "gate fix: guidance only" in report
    assert "code changed during this campaign" in report and f"`{second}` 2" in report


def test_a_mission_flown_by_a_worker_with_other_code_is_not_written(code_tree, tmp_path, monkeypatch, capsys):
    """Each worker fingerprints the code it flies. A worker with a stale checkout (its own tree,
    another guidance.py): the driver writes none of its rows, stops, names the worker, both
    fingerprints and the group, exit 3; with --allow-code-change its rows are kept under its
    own code_sha, which campaign.json and the report record."""
    pytest.importorskip("pyarrow")
    import shutil
    import socket

    from oibar_hil.campaign import execute, fingerprint
    from oibar_hil.campaign.cli import EXIT_FOLDER, main
    from oibar_hil.campaign.report import code_lines
    from oibar_hil.campaign.store import code_record, part_indices, read_rows

    root, mcu = code_tree
    calls: list[int] = []
    monkeypatch.setattr(execute, "run_mission", _fake_mission(calls))
    folder = tmp_path / "camp"

    def run(n, *extra):
        calls.clear()
        rc = main(["run", "--config", str(SHORT), "--missions", str(n), "--out", str(folder),
                   "--executor", "serial", "--mcu", str(mcu), "--no-progress", "--no-report", *extra])  # fmt: skip
        return rc, list(calls), capsys.readouterr().err

    assert run(2)[:2] == (0, [0, 1])  # the normal path: the worker's code is the campaign's
    meta = json.loads((folder / "campaign.json").read_text())
    campaign = meta["code"]["short"]
    assert [r["code_sha"] for r in read_rows(folder)] == [campaign] * 2

    stale = tmp_path / "stale"  # the worker's own checkout, one file behind
    shutil.copytree(root, stale)
    (stale / "host/oibar/nav/guidance.py").write_text("GATE = 4\n")
    theirs = execute.worker_code
    computed: list[str] = []

    def stale_worker(nav, mcu_path, model_path):
        with pytest.MonkeyPatch.context() as mp:  # SOURCE_ROOT as that worker sees it
            mp.setattr(fingerprint, "SOURCE_ROOT", stale)
            code = theirs(nav, mcu_path, model_path)
        computed.append(code["short"])
        return code

    monkeypatch.setattr(execute, "worker_code", stale_worker)
    rc, flown, err = run(4)
    (other,) = set(computed)
    assert (rc, flown) == (EXIT_FOLDER, [2]), err  # flown, then the campaign stopped
    assert len(err.strip().splitlines()) == 1, err
    assert f"mission 2 was flown by worker {socket.gethostname()}:{os.getpid()}" in err
    assert other in err and campaign in err and "differ in host)" in err and f"exit {EXIT_FOLDER}" in err
    assert part_indices(folder) == {0, 1} and [r["index"] for r in read_rows(folder)] == [0, 1]
    assert code_record(folder) == {"code": meta["code"]}  # no code recorded

    rc, flown, err = run(4, "--allow-code-change", "stale node, guidance only")
    assert (rc, flown) == (0, [2, 3]), err
    assert "kept: 'stale node, guidance only'" in err
    assert [r["code_sha"] for r in read_rows(folder)] == [campaign] * 2 + [other] * 2
    meta = json.loads((folder / "campaign.json").read_text())
    (kept,) = meta["worker_code"]
    assert kept["code"]["short"] == other and kept["changed"] == ["host"] and kept["first_mission"] == 2
    assert kept["reason"] == "stale node, guidance only" and meta["code"]["short"] == campaign
    assert main(["report", str(folder), "--no-figures"]) == 0  # its table holds known code
    assert run(4)[:2] == (0, [])  # and resumes from it
    report = "\n".join(code_lines(folder, read_rows(folder)))
    assert f"`{campaign}` 2, `{other}` 2" in report and "stale node, guidance only" in report


def test_a_worker_hashes_again_an_mcu_or_model_rebuilt_under_it(code_tree, monkeypatch):
    """A worker hashes its tree once (its Python is imported once) but starts the simulated MCU
    and opens the models afresh each mission: one rebuilt under a running campaign must show in
    the fingerprint its next mission returns, not the one cached at its first."""
    from oibar_hil.campaign import execute, fingerprint
    from oibar_hil.campaign.fingerprint import changed_groups

    root, mcu = code_tree
    monkeypatch.setattr(execute, "_WORKER_CODE", {})
    hashed: list[str] = []
    theirs = fingerprint.code_fingerprint

    def counting(nav, **kw):
        hashed.append(nav)
        return theirs(nav, **kw)

    monkeypatch.setattr(fingerprint, "code_fingerprint", counting)
    first = execute.worker_code("cnn", str(mcu), None)
    assert execute.worker_code("cnn", str(mcu), None) is first and len(hashed) == 1  # cached
    mcu.write_text("ELF 2, rebuilt")
    rebuilt = execute.worker_code("cnn", str(mcu), None)
    assert changed_groups(first, rebuilt) == ["sim MCU binary"] and len(hashed) == 2
    (root / "models/oibarnet.onnx").write_text("weights, retrained")
    assert changed_groups(rebuilt, execute.worker_code("cnn", str(mcu), None)) == ["models"]
    # a truth mission opens no model: a model written under it does not cost a hash
    execute.worker_code("truth", str(mcu), None)
    (root / "models/oibarnet.onnx").write_text("weights, retrained again")
    n = len(hashed)
    execute.worker_code("truth", str(mcu), None)
    assert len(hashed) == n


def test_a_folder_made_before_fingerprints_adopts_the_code(code_tree, tmp_path):
    """An older campaign.json (no code) resumes, recording this checkout's fingerprint, and its
    older parts (no code_sha column) still read."""
    pyarrow = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    from oibar_hil.campaign.mission import complete_row
    from oibar_hil.campaign.store import open_campaign, part_path, read_rows

    _, mcu = code_tree
    folder = tmp_path / "old"
    cfg = dataclasses.replace(load_config(SHORT), missions=2)
    open_campaign(folder, cfg, mcu_path=mcu)
    meta = json.loads((folder / "campaign.json").read_text())
    del meta["code"]
    (folder / "campaign.json").write_text(json.dumps(meta))
    old = {k: v for k, v in complete_row({"index": 0, "success": True}).items() if k != "code_sha"}
    pq.write_table(pyarrow.Table.from_pylist([old]), part_path(folder, 0))
    check = open_campaign(folder, cfg, mcu_path=mcu)
    assert check.status == "adopted"
    meta = json.loads((folder / "campaign.json").read_text())
    assert meta["code"]["sha256"] == check.fingerprint["sha256"]
    assert meta["code_adopted"]["missions_before"] == 1
    assert [(r["index"], r["code_sha"]) for r in read_rows(folder)] == [(0, "")]
    assert open_campaign(folder, cfg, mcu_path=mcu).status == "same"


# -- resuming from the merged table (pack) -------------------------------------------------------


@pytest.fixture
def fake_runs(code_tree, tmp_path, monkeypatch, capsys):
    """``main`` of the CLI with the short model's missions faked (nothing flies, the code tree's
    fingerprint): -> run(args) -> (exit status, missions flown, stderr)."""
    pytest.importorskip("pyarrow")
    from oibar_hil.campaign import execute
    from oibar_hil.campaign.cli import main

    _, mcu = code_tree
    calls: list[int] = []
    monkeypatch.setattr(execute, "run_mission", _fake_mission(calls))

    def run(*args):
        calls.clear()
        capsys.readouterr()
        argv = list(args)
        if args[0] == "run":
            argv += ["--config", str(SHORT), "--executor", "serial", "--mcu", str(mcu), "--no-progress"]
            argv += ["--no-report"]
        elif args[0] == "report":
            argv += ["--no-figures"]
        rc = main(argv)
        return rc, list(calls), capsys.readouterr().err

    return run


def test_a_packed_campaign_resumes_from_its_table(fake_runs, tmp_path):
    """pack -> campaign.json + missions.parquet (zstd, index order); a folder holding them and a
    few parts flies only the missions in neither; its table equals a one-folder campaign's."""
    import shutil

    import pyarrow.parquet as pq

    from oibar_hil.campaign.cli import EXIT_FOLDER
    from oibar_hil.campaign.store import read_rows, stored_row

    camp, packed, resumed, whole = (tmp_path / n for n in ("camp", "results/short", "resumed", "whole"))
    assert fake_runs("run", "--missions", "4", "--out", str(camp))[:2] == (0, [0, 1, 2, 3])
    (camp / "parts" / "mission_000001.parquet").unlink()  # a campaign with a gap: 0, 2, 3 finished
    assert fake_runs("pack", str(camp), "--to", str(packed))[0] == 0
    assert sorted(p.name for p in packed.iterdir()) == ["campaign.json", "missions.parquet"]
    assert (packed / "campaign.json").read_bytes() == (camp / "campaign.json").read_bytes()
    meta = pq.ParquetFile(packed / "missions.parquet").metadata
    assert meta.row_group(0).column(0).compression == "ZSTD"
    assert [r["index"] for r in pq.read_table(packed / "missions.parquet").to_pylist()] == [0, 2, 3]

    # a fresh checkout: the committed folder copied back, plus a part of a mission also in the table
    shutil.copytree(packed, resumed)
    (resumed / "parts").mkdir()
    shutil.copy(camp / "parts" / "mission_000002.parquet", resumed / "parts")
    rc, flown, err = fake_runs("run", "--missions", "6", "--out", str(resumed))
    assert (rc, flown) == (0, [1, 4, 5]), err  # no mission flown twice
    assert sorted(p.name for p in (resumed / "parts").iterdir()) == [
        f"mission_{i:06d}.parquet" for i in (1, 2, 4, 5)
    ]
    rows = read_rows(resumed)
    assert [r["index"] for r in rows] == list(range(6))  # mission 2 kept once
    assert stored_row(resumed, 3)["index"] == 3  # replay finds a row only the table holds
    assert fake_runs("run", "--missions", "6", "--out", str(resumed))[:2] == (0, [])  # all done

    assert fake_runs("run", "--missions", "6", "--out", str(whole))[:2] == (0, list(range(6)))
    assert fake_runs("report", str(resumed))[0] == 0 and fake_runs("report", str(whole))[0] == 0
    merged = pq.read_table(resumed / "missions.parquet").to_pylist()
    one_folder = pq.read_table(whole / "missions.parquet").to_pylist()
    assert _deterministic(merged) == _deterministic(one_folder)
    assert {r["code_sha"] for r in merged} == {
        json.loads((whole / "campaign.json").read_text())["code"]["short"]
    }

    # packed again over the committed folder: it grows; a source lacking its missions is refused
    assert fake_runs("pack", str(resumed), "--to", str(packed))[0] == 0
    assert [r["index"] for r in pq.read_table(packed / "missions.parquet").to_pylist()] == list(range(6))
    rc, _, err = fake_runs("pack", str(camp), "--to", str(packed))
    assert rc == EXIT_FOLDER and "1, 4-5" in err and "would drop them" in err
    assert fake_runs("pack", str(tmp_path / "nowhere"), "--to", str(packed))[0] == 2


def test_a_packed_campaign_keeps_its_code_fingerprint(fake_runs, code_tree, tmp_path):
    """The code rules hold for a packed folder as for parts: other code is refused (exit 3)."""
    import shutil

    from oibar_hil.campaign.cli import EXIT_FOLDER

    root, _ = code_tree
    camp, packed = tmp_path / "camp", tmp_path / "packed"
    assert fake_runs("run", "--missions", "2", "--out", str(camp))[0] == 0
    assert fake_runs("pack", str(camp), "--to", str(packed))[0] == 0
    (root / "firmware/app/fsm.c").write_text("int y;\n")
    resumed = tmp_path / "resumed"
    shutil.copytree(packed, resumed)
    rc, flown, err = fake_runs("run", "--missions", "3", "--out", str(resumed))
    assert (rc, flown) == (EXIT_FOLDER, []) and "firmware changed" in err
    rc, flown, _ = fake_runs("run", "--missions", "3", "--out", str(resumed), "--allow-code-change", "fsm")
    assert (rc, flown) == (0, [2])


def test_a_bad_missions_table_is_refused(fake_runs, tmp_path):
    """An unreadable missions.parquet, another campaign's (seed, name), one of code campaign.json
    does not record, or one disagreeing with a part: refused with the reason, exit 3, nothing
    flown or recorded."""
    import shutil

    import pyarrow as pa
    import pyarrow.parquet as pq

    from oibar_hil.campaign.cli import EXIT_FOLDER

    camp = tmp_path / "camp"
    assert fake_runs("run", "--missions", "3", "--out", str(camp))[0] == 0
    assert fake_runs("pack", str(camp), "--to", str(tmp_path / "good"))[0] == 0
    good = tmp_path / "good" / "missions.parquet"
    others = {}
    for name, extra in {"seed": ["--seed", "7"], "name": ["--name", "other"]}.items():
        out = tmp_path / f"other_{name}"
        assert fake_runs("run", "--missions", "3", "--out", str(out), *extra)[0] == 0
        assert fake_runs("report", str(out))[0] == 0
        others[name] = out / "missions.parquet"
    rows = pq.read_table(good).to_pylist()
    schema = pq.read_schema(good)

    def table(rows):
        buf = pa.BufferOutputStream()
        pq.write_table(pa.Table.from_pylist(rows, schema=schema), buf)
        return buf.getvalue().to_pybytes()

    cases = {
        "truncated": (good.read_bytes()[:-100], "not a readable table of missions"),
        "not parquet": (b"version https://git-lfs.github.com/spec/v1\n", "not a readable table of missions"),
        "other seed": (others["seed"].read_bytes(), "seed 7"),
        "other name": (others["name"].read_bytes(), "campaign 'other'"),
        "twice": (table(rows + rows[:1]), "missions 0 appear more than once"),
        "other code": (table([{**r, "code_sha": "0123456789ab"} for r in rows]), "0123456789ab (3 rows)"),
    }
    for case, (data, why) in cases.items():
        folder = tmp_path / f"bad_{case.replace(' ', '_')}"
        shutil.copytree(tmp_path / "good", folder)
        (folder / "missions.parquet").write_bytes(data)
        meta = (folder / "campaign.json").read_text()
        rc, flown, err = fake_runs("run", "--missions", "5", "--out", str(folder))
        assert (rc, flown) == (EXIT_FOLDER, []), (case, err)
        assert why in err and str(folder / "missions.parquet") in err, (case, err)
        assert len(err.strip().splitlines()) == 1, err
        assert (folder / "campaign.json").read_text() == meta  # nothing recorded
        assert (folder / "missions.parquet").read_bytes() == data  # nor rewritten
        assert fake_runs("report", str(folder))[0] == EXIT_FOLDER
        assert (
            fake_runs("pack", str(folder), "--to", str(tmp_path / f"{folder.name}_packed"))[0] == EXIT_FOLDER
        )
    # a part and the table's row of one mission that differ: two flights, not one
    folder = tmp_path / "disagree"
    shutil.copytree(camp, folder)
    assert fake_runs("report", str(folder))[0] == 0  # parts + the table written from them: fine
    part = folder / "parts" / "mission_000001.parquet"
    t = pq.read_table(part)
    pq.write_table(t.set_column(t.schema.get_field_index("success"), "success", pa.array([False])), part)
    rc, flown, err = fake_runs("run", "--missions", "5", "--out", str(folder))
    assert (rc, flown) == (EXIT_FOLDER, []) and "mission 1 is in both" in err and "success" in err
    # another campaign's folder as the destination of a pack
    rc, _, err = fake_runs("pack", str(camp), "--to", str(others["seed"].parent))
    assert rc == EXIT_FOLDER and "holds another campaign" in err


def test_a_table_from_before_a_column_reads_it_as_null_and_reports(tmp_path):
    """A table written before nav_attitude_replaced, the check's largest disagreement and the
    true path inside 5 m (cnn_300's, those columns taken out as its code wrote it) is read in
    today's schema, the new columns null, and its report is written without them."""
    import shutil

    import pyarrow.parquet as pq

    from oibar_hil.campaign.report import write_report
    from oibar_hil.campaign.store import load_config, table_rows

    packed = ROOT / "hil" / "campaigns" / "results" / "cnn_300"
    folder = tmp_path / "cnn_300"
    shutil.copytree(packed, folder)
    new_columns = ["nav_attitude_replaced", "nav_att_check_deg_max", "approach_off_axis_m_max_below_5m"]
    table = pq.read_table(folder / "missions.parquet")
    table = table.drop_columns([c for c in new_columns if c in table.column_names])
    pq.write_table(table, folder / "missions.parquet")
    assert not set(new_columns) & set(pq.read_schema(folder / "missions.parquet").names)
    rows = table_rows(folder)
    ok = sum(bool(r["success"]) for r in rows)
    assert len(rows) >= 100 and ok >= len(rows) - 1
    assert {r["nav_attitude_replaced"] for r in rows} == {None}
    assert {r["approach_off_axis_m_max_below_5m"] for r in rows} == {None}
    assert {r["nav_att_check_deg_max"] for r in rows} == {None}
    report = write_report(folder, rows, load_config(folder)).read_text()
    assert f"{ok}/{len(rows)}" in report
    assert (folder / "figures" / "inputs_vs_nav_lateral_err_m_p95_below_5m.png").exists()
    assert not (folder / "figures" / "inputs_vs_approach_off_axis_m_max_below_5m.png").exists()
