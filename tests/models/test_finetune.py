"""Fine-tuning on lab recordings (oibar_models.finetune, issue 58 item 5) at toy size: lab
sequences made the lab's way (a synthetic mocap recording labelled by `oibar calib apply`, its
frames drawn at the labels, written by `oibar calib to-dataset`), one step on 8 crops; the
candidate opens in the flight estimator and its table holds finite metrics; bad inputs refused."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from models_helpers import SHIPPED_KP, draw_frame

from oibar.calib import io
from oibar.cli import main as oibar_main
from oibar.geometry.rotations import matrix_to_quat
from oibar_models.finetune import main

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "hil"))


def lab_sequence(rec: Path, out: Path, n: int, seed: int) -> Path:
    """One lab recording through the calib toolbox: mocap + frame index (calib_synth), labels
    (`apply` with the true calibration), frames drawn at the labels, then `to-dataset`."""
    from oibar_hil.calib_synth import SynthConfig, truth, write_recording

    cfg = SynthConfig(n_frames=n, seed=seed)
    write_recording(rec, cfg, images=False)
    tr = truth(cfg)
    calib = {
        "format": io.CALIB_FORMAT,
        "housing_body": "housing",
        "target_body": "tmarkers",
        "T_housing_cam": tr["T_housing_cam"],
        "T_tmarkers_target": tr["T_tmarkers_target"],
        "offset_s": cfg.offset_s,
        "settings": {"intrinsics": "oibar default"},
    }
    (rec / "calib.json").write_text(json.dumps(calib))
    apply = ["calib", "apply", "--calib", str(rec / "calib.json"), "--mocap", str(rec / "mocap.csv")]
    assert oibar_main([*apply, "--frames", str(rec / "frames.csv"), "-o", str(rec / "poses.csv")]) == 0
    rng = np.random.default_rng(seed)
    for row in io.read_poses_csv(rec / "poses.csv"):
        T = row["T_cam_target"]
        draw_frame(T[:3, 3], matrix_to_quat(T[:3, :3]), rng).save(rec / row["file"])
    argv = ["calib", "to-dataset", str(rec), "--calib", str(rec / "calib.json"), "--out", str(out)]
    assert oibar_main(argv) == 0
    return out


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("lab")
    train = lab_sequence(root / "rec_a", root / "data" / "lab01", 8, seed=3)
    held = lab_sequence(root / "rec_b", root / "data" / "lab02", 3, seed=4)
    return {"train": train, "held": held, "root": root}


def test_the_lab_sequences_read_back_with_their_labels(lab):
    from oibar_models.data import load_sequence

    seq = load_sequence(lab["train"], verify_hashes=True)
    labels = io.read_poses_csv(lab["root"] / "rec_a" / "poses.csv")
    assert len(seq) == len(labels) == 8
    assert np.abs(seq.T_cam_target - np.stack([r["T_cam_target"][:3, 3] for r in labels])).max() < 1e-9


def test_one_step_fine_tune_exports_a_flight_model_and_its_table(lab, tmp_path, monkeypatch):
    import onnxruntime as ort

    from oibar.nav.pose import KeypointPoseEstimator, PoseEstimator, read_metadata
    from oibar_models import tracking

    # what goes to MLflow (the store itself is tested with the build, tests/models/test_build.py)
    logged_runs: dict = {}
    monkeypatch.setattr(
        tracking, "log_training", lambda r, stage, cfg, d, m: logged_runs.setdefault(stage, (r, d))
    )
    monkeypatch.setattr(
        tracking,
        "log_evaluation",
        lambda r, stage, model, d, m, o: logged_runs.setdefault(stage, (r, model, m, o)),
    )
    out = tmp_path / "run"
    argv = ["--data", str(lab["train"]), "--val", str(lab["held"]), "--init", str(SHIPPED_KP)]
    argv += ["--out", str(out), "--steps", "1", "--batch-size", "8", "--calibrate-crops", "8"]
    argv += ["--val-frames", "3", "--modes", "cold", "--no-baseline", "--threads", "2", "--no-progress"]
    argv += ["--turn-deg", "90"]  # rolled crops (the stage's own turn is 15 deg)
    argv += ["--roll-share", "0.5"]  # and half of them turned by any angle
    argv += ["--first-pass-steps", "2"]  # the first pass fine-tuned beside it
    assert main(argv) == 0
    augment = yaml.safe_load((out / "config.yaml").read_text())["augment"]
    assert augment["angle_deg"] == 90.0 and augment["p_roll"] == 0.5
    est = PoseEstimator(out / "oibarnet.onnx", warmup_runs=0)
    assert isinstance(est, KeypointPoseEstimator)
    meta, shipped = read_metadata(out / "oibarnet.onnx"), read_metadata(SHIPPED_KP)
    assert meta["fusion"] == shipped["fusion"] and meta["camera"] == shipped["camera"]
    assert meta["finetune"]["ships"] is False and meta["finetune"]["steps"] == 1
    assert meta["finetune"]["roll_share"] == 0.5
    # crops turned by any angle: the estimator is told its keypoints read any turn (the shipped
    # file, trained without, does not say so)
    assert meta["keypoints_any_turn"] is True and est.fusion.keypoints_any_turn
    assert "keypoints_any_turn" not in shipped
    # its keypoint gate: the shipped one scaled with how its heat maps broadened on the training crops
    s = meta["finetune"]["spread_median_crop_px"]
    assert s["start"] > 0 and s["finetuned"] > 0
    from oibar.nav.pose.reader import MAX_SPREAD_CROP_PX

    gate = shipped["pnp"].get("max_spread_crop_px", MAX_SPREAD_CROP_PX)
    assert meta["pnp"]["max_spread_crop_px"] == pytest.approx(gate * s["finetuned"] / s["start"], abs=2e-3)
    # the shipped file's companions beside it, its finder among them (a fine-tune keeps its init's)
    assert meta["finder"] == shipped["finder"] and (out / shipped["finder"]["file"]).is_file()
    # but its first pass fine-tuned on the same sequences: another network under the same name
    from oibar.nav.pose.model_file import companion_files

    first = out / companion_files(shipped)["first_pass"]
    assert meta["first_pass"] == shipped["first_pass"] and meta["finetune"]["first_pass_steps"] == 2
    first_meta = read_metadata(first)
    assert first_meta["finetune"]["steps"] == 2 and first_meta["finetune"]["data"] == [str(lab["train"])]
    xf = np.random.default_rng(0).random((1, 3, 160, 248), dtype=np.float32)
    outs = [
        ort.InferenceSession(str(p)).run(None, {"image": xf})[0]
        for p in (first, SHIPPED_KP.parent / first.name)
    ]
    assert np.abs(outs[0] - outs[1]).max() > 1e-4
    assert meta["finetune"]["config"] == "models/configs/keypoints/oibarnet_kp_stage15.yaml"
    # paths as the repository names them (no checkout's place); the tmp sequences lie outside it
    assert meta["finetune"]["from"] == "models/oibarnet.onnx"
    assert meta["finetune"]["data"] == [str(lab["train"])]
    assert est.reader.max_spread_crop_px == meta["pnp"]["max_spread_crop_px"]
    assert meta["model_version"].endswith("+finetune")
    res = json.loads((out / "eval.json").read_text())
    row = res["fine-tuned cold"]["_all"]
    assert row["frames"] == 3
    for k in ("dt_mean_pct", "dq_mean_deg", "compliance_pos_pct", "compliance_att_pct"):
        assert np.isfinite(row[k]), (k, row)
    assert "| lab02 | fine-tuned cold |" in (out / "eval.md").read_text()
    logged = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in logged] == [0, 1]
    for name in ("recovered.pt", "finetuned.pt", "config.yaml", "done.json", "metrics.json"):
        assert (out / name).is_file(), name
    # the step changed the network (the graph and its tables are the shipped file's)
    x = np.random.default_rng(0).random((1, 3, 128, 128), dtype=np.float32)
    got = [
        ort.InferenceSession(str(p)).run(None, {"image": x})[0] for p in (out / "oibarnet.onnx", SHIPPED_KP)
    ]
    assert np.abs(got[0] - got[1]).max() > 1e-4
    # and both stages go to MLflow, as a build's do
    assert set(logged_runs) == {"run/train", "run/evaluate"}
    run_info, model, metrics, opts = logged_runs["run/evaluate"]
    assert opts["first_pass_steps"] == 2
    assert run_info.name == "finetune_lab" and model == out / "oibarnet.onnx"
    assert np.isfinite(metrics["finetuned_cold.dt_mean_pct"])


def test_bad_inputs_are_refused(lab, tmp_path, capsys):
    def refused(message: str, *argv: str) -> None:
        assert main([*argv, "--no-progress"]) == 2
        assert message in capsys.readouterr().err

    base = ["--init", str(SHIPPED_KP), "--out", str(tmp_path / "run")]
    refused("both trained on and held", "--data", str(lab["train"]), "--val", str(lab["train"]), *base)
    refused("sequence folder not found", "--data", str(tmp_path / "nope"), "--val", str(lab["held"]), *base)
    direct = ["--init", str(REPO / "models" / "oibarnet_lite.onnx"), "--out", str(tmp_path / "r2")]
    refused("not a keypoint model", "--data", str(lab["train"]), "--val", str(lab["held"]), *direct)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    busy = ["--init", str(SHIPPED_KP), "--out", str(tmp_path / "full")]
    refused("is not empty", "--data", str(lab["train"]), "--val", str(lab["held"]), *busy)
    with pytest.raises(SystemExit):  # a turn beyond a half turn is a mistake, not a roll
        main(["--data", str(lab["train"]), "--val", str(lab["held"]), *base, "--turn-deg", "200"])
    assert "--turn-deg must be in [0, 180]" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # a share, not a count of crops
        main(["--data", str(lab["train"]), "--val", str(lab["held"]), *base, "--roll-share", "4"])
    with pytest.raises(SystemExit):
        main(["--data", str(lab["train"]), "--val", str(lab["held"]), *base, "--first-pass-steps", "-1"])
    assert "--roll-share must be in [0, 1]" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # a part the network does not have
        main(["--data", str(lab["train"]), "--val", str(lab["held"]), *base, "--freeze", "neck"])
    assert "--freeze: invalid choice: 'neck'" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # what to distil on, with no distillation
        main(
            [
                "--data",
                str(lab["train"]),
                "--val",
                str(lab["held"]),
                *base,
                "--distill-data",
                str(lab["train"]),
            ]
        )
    assert "--distill-data needs --distill-weight > 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--data", str(lab["train"]), "--val", str(lab["held"]), *base, "--distill-weight", "-1"])
    assert "--distill-weight must be a finite number >= 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # a teacher, with no distillation
        main(
            ["--data", str(lab["train"]), "--val", str(lab["held"]), *base, "--distill-from", str(SHIPPED_KP)]
        )
    assert "--distill-from needs --distill-weight > 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # a target, with no distillation
        main(["--data", str(lab["train"]), "--val", str(lab["held"]), *base, "--distill-target", "last_tap"])
    assert "--distill-target needs --distill-weight > 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(
            ["--data", str(lab["train"]), "--val", str(lab["held"]), *base, "--distill-weight", "1"]
            + ["--distill-from", str(tmp_path / "nope.onnx")]
        )
    assert "--distill-from: not found" in capsys.readouterr().err
    teacher = ["--init", str(SHIPPED_KP), "--out", str(tmp_path / "r3"), "--distill-weight", "1"]
    teacher += ["--distill-from", str(REPO / "models" / "oibarnet_lite.onnx")]  # no keypoints, no head
    refused("distill from", "--data", str(lab["train"]), "--val", str(lab["held"]), *teacher)
    held = ["--distill-weight", "1", "--distill-data", str(lab["held"])]  # not a training sequence
    refused(
        "distill data not among the training sequences",
        "--data",
        str(lab["train"]),
        "--val",
        str(lab["held"]),
        *base,
        *held,
    )


def test_frozen_parts_keep_their_weights_out_of_training_and_leave_something_to_train():
    """finetune.frozen_parts: the named children lose their gradients; a name the network lacks,
    or freezing every part, is refused."""
    import torch

    from oibar_models.finetune import FREEZABLE, FinetuneError, frozen_parts

    class Toy(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.backbone, self.attitude = torch.nn.Linear(2, 2), torch.nn.Linear(2, 1)

    net = Toy()
    assert frozen_parts(net, ("attitude",)) == [net.attitude]
    assert [p.requires_grad for p in net.parameters()] == [True, True, False, False]
    with pytest.raises(FinetuneError, match="'head' is not a part of this network"):
        frozen_parts(Toy(), ("head",))
    with pytest.raises(FinetuneError, match="leaves nothing to train"):
        frozen_parts(Toy(), ("backbone", "attitude"))
    assert "head" in FREEZABLE


def test_the_distillation_pulls_the_attitude_head_back_to_the_starting_networks_answers(tmp_path):
    """finetune.distill_teacher / distill_deg2: the teacher is a frozen copy of the network as it
    starts, held to on the named training sequences' crops only; the term is zero before anything
    moves, grows when the backbone drifts, and its gradient takes the drifted backbone back toward
    the teacher's answers while the teacher stays as it was."""
    import torch

    from oibar_models.finetune import Options, distill_deg2, distill_teacher
    from oibar_models.kpnet import KeypointNet

    torch.manual_seed(0)
    net = KeypointNet(n_keypoints=4, pretrained=False).eval()
    with torch.no_grad():  # answers of a few degrees, as a trained head gives (an untrained one: ~0.01)
        net.attitude[-1].weight.mul_(300.0)
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    o = Options(
        data=[a, b, c],
        val=[],
        init=tmp_path / "m.onnx",
        out=tmp_path,
        distill_weight=1.0,
        distill_data=(c, a),
    )
    teacher, taught = distill_teacher(o, net)
    assert taught.tolist() == [True, False, True]
    assert distill_teacher(Options(data=[a, b], val=[], init=a, out=tmp_path), net)[0] is None
    assert distill_teacher(Options(data=[a, b], val=[], init=a, out=tmp_path, distill_weight=0.5), net)[
        1
    ].all()
    x = torch.rand(4, 3, 64, 64)
    assert float(distill_deg2(teacher, x, net(x)[2])) == pytest.approx(0.0, abs=1e-9)
    before = {k: v.clone() for k, v in teacher.state_dict().items()}
    with torch.no_grad():
        for p in net.backbone.parameters():
            p.add_(0.05 * torch.randn_like(p))
    opt = torch.optim.Adam(net.backbone.parameters(), lr=1e-3)
    drifted = float(distill_deg2(teacher, x, net(x)[2]))
    assert drifted > 1e-6
    for _ in range(20):
        d = distill_deg2(teacher, x, net(x)[2])
        opt.zero_grad()
        d.backward()
        opt.step()
    assert float(distill_deg2(teacher, x, net(x)[2])) < 0.5 * drifted
    assert all(torch.equal(before[k], v) for k, v in teacher.state_dict().items())
    assert not any(p.requires_grad for p in teacher.parameters())


def test_the_map_distillation_pulls_the_drifted_backbone_back_to_the_teachers_last_map(tmp_path):
    """finetune.distill_tap: zero on the teacher's own map, 1 for an empty map (relative to the
    teacher's mean square), and its gradient takes a drifted backbone's stride-32 map back toward
    the teacher's; the student's map is the one `read_taps` reads (forward = read_taps(features))."""
    import torch

    from oibar_models.finetune import (
        DISTILL,
        DISTILL_TARGETS,
        Options,
        distill_tap,
        distill_teacher,
        start_gap,
    )
    from oibar_models.kpnet import KeypointNet

    assert set(DISTILL) == set(DISTILL_TARGETS) == {"attitude", "last_tap"}
    torch.manual_seed(0)
    net = KeypointNet(n_keypoints=4, pretrained=False).eval()
    with torch.no_grad():  # maps of a trained network's size (a fresh one's last map is ~1e-8)
        for m in net.backbone.modules():
            if isinstance(m, torch.nn.Conv2d):
                torch.nn.init.kaiming_normal_(m.weight)
    a = tmp_path / "a"
    teacher, _ = distill_teacher(Options(data=[a], val=[], init=a, out=tmp_path, distill_weight=1.0), net)
    x = torch.rand(4, 3, 64, 64)
    taps = net.backbone.features(x)
    assert all(torch.equal(u, v) for u, v in zip(net(x), net.read_taps(taps), strict=True))
    assert float(distill_tap(teacher, x, taps[-1])) == pytest.approx(0.0, abs=1e-9)
    assert float(distill_tap(teacher, x, torch.zeros_like(taps[-1]))) == pytest.approx(1.0)
    with torch.no_grad():
        for p in net.backbone.parameters():
            p.add_(0.05 * torch.randn_like(p))
    drifted = float(distill_tap(teacher, x, net.backbone.features(x)[-1]))
    assert drifted > 1e-4
    assert start_gap(teacher, net, x, "last_tap") == pytest.approx(drifted, rel=1e-4)
    assert start_gap(teacher, net, x, "attitude") > 0 and not net.training
    opt = torch.optim.Adam(net.backbone.parameters(), lr=1e-3)
    for _ in range(20):
        d = distill_tap(teacher, x, net.backbone.features(x)[-1])
        opt.zero_grad()
        d.backward()
        opt.step()
    assert float(distill_tap(teacher, x, net.backbone.features(x)[-1])) < 0.5 * drifted


def test_the_cli_turns_a_tenth_of_the_crops_by_default_and_says_what_its_keypoints_read():
    from oibar_models.finetune import ROLL_SHARE, parse

    need = ["--data", "a", "--val", "b", "--out", "c"]
    o = parse(need)
    assert o.roll_share == ROLL_SHARE > 0 and o.keypoints_any_turn
    from oibar_models.finetune import FIRST_PASS_STEPS

    assert o.first_pass_steps == FIRST_PASS_STEPS > 0  # the first pass learns the look too
    assert parse([*need, "--first-pass-steps", "0"]).first_pass_steps == 0
    o = parse([*need, "--roll-share", "0"])  # none turned: its keypoints read upright views only
    assert o.roll_share == 0 and not o.keypoints_any_turn
    # a recipe's stage builds Options itself: its retag stage says what the keypoints read
    from oibar_models.finetune import Options

    recipe_like = Options(data=[], val=[], init=SHIPPED_KP, out=Path("x"))
    assert recipe_like.keypoints_any_turn is False
    assert recipe_like.first_pass_steps == 0  # and keeps the shipped first pass, which its judge assumes
