"""The ship rule (oibar_models.judge) on the committed figures of earlier candidates, and each
clause on figures made to fail it."""

import copy
import json
import sys
from pathlib import Path

import pytest

from oibar_models.judge import (
    BASE_LOOP,
    DEMO_SCENE,
    JudgeInputError,
    Rule,
    _failing,
    judge_demo,
    judge_looks,
    judge_loop,
    judge_probe,
    judge_rolls,
    judge_validation,
    looks_rendered,
    main,
    next_base,
)

# Earlier candidates' figures, the cases the rule was written against (once in docs/data; the
# probes kept without their per-frame records, which the rule does not read; the whole files are
# in MLflow's history experiment, oibar_models.history).
DATA = Path(__file__).resolve().parent / "judge_cases"
GRAPH = (["Conv", "Relu"], [(8, 3, 3, 3), (8,)])
# The figures these tests check were measured against 0.15.3's probe and loop (the bases until a
# model ships after it); BASE_PROBE / BASE_LOOP are whatever the shipped model's are.
PROBE_0153 = DATA / "probe_val_0153.json"
LOOP_0153 = DATA / "loop_candidate_0153.json"


def _json(name):
    return json.loads((DATA / name).read_text())


def test_candidate_0200_passes_validation_and_fails_the_probe_as_its_card_records():
    v1 = judge_validation(_json("eval_val_candidate_0200.json"), "0.15.3", "0.20.0", GRAPH, GRAPH)
    assert v1.holds, v1.text()
    assert v1.figures["candidate"]["dq_mean_deg"] == pytest.approx(0.5062, abs=1e-4)
    v2 = judge_probe(json.loads(PROBE_0153.read_text()), _json("probe_val_0200.json"))
    assert not v2.holds
    assert "3 m meas_view_slope" in _failing(v2)  # 0.935 -> 0.915, 2.3 SE


def _as_flown(paired_runs):
    """A paired file's runs (its 'new' arm) as `oibar_hil.rig.looks --json` writes them."""
    return [
        {
            "key": {
                "look": r["look"],
                "start_range_m": r["start_m"],
                "seed": r["seed"],
                "turn_deg": r["turn"],
            },
            "outcome": r["outcome_new"],
            "lateral_p95_below_5m_m": r["lat_p95_new_cm"] / 100,
            "capture_lateral_m": r["capture_new_mm"] / 1000,
        }
        for r in paired_runs
    ]


def test_candidate_0200s_loop_study_fails_on_the_default_runs_as_its_card_records():
    study = _json("loop_study_0200.json")
    flown = {label: {"runs": _as_flown(study[label]["runs"])} for label in ("held_out", "default")}
    v = judge_loop(json.loads(LOOP_0153.read_text()), flown)
    assert not v.holds
    assert "default: paired lateral p95 below 5 m" in _failing(v)  # +0.74 +- 0.21 cm
    assert v.figures["default"]["paired_diff_cm"] == pytest.approx(0.74, abs=0.01)
    assert "held_out: every run docks" not in _failing(v)
    # a run of the base not flown, and a run that does not dock, each fail their clause
    short = copy.deepcopy(flown)
    short["held_out"]["runs"].pop()
    short["held_out"]["runs"][0]["outcome"] = "aborted"
    failing = _failing(judge_loop(json.loads(LOOP_0153.read_text()), {"held_out": short["held_out"]}))
    assert "held_out: every base run flown" in failing and "held_out: every run docks" in failing


def _eval(att=0.55, pos=0.30, cpos=99.9, catt=99.8):
    arm = {
        "_all": {
            "dq_mean_deg": att,
            "dt_mean_pct": pos,
            "compliance_pos_pct": cpos,
            "compliance_att_pct": catt,
        }
    }
    base = {
        "_all": {
            "dq_mean_deg": 0.56,
            "dt_mean_pct": 0.30,
            "compliance_pos_pct": 99.9,
            "compliance_att_pct": 99.8,
        }
    }
    return {"val": {"oibarnet 0.9.9 tracking": arm, "oibarnet 0.15.3 tracking": base}}


@pytest.mark.parametrize(
    "change, clause",
    [
        ({"att": 0.555}, "attitude better"),  # better, but by less than 0.01 deg
        ({"pos": 0.315}, "position held"),
        ({"cpos": 99.8}, "compliance_pos held"),
        ({"catt": 99.7}, "compliance_att held"),
    ],
)
def test_each_validation_clause_fails_on_its_own(change, clause):
    assert judge_validation(_eval(), "0.15.3", "0.9.9", GRAPH, GRAPH).holds
    v = judge_validation(_eval(**change), "0.15.3", "0.9.9", GRAPH, GRAPH)
    assert _failing(v) == [clause]
    other = (GRAPH[0], [(8, 3, 5, 5), (8,)])
    assert _failing(judge_validation(_eval(), "0.15.3", "0.9.9", GRAPH, other)) == ["same graph"]


def test_a_pairs_far_network_must_have_the_shipped_graph_too():
    """A candidate with a far network (oibar.far_network) reads each window with one of two
    networks: both must be the shipped graph for the cost per crop to stay the shipped one's."""
    assert judge_validation(_eval(), "0.15.3", "0.9.9", GRAPH, GRAPH, cand_far_graph=GRAPH).holds
    other = (GRAPH[0] + ["Relu"], GRAPH[1])
    v = judge_validation(_eval(), "0.15.3", "0.9.9", GRAPH, GRAPH, cand_far_graph=other)
    assert _failing(v) == ["same graph (far network)"]


def test_a_validation_without_both_arms_or_with_one_version_is_refused():
    with pytest.raises(JudgeInputError, match="version 0.9.8"):
        judge_validation(_eval(), "0.15.3", "0.9.8", GRAPH, GRAPH)
    with pytest.raises(JudgeInputError, match="its own"):
        judge_validation(_eval(), "0.15.3", "0.15.3", GRAPH, GRAPH)
    with pytest.raises(JudgeInputError, match="validation"):
        judge_validation({"test": {}}, "0.15.3", "0.9.9", GRAPH, GRAPH)


def _cold(pos, att, cpos, catt, silent, frames=229):
    return {
        "_all": {
            "frames": frames,
            "dt_mean_pct": pos,
            "dq_mean_deg": att,
            "compliance_pos_pct": cpos,
            "compliance_att_pct": catt,
            "silent_failures": silent,
        }
    }


def _looks(matched=None, lab=None):
    """Part 1b's evaluation: 0.34.0 beside a candidate, each look every 2nd frame read cold, the
    model card's figures (2026-12-05, "A CPU fine-tune ..."): the matched look read by 0.35.1, the
    lab look by its fine-tuned network."""
    return {
        "val_mitsuba": {
            "oibarnet 0.34.0 cold": _cold(0.50, 1.25, 100.0, 100.0, 0),
            "oibarnet 0.35.1 cold": _cold(*(matched or (0.65, 1.03, 100.0, 100.0, 0))),
        },
        "val_lab": {
            "oibarnet 0.34.0 cold": _cold(5.27, 4.74, 55.0, 59.8, 87),
            "oibarnet 0.35.1 cold": _cold(*(lab or (4.16, 1.75, 97.8, 98.7, 2))),
        },
    }


@pytest.mark.parametrize(
    "look, change, clause",
    [
        # 0.15 % of range given for 0.22 deg holds (the paper's score); worse by 0.0024 does not
        ("matched", (0.65, 1.30, 100.0, 100.0, 0), "val_mitsuba: score held"),
        ("matched", (0.50, 1.25, 99.4, 100.0, 0), "val_mitsuba: compliance_pos held"),
        ("matched", (0.50, 1.25, 100.0, 99.4, 0), "val_mitsuba: compliance_att held"),
        ("matched", (0.50, 1.25, 100.0, 100.0, 1), "val_mitsuba: silent failures held"),
        ("lab", (4.16, 1.75, 97.8, 98.7, 88), "val_lab: silent failures held"),
        ("lab", (4.16, 1.75, 54.4, 98.7, 2), "val_lab: compliance_pos held"),
    ],
)
def test_each_looks_clause_fails_on_its_own(look, change, clause):
    """Part 1b: the second renderer's looks must not lose what the shipped model transfers."""
    assert judge_looks(_looks(), "0.34.0", "0.35.1").holds
    v = judge_looks(_looks(**{look: change}), "0.34.0", "0.35.1")
    assert _failing(v) == [clause]
    # within the slack: one frame in 229 out of the matched look's bounds more
    assert judge_looks(_looks(matched=(0.50, 1.25, 99.6, 100.0, 0)), "0.34.0", "0.35.1").holds


def test_a_looks_evaluation_that_cannot_be_judged_is_refused():
    ev = _looks()
    with pytest.raises(JudgeInputError, match="its own"):
        judge_looks(ev, "0.34.0", "0.34.0")
    with pytest.raises(JudgeInputError, match="make dataset-looks"):
        judge_looks({"val_mitsuba": ev["val_mitsuba"]}, "0.34.0", "0.35.1")
    with pytest.raises(JudgeInputError, match="cold arms of version 0.35.2"):
        judge_looks(ev, "0.34.0", "0.35.2")
    short = copy.deepcopy(ev)
    short["val_lab"]["oibarnet 0.35.1 cold"]["_all"]["frames"] = 100
    with pytest.raises(JudgeInputError, match="229 / 100 frames"):
        judge_looks(short, "0.34.0", "0.35.1")


def test_a_candidate_that_answers_no_look_frame_fails_the_score():
    """kp_evaluate writes no means for an arm without an answer: that is the worst score, not a pass."""
    ev = _looks()
    ev["val_lab"]["oibarnet 0.35.1 cold"]["_all"] = {"frames": 229, "silent_failures": 0}
    v = judge_looks(ev, "0.34.0", "0.35.1")
    assert "val_lab: score held" in _failing(v)


def _rolls(cand=None):
    """Part 1c's evaluation: the roll sweep's 401 frames read cold, the figures measured on
    2026-12-07: 0.35.15 (here the shipped arm) and 0.35.18 with its any-turn flag (the candidate)."""
    return {
        "val_roll": {
            "oibarnet 0.34.0 cold": _cold(10.64, 22.86, 85.8, 75.8, 29, frames=401),
            "oibarnet 0.35.1 cold": _cold(*(cand or (2.70, 1.74, 98.8, 97.5, 0)), frames=401),
        }
    }


@pytest.mark.parametrize(
    "cand, clause",
    [
        # a model that reads rolls like the shipped one but one more frame silently wrong
        ((10.64, 22.86, 85.8, 75.8, 30), "val_roll: silent failures held"),
        ((10.64, 22.86, 85.0, 75.8, 29), "val_roll: compliance_pos held"),
        ((10.64, 22.86, 85.8, 75.0, 29), "val_roll: compliance_att held"),
        ((10.84, 22.86, 85.8, 75.8, 29), "val_roll: score held"),
    ],
)
def test_each_roll_sweep_clause_fails_on_its_own(cand, clause):
    """Part 1c: a candidate must not read fewer rolls than the shipped model; one that reads them
    all (0.35.18's figures) holds against 0.35.15's."""
    assert judge_rolls(_rolls(), "0.34.0", "0.35.1").holds
    v = judge_rolls(_rolls(cand), "0.34.0", "0.35.1")
    assert v.part.startswith("1c") and _failing(v) == [clause]
    # the other way round (a shipped model that reads every roll, a candidate that does not) fails
    # every clause
    back = {"val_roll": {"oibarnet 0.34.0 cold": _rolls()["val_roll"]["oibarnet 0.35.1 cold"],
                         "oibarnet 0.35.1 cold": _rolls()["val_roll"]["oibarnet 0.34.0 cold"]}}  # fmt: skip
    assert len(_failing(judge_rolls(back, "0.34.0", "0.35.1"))) == 4


def test_a_roll_sweep_not_evaluated_is_refused_naming_its_target():
    with pytest.raises(JudgeInputError, match="make dataset-val-roll"):
        judge_rolls(_looks(), "0.34.0", "0.35.1")


def test_the_rolls_command_judges_an_evaluation_made_already(tmp_path, monkeypatch):
    import oibar_models.judge as judge

    monkeypatch.setattr(judge, "_version", lambda p: "0.35.1" if "cand" in str(p) else "0.34.0")
    ok, lost = tmp_path / "ok.json", tmp_path / "lost.json"
    ok.write_text(json.dumps(_rolls()))
    lost.write_text(json.dumps(_rolls((10.64, 22.86, 85.8, 75.8, 31))))
    out = ["--out", str(tmp_path / "out")]
    assert main([*out, "rolls", str(ok), "--candidate", "cand.onnx"]) == 0
    assert json.loads((tmp_path / "out" / "part1c.json").read_text())["holds"] is True
    assert main([*out, "rolls", str(lost), "--candidate", "cand.onnx"]) == 1
    assert main([*out, "rolls", str(tmp_path / "missing.json"), "--candidate", "cand.onnx"]) == 2


def test_looks_rendered_names_each_scene_not_rendered(tmp_path):
    from oibar_models.kp_evaluate import SETS
    from oibar_models.scenes import load_set

    repo = Path(__file__).resolve().parents[2]
    names = []
    for look in ("val_mitsuba", "val_lab"):
        spec, data = SETS[look]
        (tmp_path / spec).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / spec).write_text((repo / spec).read_text())
        for sc in load_set(repo / spec):
            (tmp_path / data / sc.name).mkdir(parents=True)
            (tmp_path / data / sc.name / "manifest.json").write_text("{}")
            names.append(f"{data}/{sc.name}")
    assert looks_rendered(tmp_path) == ""
    (tmp_path / names[-1] / "manifest.json").unlink()  # a scene cut off before its manifest
    assert looks_rendered(tmp_path) == names[-1]


def _probe(slope, se):
    return {"scenes": "v", "rows": [{"range_m": 3.0, "view_slope": slope, "view_slope_se": se}]}


def test_a_probe_slope_fails_beyond_two_se_or_leaving_the_band():
    assert judge_probe(_probe(0.95, 0.005), _probe(0.94, 0.005)).holds  # 1.4 SE
    assert not judge_probe(_probe(0.95, 0.005), _probe(0.93, 0.005)).holds  # 2.8 SE
    assert judge_probe(_probe(0.95, 0.005), _probe(1.03, 0.005)).holds  # as far from 1, other side
    # within the SE, but out of the 0.1 band the base was in
    assert not judge_probe(_probe(0.91, 0.05), _probe(0.89, 0.05)).holds
    assert judge_probe(_probe(0.85, 0.05), _probe(0.84, 0.05)).holds  # the base was out already
    assert judge_probe(_probe(0.95, 0.0), _probe(0.95, 0.0)).holds  # no spread at all: not worse
    assert not judge_probe(_probe(0.95, 0.0), _probe(0.94, 0.0)).holds
    with pytest.raises(JudgeInputError, match="other scenes"):
        judge_probe(_probe(0.9, 0.01), {**_probe(0.9, 0.01), "scenes": "seq01"})


def _demo(lat_m=0.03, cap_m=0.002, p99=45.0, passed=True, scene=DEMO_SCENE):
    return [
        {
            "scene": scene,
            "outcome": "completed",
            "passed": passed,
            "metrics": {"nav_lateral_err_m_p95_below_5m": lat_m, "nav_ms_p99": p99},
            "capture": {"lateral_m": cap_m},
        }
    ]


def test_each_demo_clause_fails_on_its_own():
    assert judge_demo(_demo()).holds
    assert _failing(judge_demo(_demo(lat_m=0.051))) == ["lateral p95 below 5 m"]
    assert _failing(judge_demo(_demo(cap_m=0.011))) == ["capture off the axis"]
    assert _failing(judge_demo(_demo(p99=50.5))) == ["navigator p99"]
    assert _failing(judge_demo(_demo(passed=False))) == ["mission passes"]
    with pytest.raises(JudgeInputError):
        judge_demo({"metrics": {}})


def test_the_demos_lateral_clause_holds_within_5_cm_or_near_the_shipped_models_flight():
    """Beyond 5 cm the candidate holds when the shipped model, flown on the same scene, is no more
    than 0.5 cm better (0.34.0 flew 21.3 cm on today's renderer, where the 5 cm was written for
    its 3.76 cm)."""
    cand = _demo(lat_m=0.055)
    assert _failing(judge_demo(cand)) == ["lateral p95 below 5 m"]
    assert judge_demo(cand, shipped=_demo(lat_m=0.213)).holds
    assert judge_demo(cand, shipped=_demo(lat_m=0.051)).holds  # 5.5 <= 5.1 + 0.5
    assert _failing(judge_demo(cand, shipped=_demo(lat_m=0.049))) == ["lateral p95 below 5 m"]
    # within 5 cm it holds whatever the shipped model flew
    v = judge_demo(_demo(lat_m=0.045), shipped=_demo(lat_m=0.02))
    assert v.holds and v.figures["shipped_lateral_p95_below_5m_cm"] == pytest.approx(2.0)
    # the shipped model's flight counts only on the candidate's scene
    with pytest.raises(JudgeInputError, match="other scenes"):
        judge_demo(cand, shipped=_demo(lat_m=0.213, scene="models/scenes/val.json:va001"))


@pytest.mark.parametrize("scene", ["seq01", "seq08", "models/scenes/test.json:seq01"])
def test_a_demo_flown_on_a_test_sequence_is_refused(scene, tmp_path, capsys):
    with pytest.raises(JudgeInputError, match="test sequence"):
        judge_demo(_demo(scene=scene))
    with pytest.raises(JudgeInputError, match="test sequence"):
        judge_demo(_demo(), shipped=_demo(scene=scene))
    f = tmp_path / "demo.json"
    f.write_text(json.dumps(_demo(scene=scene)))
    assert main(["--out", str(tmp_path), "demo", str(f)]) == 2
    assert "a test sequence" in capsys.readouterr().err


def test_the_command_line_writes_the_verdict_and_says_so_in_its_exit_code(tmp_path, capsys, monkeypatch):
    import oibar_models.judge as judge

    monkeypatch.setattr(judge, "BASE_PROBE", PROBE_0153)
    assert main(["--out", str(tmp_path), "probe", str(DATA / "probe_val_0200.json")]) == 1
    verdict = json.loads((tmp_path / "part2.json").read_text())
    assert verdict["holds"] is False and "FAILS" in capsys.readouterr().out
    assert main(["--out", str(tmp_path), "probe", str(DATA / "probe_val_0153.json")]) == 0
    assert main(["--out", str(tmp_path), "probe", str(tmp_path / "missing.json")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["--out", str(tmp_path), "pair", "sideways=x.json"]) == 2
    # part 1b from an evaluation made already
    monkeypatch.setattr(judge, "_version", lambda p: "0.34.0" if p == judge.SHIPPED else "0.35.1")
    ev = tmp_path / "looks.json"
    ev.write_text(json.dumps(_looks(lab=(4.16, 1.75, 97.8, 98.7, 88))))
    assert main(["--out", str(tmp_path), "looks", str(ev), "--candidate", "c.onnx"]) == 1
    assert json.loads((tmp_path / "part1b.json").read_text())["holds"] is False
    ev.write_text(json.dumps(_looks()))
    assert main(["--out", str(tmp_path), "looks", str(ev), "--candidate", "c.onnx"]) == 0


def _other_code(monkeypatch, tag="0123456789"):
    """Today's flight code as `tag` (the committed base records the code it was flown under)."""
    import oibar_hil.rig.looks as looks

    monkeypatch.setattr(looks, "code_tag", lambda *a, **k: tag)


def _moved(runs, cm):
    """The base's runs with every lateral p95 `cm` larger: the same model under other flight code."""
    return [dict(r, lat_p95_new_cm=r["lat_p95_new_cm"] + cm) for r in runs]


def test_a_step_writes_its_log_into_an_out_folder_not_made_yet(tmp_path):
    """`judge loop --out DIR` on a fresh clone: its first step (the spot check) logs into DIR,
    which no earlier part made; a failing step still says where its log is."""
    import oibar_models.judge as judge

    log = tmp_path / "judge" / "spot.log"
    judge._run([sys.executable, "-c", "print('flown')"], log)
    assert log.read_text().strip() == "flown"
    with pytest.raises(judge.JudgeInputError, match="exit 3"):
        judge._run([sys.executable, "-c", "raise SystemExit(3)"], tmp_path / "again" / "x.log")


def test_the_loop_flies_the_bases_runs_held_out_first_and_pairs_them(tmp_path, monkeypatch):
    """Part 4's command: each set's looks, starts, seeds and turns are the base's own, the held-out
    set first, flown by the shipped model and then the candidate; a candidate that flies exactly
    as the shipped model does today holds."""
    import oibar_models.judge as judge

    _other_code(monkeypatch)

    base = json.loads(BASE_LOOP.read_text())
    cmds = []

    def fake_run(cmd, log):
        cmds.append(cmd)
        label = "held_out" if cmd[cmd.index("--looks") + 1] == "held-out" else "default"
        Path(cmd[cmd.index("--json") + 1]).write_text(json.dumps({"runs": _as_flown(base[label]["runs"])}))

    monkeypatch.setattr(judge, "_run", fake_run)
    assert judge.fly_loop(Path("cand.onnx"), tmp_path, jobs=2, shipped=Path("shipped.onnx"))
    assert [(c[c.index("--looks") + 1], c[c.index("--model") + 1]) for c in cmds] == [
        ("held-out", "shipped.onnx"),
        ("held-out", "cand.onnx"),
        ("default", "shipped.onnx"),
        ("default", "cand.onnx"),
    ]
    held, default = cmds[1], cmds[3]
    assert held[held.index("--seeds") + 1] == "1" and default[default.index("--seeds") + 1] == "1,2"
    assert "--turns=-2:1.5,2:-1.5" in held and held[held.index("--starts") + 1] == "10"
    assert json.loads((tmp_path / "part4.json").read_text())["holds"] is True


def test_the_loop_pairs_the_candidate_with_the_shipped_runs_flown_under_the_same_code(tmp_path, monkeypatch):
    """The flight code moves the runs of one model (2026-11-29: 0.15.3's held-out runs differ from
    its committed ones by up to 1.3 cm): a candidate is paired with the shipped model flown today,
    not with the committed figures, and how far those moved is reported beside the verdict."""
    import oibar_models.judge as judge

    _other_code(monkeypatch)

    base = json.loads(BASE_LOOP.read_text())

    def fly(shipped_cm, cand_cm):
        def fake_run(cmd, log):
            label = "held_out" if cmd[cmd.index("--looks") + 1] == "held-out" else "default"
            cm = shipped_cm if cmd[cmd.index("--model") + 1] == "shipped.onnx" else cand_cm
            runs = _as_flown(_moved(base[label]["runs"], cm))
            Path(cmd[cmd.index("--json") + 1]).write_text(json.dumps({"runs": runs}))

        monkeypatch.setattr(judge, "_run", fake_run)
        ok = judge.fly_loop(Path("cand.onnx"), tmp_path, jobs=2, shipped=Path("shipped.onnx"))
        return ok, json.loads((tmp_path / "part4.json").read_text())

    # today's code moves every run 0.8 cm; the candidate flies as the shipped model: it holds
    ok, v = fly(0.8, 0.8)
    assert ok and v["figures"]["held_out"]["shipped_moved_cm"] == pytest.approx(0.8)
    assert v["figures"]["held_out"]["paired_diff_cm"] == pytest.approx(0.0, abs=1e-9)
    # the same candidate against the committed figures would have failed
    flown = {"held_out": {"runs": _as_flown(_moved(base["held_out"]["runs"], 0.8))}}
    assert not judge_loop(base, flown).holds
    # and a candidate 0.8 cm worse than the shipped model today fails, the code unmoved or not
    assert not fly(0.0, 0.8)[0] and not fly(0.8, 1.6)[0]


def test_pair_takes_the_shipped_runs_flown_beside_the_candidate(tmp_path):
    base = json.loads(BASE_LOOP.read_text())
    shipped, cand = tmp_path / "shipped.json", tmp_path / "cand.json"
    shipped.write_text(json.dumps({"runs": _as_flown(_moved(base["held_out"]["runs"], 0.8))}))
    cand.write_text(json.dumps({"runs": _as_flown(_moved(base["held_out"]["runs"], 0.8))}))
    out = ["--out", str(tmp_path)]
    assert main(out + ["pair", f"held_out={cand}"]) == 1  # against the committed figures
    assert main(out + ["pair", f"held_out={cand}", "--shipped", f"held_out={shipped}"]) == 0
    short = tmp_path / "short.json"
    short.write_text(json.dumps({"runs": _as_flown(base["held_out"]["runs"][:5])}))
    assert main(out + ["pair", f"held_out={cand}", "--shipped", f"held_out={short}"]) == 2


def test_a_candidate_that_is_no_model_file_is_refused_with_its_reason(tmp_path, capsys):
    bad = tmp_path / "oibarnet.onnx"
    bad.write_bytes(b"not onnx")
    assert (
        main(
            [
                "--out",
                str(tmp_path),
                "validation",
                str(DATA / "eval_val_candidate_0200.json"),
                "--candidate",
                str(bad),
            ]
        )
        == 2
    )
    assert str(bad) in capsys.readouterr().err


def test_a_shipped_candidates_loop_becomes_the_next_base_in_the_bases_layout(tmp_path):
    base = json.loads(BASE_LOOP.read_text())
    # The base's own runs flown again, unchanged: part 4 holds (paired difference 0) ...
    again = {label: {"runs": _as_flown(base[label]["runs"])} for label in ("held_out", "default")}
    nb = next_base(base, again, "test")
    for label in ("held_out", "default"):
        assert nb[label]["n"] == len(base[label]["runs"])
        assert nb[label]["paired_diff_cm"] == pytest.approx(0.0, abs=1e-9)
        for new, old in zip(nb[label]["runs"], base[label]["runs"], strict=True):
            assert new["lat_p95_base_cm"] == pytest.approx(old["lat_p95_new_cm"], abs=1e-4)
    # ... and the next candidate is paired against what this one flew: the same runs tie.
    assert judge_loop(nb, again).holds
    # A loop that fails part 4 never becomes a base, nor does one missing a set.
    study = _json("loop_study_0200.json")
    failing = {label: {"runs": _as_flown(study[label]["runs"])} for label in ("held_out", "default")}
    with pytest.raises(JudgeInputError, match="do not pass"):
        next_base(json.loads(LOOP_0153.read_text()), failing, "test")
    with pytest.raises(JudgeInputError, match="every set"):
        next_base(base, {"held_out": again["held_out"]}, "test")
    # The CLI writes it.
    f = tmp_path / "base.json"
    held, dflt = tmp_path / "h.json", tmp_path / "d.json"
    held.write_text(json.dumps(again["held_out"]))
    dflt.write_text(json.dumps(again["default"]))
    assert main(["--out", str(tmp_path), "base", "--what", "t", "--out-file", str(f),
                 f"held_out={held}", f"default={dflt}"]) == 0  # fmt: skip
    assert json.loads(f.read_text())["default"]["n"] == len(base["default"]["runs"])


def test_the_next_base_pairs_with_the_shipped_runs_flown_beside_the_candidate(tmp_path, capsys):
    """A ship whose part 4 was paired with the shipped model flown under today's code writes its
    next base from the same pairing: the ``*_base`` fields are today's shipped runs."""
    base = json.loads(BASE_LOOP.read_text())
    files = {}
    for label in ("held_out", "default"):
        for who in ("shipped", "cand"):
            files[label, who] = tmp_path / f"{label}_{who}.json"
            files[label, who].write_text(json.dumps({"runs": _as_flown(_moved(base[label]["runs"], 0.8))}))
    f = tmp_path / "next.json"
    cli = ["--out", str(tmp_path), "base", "--what", "t", "--out-file", str(f)]
    cand = [f"held_out={files['held_out', 'cand']}", f"default={files['default', 'cand']}"]
    # against the committed figures the moved runs do not pass: nothing is written
    assert main(cli + cand) == 2 and not f.exists()
    assert "do not pass" in capsys.readouterr().err
    shipped = [f"held_out={files['held_out', 'shipped']}", f"default={files['default', 'shipped']}"]
    assert main(cli + cand + ["--shipped", *shipped]) == 0
    nb = json.loads(f.read_text())
    for label in ("held_out", "default"):
        assert nb[label]["paired_diff_cm"] == pytest.approx(0.0, abs=1e-9)
        for new, old in zip(nb[label]["runs"], base[label]["runs"], strict=True):
            assert new["lat_p95_base_cm"] == pytest.approx(old["lat_p95_new_cm"] + 0.8, abs=1e-4)


# --- the worst run flown again on fresh seeds (Rule.loop_refly_seeds, 2026-12-01) -------------

LOOP_0320 = DATA / "loop_candidate_0320.json"
VA001_SEEDS = (5, 6, 7, 8, 9, 10)  # the committed va001 study's seeds (loop_study_va001_0330.json)


def _refly_of(study, cand_cm=0.0, outcome=None):
    """A looks study with two models (the shipped one first), the candidate's runs moved by
    `cand_cm` (and given `outcome`)."""
    study = copy.deepcopy(study)
    cand = list(study["labels"])[1]
    for r in study["runs"]:
        if r["key"]["model"] == cand:
            r["lateral_p95_below_5m_m"] += cand_cm / 100
            if outcome:
                r["outcome"] = outcome
    return study


def test_candidate_0330s_worst_run_alone_fails_and_its_looks_fresh_seeds_decide():
    """0.33.0's held-out part 4 (committed): the mean ties, the worst run (va001) is 0.88 cm worse;
    that alone no longer fails it: va001 flown again on fresh seeds decides. On the committed
    study's twelve fresh pairs (-0.49 +- 0.44 cm) it holds; those runs 1 cm worse fail it."""
    base = json.loads(LOOP_0320.read_text())
    flown = {"held_out": _json("loop_held_out_0330.json")}
    v = judge_loop(base, flown)
    assert _failing(v) == ["held_out: worst run"]
    assert v.figures["held_out"]["refly_look"] == "va001"
    rule = Rule(loop_refly_seeds=VA001_SEEDS)
    study = _json("loop_study_va001_0330.json")
    v = judge_loop(base, flown, rule, refly={"held_out": study})
    assert v.holds, v.text()
    assert v.figures["held_out"]["refly"]["paired_diff_cm"] == pytest.approx(-0.49, abs=0.01)
    assert v.figures["held_out"]["refly"]["n"] == 12
    worse = judge_loop(base, flown, rule, refly={"held_out": _refly_of(study, cand_cm=1.0)})
    assert _failing(worse) == ["held_out: worst run"]
    undocked = judge_loop(base, flown, rule, refly={"held_out": _refly_of(study, outcome="aborted")})
    assert _failing(undocked) == ["held_out: worst run"]


def test_a_reflight_that_is_not_the_plan_is_refused():
    base = json.loads(LOOP_0320.read_text())
    flown = {"held_out": _json("loop_held_out_0330.json")}
    study = _json("loop_study_va001_0330.json")
    # the rule's own seeds (101-106) were not flown in the committed study
    with pytest.raises(JudgeInputError, match="0 of its 12 planned runs"):
        judge_loop(base, flown, refly={"held_out": study})
    # a run short
    short = copy.deepcopy(study)
    short["runs"].pop()
    with pytest.raises(JudgeInputError, match="11 of its 12"):
        judge_loop(base, flown, Rule(loop_refly_seeds=VA001_SEEDS), refly={"held_out": short})
    # seeds that are the base's own are not fresh
    with pytest.raises(JudgeInputError, match="not fresh"):
        judge_loop(base, flown, Rule(loop_refly_seeds=(1, 5)), refly={"held_out": study})
    # one model only
    one = copy.deepcopy(study)
    one["labels"] = dict(list(one["labels"].items())[:1])
    with pytest.raises(JudgeInputError, match="two models"):
        judge_loop(base, flown, Rule(loop_refly_seeds=VA001_SEEDS), refly={"held_out": one})


def _looks_of(runs, model):
    return [dict(r, key=dict(r["key"], model=model)) for r in runs]


def test_the_loop_flies_the_worst_runs_look_again_when_only_that_clause_fails(tmp_path, monkeypatch):
    """A candidate that flies as the shipped model except one held-out run 2 cm worse: part 4 flies
    that run's look again with both models on the fresh seeds, then goes on to the default set
    when the re-flight ties; when the candidate loses there too, it stops at the held-out set."""
    import oibar_models.judge as judge

    _other_code(monkeypatch)

    base = json.loads(BASE_LOOP.read_text())
    held = base["held_out"]["runs"]
    bad = max(range(len(held)), key=lambda i: held[i]["lat_p95_new_cm"])
    look = held[bad]["look"]

    def fly(refly_cm):
        cmds = []

        def fake_run(cmd, log):
            cmds.append(cmd)
            models = [cmd[i + 1] for i, c in enumerate(cmd) if c == "--model"]
            looks = cmd[cmd.index("--looks") + 1]
            out = Path(cmd[cmd.index("--json") + 1])
            if len(models) == 2:  # the re-flight: both models, the look, the fresh seeds
                seeds = [int(s) for s in cmd[cmd.index("--seeds") + 1].split(",")]
                runs = []
                for m, cm in (("ship", 0.0), ("cand", refly_cm)):
                    for seed in seeds:
                        for turn in ([-2.0, 1.5], [2.0, -1.5]):
                            runs.append({
                                "key": {"model": m, "look": looks, "start_range_m": 10.0, "seed": seed,
                                        "turn_deg": turn},
                                "outcome": "completed", "capture_lateral_m": 0.0015,
                                "lateral_p95_below_5m_m": (4.0 + 0.1 * seed + turn[0] + cm) / 100,
                            })  # fmt: skip
                out.write_text(json.dumps({"labels": {"ship": models[0], "cand": models[1]}, "runs": runs}))
                return
            label = "held_out" if looks == "held-out" else "default"
            runs = _as_flown(base[label]["runs"])
            if label == "held_out" and models[0] == "cand.onnx":
                runs[bad]["lateral_p95_below_5m_m"] += 0.02
            out.write_text(json.dumps({"runs": runs}))

        monkeypatch.setattr(judge, "_run", fake_run)
        ok = judge.fly_loop(Path("cand.onnx"), tmp_path, jobs=2, shipped=Path("shipped.onnx"))
        return ok, cmds, json.loads((tmp_path / "part4.json").read_text())

    ok, cmds, v = fly(0.0)
    assert ok, v
    refly = cmds[2]
    assert [refly[i + 1] for i, c in enumerate(refly) if c == "--model"] == ["shipped.onnx", "cand.onnx"]
    assert refly[refly.index("--looks") + 1] == look
    assert refly[refly.index("--seeds") + 1] == ",".join(map(str, Rule().loop_refly_seeds))
    assert len(cmds) == 5 and v["figures"]["held_out"]["refly"]["look"] == look
    ok, cmds, v = fly(0.5)
    assert not ok and len(cmds) == 3
    assert [c["clause"] for c in v["clauses"] if not c["holds"]] == ["held_out: worst run"]


def test_pair_reads_the_reflight(tmp_path, monkeypatch):
    """`judge pair --refly`: 0.33.0's held-out runs fail on the worst run alone against 0.32.0's
    base; va001's committed fresh pairs, given the rule's seeds, decide it (they hold; moved 1 cm
    worse they fail); the study on its own seeds (5-10) is not the rule's re-flight and is refused."""
    import oibar_models.judge as judge

    monkeypatch.setattr(judge, "BASE_LOOP", LOOP_0320)
    cand = DATA / "loop_held_out_0330.json"
    out = ["--out", str(tmp_path)]
    assert main(out + ["pair", f"held_out={cand}"]) == 1
    study = _json("loop_study_va001_0330.json")
    assert (
        main(out + ["pair", f"held_out={cand}", "--refly", f"held_out={DATA / 'loop_study_va001_0330.json'}"])
        == 2
    )
    as_rule = dict(zip(VA001_SEEDS, Rule().loop_refly_seeds, strict=True))
    for cm, rc in ((0.0, 0), (1.0, 1)):
        moved = _refly_of(study, cand_cm=cm)
        for r in moved["runs"]:
            r["key"]["seed"] = as_rule[r["key"]["seed"]]
        f = tmp_path / f"refly_{cm:g}.json"
        f.write_text(json.dumps(moved))
        assert main(out + ["pair", f"held_out={cand}", "--refly", f"held_out={f}"]) == rc
    assert (
        json.loads((tmp_path / "part4.json").read_text())["figures"]["held_out"]["refly"]["look"] == "va001"
    )


def test_a_base_flown_under_todays_code_is_the_shipped_arm_after_a_spot_check(tmp_path, monkeypatch):
    """The base records its flight code (0.32.0's: e18f7fcda7). Under that code the shipped model
    flies only each set's worst base run's look again; when those runs are the base's, the base is
    the arm (half of part 4's time saved); when one differs (another machine, say), the whole arm
    is flown as before; under other code, the whole arm without a spot check."""
    import oibar_models.judge as judge

    base = json.loads(BASE_LOOP.read_text())
    assert base["code_tag"]

    def fly(spot_cm):
        cmds = []

        def fake_run(cmd, log):
            cmds.append(cmd)
            looks = cmd[cmd.index("--looks") + 1]
            if looks in ("held-out", "default"):
                runs = _as_flown(base[looks.replace("-", "_")]["runs"])
            else:  # a spot check: one look of the set, moved `spot_cm`
                label = "held_out" if any(r["look"] == looks for r in base["held_out"]["runs"]) else "default"
                runs = _as_flown(_moved([r for r in base[label]["runs"] if r["look"] == looks], spot_cm))
            Path(cmd[cmd.index("--json") + 1]).write_text(json.dumps({"runs": runs}))

        monkeypatch.setattr(judge, "_run", fake_run)
        ok = judge.fly_loop(Path("cand.onnx"), tmp_path, jobs=2, shipped=Path("shipped.onnx"))
        flown = [(c[c.index("--looks") + 1], c[c.index("--model") + 1]) for c in cmds]
        return ok, flown, json.loads((tmp_path / "part4.json").read_text())

    worst = {
        k: max(base[k]["runs"], key=lambda r: r["lat_p95_new_cm"])["look"] for k in ("held_out", "default")
    }
    _other_code(monkeypatch, base["code_tag"])
    ok, flown, v = fly(0.0)
    assert ok and flown == [
        (worst["held_out"], "shipped.onnx"),
        ("held-out", "cand.onnx"),
        (worst["default"], "shipped.onnx"),
        ("default", "cand.onnx"),
    ]
    assert "the same" in v["figures"]["default"]["shipped_arm"]
    ok, flown, v = fly(0.01)  # this machine flies the shipped model 0.01 cm off: the whole arm
    assert ok and flown == [
        (worst["held_out"], "shipped.onnx"),
        ("held-out", "shipped.onnx"),
        ("held-out", "cand.onnx"),
        (worst["default"], "shipped.onnx"),
        ("default", "shipped.onnx"),
        ("default", "cand.onnx"),
    ]
    assert "differs" in v["figures"]["held_out"]["shipped_arm"]
    _other_code(monkeypatch)
    assert fly(0.0)[1] == [(k, m) for k in ("held-out", "default") for m in ("shipped.onnx", "cand.onnx")]


def test_a_rebase_makes_the_shipped_arm_flown_under_todays_code_the_base(tmp_path, monkeypatch, capsys):
    """The shipped model's 64 runs flown again under today's flight code become the base: its runs'
    shipped arm what they flew now, the code's tag today's (so part 4 under that code flies only the
    spot check), the ship's own figures kept and what moved recorded; a set or run missing is refused."""
    import oibar_models.judge as judge

    base = json.loads(BASE_LOOP.read_text())
    now = {label: {"runs": _as_flown(_moved(base[label]["runs"], 0.3))} for label in ("held_out", "default")}
    _other_code(monkeypatch, "feedc0de00")
    rb = judge.rebase(base, now, "0.34.0 flown again")
    assert rb["code_tag"] == "feedc0de00" and rb["verdict"] == base["verdict"]
    assert rb["rebased"][-1]["from_code_tag"] == base["code_tag"]
    for label in ("held_out", "default"):
        assert rb["rebased"][-1]["moved"][label]["mean_cm"] == pytest.approx(0.3, abs=1e-4)
        for old, new in zip(base[label]["runs"], rb[label]["runs"], strict=True):
            assert new["lat_p95_new_cm"] == pytest.approx(old["lat_p95_new_cm"] + 0.3, abs=1e-4)
            assert new["lat_p95_base_cm"] == old["lat_p95_base_cm"]
        assert rb[label]["lat_p95_new_cm"] == pytest.approx(base[label]["lat_p95_new_cm"] + 0.3, abs=1e-3)
        # today's flights are the rebased base's runs, not the committed one's
        assert judge.spot_check(rb, label, now[label]) == ""
        assert "cm" in judge.spot_check(base, label, now[label])
    with pytest.raises(JudgeInputError, match="default"):
        judge.rebase(base, {"held_out": now["held_out"]}, "one set")
    # a set flown under other code than today's is no base for today's
    stale = {**now, "default": {**now["default"], "code_tag": "0ld0ld0ld0"}}
    with pytest.raises(JudgeInputError, match="other flight code.*0ld0ld0ld0"):
        judge.rebase(base, stale, "stale")
    assert judge.rebase(base, {**now, "default": {**now["default"], "code_tag": "feedc0de00"}}, "x")
    short = {**now, "default": {"runs": now["default"]["runs"][1:]}}
    with pytest.raises(JudgeInputError, match="flew 39 of the base's 40"):
        judge.rebase(base, short, "a run missing")
    # from the command line, into a file part 4 reads as a base
    files = []
    for label in ("held_out", "default"):
        f = tmp_path / f"{label}.json"
        f.write_text(json.dumps(now[label]))
        files.append(f"{label}={f}")
    out = tmp_path / "rebased.json"
    assert main(["--out", str(tmp_path), "rebase", "--what", "test", "--out-file", str(out), *files]) == 0
    assert json.loads(out.read_text())["code_tag"] == "feedc0de00"
    assert "base under flight code feedc0de00" in capsys.readouterr().out


def test_the_next_base_records_the_flight_code(monkeypatch):
    base = json.loads(BASE_LOOP.read_text())
    again = {label: {"runs": _as_flown(base[label]["runs"])} for label in ("held_out", "default")}
    _other_code(monkeypatch, "abcdef0123")
    assert next_base(base, again, "test")["code_tag"] == "abcdef0123"


def test_part_2_judges_against_the_shipped_model_probed_in_the_same_run(tmp_path, monkeypatch, capsys):
    """The committed probe was drawn by the renderer of its day: 0.20.0's probe fails against
    0.15.3's committed one, and holds against a shipped model that reads today's frames as 0.20.0
    did. The run probes the shipped model beside the candidate and says the base moved."""
    import shutil
    import subprocess

    import oibar_models.judge as judge

    cand, base = tmp_path / "cand.onnx", tmp_path / "shipped.onnx"
    cand.write_bytes(b"c")
    base.write_bytes(b"s")
    monkeypatch.setattr(judge, "BASE_PROBE", PROBE_0153)
    probed = []

    def fake_run(cmd, log):
        if "oibar_models.kp_evaluate" in cmd:
            out = Path(cmd[cmd.index("--out") + 1])
            out.mkdir(parents=True, exist_ok=True)
            if "val_mitsuba" in cmd:
                (out / "eval.json").write_text(json.dumps(_looks_as(_looks(), "0.15.3", "0.20.0")))
            elif "val_roll" in cmd:
                (out / "eval.json").write_text(json.dumps(_looks_as(_rolls(), "0.15.3", "0.20.0")))
            else:
                shutil.copy(DATA / "eval_val_candidate_0200.json", out / "eval.json")
        elif "oibar_hil.rig.probe" in cmd:
            probed.append(Path(cmd[cmd.index("--model") + 1]))
            shutil.copy(DATA / "probe_val_0200.json", cmd[cmd.index("--json") + 1])

    flown = []

    def fake_demo(cmd, **kw):
        scene, model = cmd[cmd.index("--scene") + 1], Path(cmd[cmd.index("--model") + 1])
        flown.append((model, scene))
        lat_m = 0.055 if model == cand else 0.213  # the candidate beyond 5 cm, the shipped model far worse
        demo = {"metrics": {"nav_lateral_err_m_p95_below_5m": lat_m, "nav_ms_p99": 30.0}, "passed": True}
        demo |= {"scene": scene, "capture": {"lateral_m": 0.004}}
        Path(cmd[cmd.index("--json") + 1]).write_text(json.dumps([demo]))
        return 0

    monkeypatch.setattr(judge, "_run", fake_run)
    monkeypatch.setattr(judge, "looks_rendered", lambda **k: "")
    monkeypatch.setattr(subprocess, "call", fake_demo)
    monkeypatch.setattr(judge, "_version", lambda p: "0.20.0" if p == cand else "0.15.3")
    monkeypatch.setattr(judge, "_graph_signature", lambda p: GRAPH)
    monkeypatch.setattr(judge, "_far_graph_signature", lambda p: None)
    assert judge.run_parts(cand, tmp_path / "out", base=base)
    assert probed == [cand, base]
    assert json.loads((tmp_path / "out" / "part2.json").read_text())["holds"] is True
    # part 3 flies a validation scene, with both models, and pairs them
    assert flown == [(cand, judge.DEMO_SCENE), (base, judge.DEMO_SCENE)]
    assert "val.json" in judge.DEMO_SCENE and judge.DEMO_SCENE.rsplit(":", 1)[-1] not in judge.TEST_SEQUENCES
    part3 = json.loads((tmp_path / "out" / "part3.json").read_text())
    assert part3["holds"] is True
    assert part3["figures"]["shipped_lateral_p95_below_5m_cm"] == pytest.approx(21.3)
    assert "probe moved since probe_val_0153.json" in capsys.readouterr().out
    # by hand: against the committed probe (the default) it fails, against the one made beside it holds
    out = ["--out", str(tmp_path / "by_hand")]
    assert main([*out, "probe", str(DATA / "probe_val_0200.json")]) == 1
    assert (
        main(
            [*out, "probe", str(DATA / "probe_val_0200.json"), "--shipped", str(DATA / "probe_val_0200.json")]
        )
        == 0
    )


def _looks_as(ev, base, cand):
    """_looks() with its arms named for other versions."""
    return {
        look: {f"oibarnet {base if '0.34.0' in k else cand} cold": v for k, v in arms.items()}
        for look, arms in ev.items()
    }


def _cold_run(tmp_path, monkeypatch, looks: dict, rolls: dict):
    """run_parts with its steps faked: validation 0.20.0's committed evaluation against 0.15.3,
    the looks and the roll sweep these evaluations (made by _looks() and _rolls()); the commands
    run are kept in the list returned beside the two files."""
    import shutil

    import oibar_models.judge as judge

    cand, base = tmp_path / "cand.onnx", tmp_path / "shipped.onnx"
    cand.write_bytes(b"c")
    base.write_bytes(b"s")
    ran: list[list[str]] = []

    def fake_run(cmd, log):
        ran.append(cmd)
        out = Path(cmd[cmd.index("--out") + 1])
        out.mkdir(parents=True, exist_ok=True)
        ev = looks if "val_mitsuba" in cmd else rolls if "val_roll" in cmd else None
        if ev is None:
            shutil.copy(DATA / "eval_val_candidate_0200.json", out / "eval.json")
        else:
            (out / "eval.json").write_text(json.dumps(_looks_as(ev, "0.15.3", "0.20.0")))

    monkeypatch.setattr(judge, "_run", fake_run)
    monkeypatch.setattr(judge, "_version", lambda p: "0.20.0" if p == cand else "0.15.3")
    monkeypatch.setattr(judge, "_graph_signature", lambda p: GRAPH)
    monkeypatch.setattr(judge, "_far_graph_signature", lambda p: None)
    monkeypatch.setattr(judge, "BASE_PROBE", PROBE_0153)
    monkeypatch.setattr(judge, "looks_rendered", lambda **k: "")
    return cand, base, ran


def _cold_cmd_ok(cmd: list[str], sets: list[str]) -> bool:
    """A kp_evaluate command of parts 1b and 1c: these sets, every frame, cold."""
    i = cmd.index("--sets") + 1
    return (
        cmd[i : i + len(sets)] == sets
        and cmd[cmd.index("--modes") + 1] == "cold"
        and cmd[cmd.index("--stride") + 1] == "1"
    )


def test_the_run_reads_the_looks_after_validation_and_stops_when_they_fail(tmp_path, monkeypatch):
    """Part 1b runs after part 1 holds, on the looks' every frame read cold; a candidate that loses
    the lab look stops there (no probe flown), and looks not rendered stop the run before it reads
    anything, naming the scenes."""
    import oibar_models.judge as judge

    lost = _looks(lab=(4.16, 1.75, 97.8, 98.7, 90))
    cand, base, ran = _cold_run(tmp_path, monkeypatch, lost, _rolls())
    assert not judge.run_parts(cand, tmp_path / "out", base=base)
    assert _cold_cmd_ok(ran[1], ["val_mitsuba", "val_lab"])
    assert len(ran) == 2  # no roll sweep, no probe after a failed part 1b
    verdict = json.loads((tmp_path / "out" / "part1b.json").read_text())
    assert [c["clause"] for c in verdict["clauses"] if not c["holds"]] == ["val_lab: silent failures held"]

    ran.clear()
    monkeypatch.setattr(judge, "looks_rendered", lambda **k: "data/val_lab/va000")
    with pytest.raises(JudgeInputError, match="make dataset-looks.*data/val_lab/va000"):
        judge.run_parts(cand, tmp_path / "out", base=base)
    assert ran == []


def test_the_run_reads_the_roll_sweep_after_the_looks_and_stops_when_it_fails(tmp_path, monkeypatch):
    """Part 1c runs after part 1b holds, on the roll sweep's every frame read cold; a candidate
    with one silent failure more than the shipped model stops there (no probe), and a sweep not
    rendered stops the run before it reads anything, naming its make target."""
    import oibar_models.judge as judge

    cand, base, ran = _cold_run(tmp_path, monkeypatch, _looks(), _rolls((10.64, 22.86, 85.8, 75.8, 30)))
    assert not judge.run_parts(cand, tmp_path / "out", base=base)
    assert len(ran) == 3  # validation, looks, rolls; no probe after a failed part 1c
    assert _cold_cmd_ok(ran[2], ["val_roll"])
    assert json.loads((tmp_path / "out" / "part1b.json").read_text())["holds"] is True
    verdict = json.loads((tmp_path / "out" / "part1c.json").read_text())
    assert [c["clause"] for c in verdict["clauses"] if not c["holds"]] == ["val_roll: silent failures held"]

    ran.clear()
    monkeypatch.setattr(
        judge,
        "looks_rendered",
        lambda sets=judge.LOOK_SETS: "data/val_roll/vr000" if "val_roll" in sets else "",
    )
    with pytest.raises(JudgeInputError, match="make dataset-val-roll.*data/val_roll/vr000"):
        judge.run_parts(cand, tmp_path / "out", base=base)
    assert ran == []


def test_roll_sweep_rendered_is_checked_scene_by_scene(tmp_path):
    from oibar_models.kp_evaluate import SETS
    from oibar_models.scenes import load_set

    repo = Path(__file__).resolve().parents[2]
    spec, data = SETS["val_roll"]
    (tmp_path / spec).parent.mkdir(parents=True, exist_ok=True)
    (tmp_path / spec).write_text((repo / spec).read_text())
    scenes = [sc.name for sc in load_set(repo / spec)]
    for name in scenes[:-1]:
        (tmp_path / data / name).mkdir(parents=True)
        (tmp_path / data / name / "manifest.json").write_text("{}")
    from oibar_models.judge import ROLL_SETS

    assert looks_rendered(tmp_path, sets=ROLL_SETS) == f"{data}/{scenes[-1]}"
    (tmp_path / data / scenes[-1]).mkdir(parents=True)
    (tmp_path / data / scenes[-1] / "manifest.json").write_text("{}")
    assert looks_rendered(tmp_path, sets=ROLL_SETS) == ""
