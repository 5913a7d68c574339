"""The closed-loop looks study (oibar_hil.rig.looks): its statistics, its run cache and the rig
command line it drives. The loops themselves take a minute each; here the rig is replaced where
a loop would run, and the plumbing that reaches the real rig (--seed, --misalignment-deg, the
capture in --json) is checked against the rig's own command line."""

from __future__ import annotations

import json
import math
import sys

import pytest

from oibar_hil.rig import cli, looks
from oibar_hil.rig.looks import LoopResult, RunKey, summarise


def _r(model, look, lat_cm, cap_mm=5.0, start=10.0, seed=1, turn=(2.0, -1.5), completed=True):
    return LoopResult(
        RunKey(model, look, start, seed, turn), completed, lat_cm / 100, 1.0, cap_mm / 1000, "completed"
    )


def test_the_summary_pairs_runs_by_condition_and_gives_error_bars():
    runs = [
        _r("a", "va000", 2.0),
        _r("a", "va001", 4.0),
        _r("a", "va002", 6.0, cap_mm=9.0),
        _r("a", "va003", math.nan),  # never came below 5 m: left out of the lateral figures
        _r("b", "va000", 1.0),
        _r("b", "va001", 5.0),
        _r("b", "va002", 3.0),
        _r("b", "va004", 9.0),  # a condition the reference did not fly: not paired
    ]
    s = summarise(runs, ["a", "b"])["models"]
    a, b = s["a"], s["b"]
    assert a["runs"] == 4 and b["runs"] == 4
    assert a["lateral_p95_below_5m_cm_mean"] == pytest.approx(4.0)
    assert a["lateral_p95_below_5m_cm_se"] == pytest.approx(2.0 / math.sqrt(3))  # sd 2 over 3 runs
    assert a["lateral_p95_below_5m_cm_worst"] == pytest.approx(6.0)
    assert a["within_5cm_share"] == pytest.approx(2 / 3)
    assert a["capture_lateral_mm_worst"] == pytest.approx(9.0)
    assert "paired_vs_first" not in a
    p = b["paired_vs_first"]
    # differences on va000 / va001 / va002: -1, +1, -3
    assert p["runs"] == 3 and p["better"] == 2 and p["worse"] == 1
    assert p["lateral_p95_diff_cm_mean"] == pytest.approx(-1.0)
    assert p["lateral_p95_diff_cm_se"] == pytest.approx(2.0 / math.sqrt(3))


def test_runs_of_other_starts_or_turns_are_not_paired():
    runs = [_r("a", "va000", 2.0), _r("b", "va000", 3.0, start=9.0), _r("b", "va000", 1.0, turn=(-2.0, 1.5))]
    assert summarise(runs, ["a", "b"])["models"]["b"]["paired_vs_first"]["runs"] == 0


def _fake_rig(tmp_path, monkeypatch, lateral_m=0.03, write=True):
    """Replace the rig's command with a small program that writes what the rig's --json writes
    (or nothing, as a crashed rig), counting its runs."""
    count = tmp_path / "count"
    count.write_text("0")

    def command(key, model_path, spec, run_dir, json_path):
        doc = [
            {
                "outcome": "completed",
                "metrics": {
                    "nav_lateral_err_m_p95_below_5m": lateral_m,
                    "nav_misalign_err_deg_p95_below_5m": 0.4,
                },
                "capture": {"lateral_m": 0.004},
            }
        ]
        body = f"import json, pathlib; p = pathlib.Path({str(count)!r}); p.write_text(str(int(p.read_text()) + 1))"
        if write:
            body += f"; pathlib.Path({str(json_path)!r}).write_text({json.dumps(json.dumps(doc))})"
        return [sys.executable, "-c", body]

    monkeypatch.setattr(looks, "rig_command", command)
    return count


def test_a_finished_run_is_read_back_not_flown_again(tmp_path, monkeypatch):
    count = _fake_rig(tmp_path, monkeypatch)
    key = RunKey("m-1", "va000", 10.0, 1, (2.0, -1.5))
    first = looks.run_one(key, "m.onnx", "models/scenes/val.json", tmp_path / "cache")
    again = looks.run_one(key, "m.onnx", "models/scenes/val.json", tmp_path / "cache")
    assert count.read_text() == "1"
    assert first == again and first.lateral_p95_below_5m_m == pytest.approx(0.03)
    assert first.capture_lateral_m == pytest.approx(0.004) and first.completed


def test_a_rig_that_dies_leaves_no_result_and_the_study_goes_on(tmp_path, monkeypatch, capsys):
    _fake_rig(tmp_path, monkeypatch, write=False)
    key = RunKey("m-1", "va000", 10.0, 1, (2.0, -1.5))
    with pytest.raises(RuntimeError, match="without results"):
        looks.run_one(key, "m.onnx", "spec", tmp_path / "cache")
    assert not (tmp_path / "cache" / "m-1" / key.name() / "result.json").exists()

    good = RunKey("m-1", "va001", 10.0, 1, (2.0, -1.5))

    def runner(k, path, spec, out):
        if k == key:
            raise RuntimeError("the rig exited 1")
        return _r(k.model, k.look, 2.0)

    got = looks.run_study([key, good], {"m-1": "m.onnx"}, "spec", tmp_path, 2, runner=runner, progress=False)
    assert [r.key for r in got] == [good]
    assert "va000" in capsys.readouterr().err


def test_bad_arguments_are_refused_with_a_reason(capsys):
    assert looks.main(["--model", "truth", "--looks", "va999"]) == 2
    assert "va999" in capsys.readouterr().err
    assert looks.main(["--model", "truth", "--turns", "2,-1.5"]) == 2
    assert "PITCH:YAW" in capsys.readouterr().err
    assert looks.main(["--model", "no/such/model.onnx"]) == 2
    assert "no such file" in capsys.readouterr().err


def test_model_tags_follow_the_files_content(tmp_path):
    a, b = tmp_path / "x" / "oibarnet.onnx", tmp_path / "y" / "oibarnet.onnx"
    a.parent.mkdir()
    b.parent.mkdir()
    a.write_bytes(b"one")
    b.write_bytes(b"two")
    assert looks.model_tag(str(a)) != looks.model_tag(str(b))
    b.write_bytes(b"one")
    assert looks.model_tag(str(a)) == looks.model_tag(str(b))


def test_the_rig_command_line_takes_the_studys_start_seed_and_turn(tmp_path, monkeypatch):
    """The study's command line, parsed by the rig's own: the scenario flown has the start
    range, seed and turn asked for, and the JSON carries the capture."""
    flown = {}

    class Done:
        outcome, passed, sim_time_s, wall_time_s, speed_factor = "completed", True, 1.0, 1.0, 1.0
        metrics = {"nav": "truth"}
        capture = {"lateral_m": 0.002}
        checks: list = []
        report_path = None

    def fake_run(sc, **kw):
        flown["sc"], flown["nav"] = sc, kw["nav"]
        Done.scenario = sc
        return Done()

    monkeypatch.setattr(cli, "run_scenario", fake_run)
    key = RunKey("truth", "va000", 9.0, 7, (-2.0, 1.5))
    cmd = looks.rig_command(key, "truth", "models/scenes/val.json", tmp_path, tmp_path / "r.json")
    assert cmd[1:3] == ["-m", "oibar_hil.rig.cli"]
    assert cli.main(cmd[3:]) == 0
    sc = flown["sc"]
    assert flown["nav"] == "truth"
    assert sc.start.range_m == 9.0 and sc.seed == 7 and tuple(sc.start.misalignment_deg) == (-2.0, 1.5)
    got = looks.result_from_json(key, json.loads((tmp_path / "r.json").read_text()))
    assert got.capture_lateral_m == pytest.approx(0.002)


def test_the_cache_follows_the_flight_code(tmp_path):
    """Runs are cached per flight-code version: an edit to the host's or the rig's code (a filter
    default, say) or to the firmware the simulated MCU is built from gives another code tag; an
    edit to the study itself, or to the probe, does not."""
    rels = (
        "host/oibar/nav/filter.py",
        "hil/oibar_hil/rig/runner.py",
        "hil/oibar_hil/rig/looks.py",
        "hil/oibar_hil/rig/probe.py",
        "firmware/app/latch.c",
        "proto/oibar.proto",
    )
    for rel in rels:
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("x = 1\n")
    tags = {looks.code_tag(tmp_path)}
    for rel in ("hil/oibar_hil/rig/looks.py", "hil/oibar_hil/rig/probe.py"):
        (tmp_path / rel).write_text("x = 2\n")
        assert looks.code_tag(tmp_path) in tags, rel
    for rel in ("host/oibar/nav/filter.py", "firmware/app/latch.c", "proto/oibar.proto"):
        (tmp_path / rel).write_text("x = 2\n")
        tag = looks.code_tag(tmp_path)
        assert tag not in tags, rel
        tags.add(tag)


def test_the_held_out_looks_are_the_validation_looks_no_choice_used(capsys):
    from oibar_hil.dataset import load_spec_file

    names = {s.name for s in load_spec_file(looks.REPO_ROOT / looks.DEFAULT_SPEC)}
    assert not set(looks.HELD_OUT_LOOKS) & set(looks.DEFAULT_LOOKS)
    assert set(looks.HELD_OUT_LOOKS) | set(looks.DEFAULT_LOOKS) == names
    # a set's name stands for its looks; only a name that is neither is refused
    assert looks.main(["--model", "truth", "--looks", "held-out,va999"]) == 2
    err = capsys.readouterr().err
    assert "['va999']" in err and "held-out" not in err


def test_the_json_says_which_flight_code_flew_the_runs(tmp_path, monkeypatch):
    """A rebase of the ship rule's loop base checks the code its runs were flown under."""
    import json

    monkeypatch.setattr(looks, "run_study", lambda keys, *a, **k: [_r(keys[0].model, "va000", 2.0)])
    monkeypatch.setattr(looks, "code_tag", lambda *a, **k: "c0ffee1234")
    out = tmp_path / "runs.json"
    args = ["--model", "truth", "--looks", "va000", "--out", str(tmp_path / "cache"), "--json", str(out)]
    assert looks.main([*args, "--no-progress"]) == 0
    doc = json.loads(out.read_text())
    assert doc["code_tag"] == "c0ffee1234" and len(doc["runs"]) == 1
