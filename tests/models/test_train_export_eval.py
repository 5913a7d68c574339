"""A tiny end-to-end run: train (and resume), export to ONNX (parity with PyTorch), evaluate
(tables, plots, overlays); plus the backbones, the BiLSTM hook and missing-model errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from models_helpers import tiny_config

from oibar_models import evaluate as evaluate_mod
from oibar_models.engine import load_checkpoint, train
from oibar_models.export import export_onnx, parity, quantize_int8
from oibar_models.infer import ModelFileError, OnnxPoseEstimator, read_metadata
from oibar_models.nets import BACKBONES, OibarNet, TemporalOibarNet, count_parameters


@pytest.fixture(scope="module")
def trained(tiny_dataset, tmp_path_factory):
    run = tmp_path_factory.mktemp("run")
    cfg = tiny_config(tiny_dataset, run)
    logs = []
    train(cfg, progress=False, log=logs.append)
    return cfg, run, logs


def test_smoke_training_writes_checkpoints_and_logs(trained):
    cfg, run, logs = trained
    for f in (
        "last.pt",
        "best.pt",
        "log.jsonl",
        "log.csv",
        "split.json",
        "labels.json",
        "config.yaml",
        "done.json",
    ):
        assert (run / f).is_file(), f
    rows = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [1, 2]
    assert all(np.isfinite(r["loss"]) and r["train_images_per_s"] > 0 for r in rows)
    assert "val_dt_mean_pct" in rows[-1] and "val_compliance_att_pct" in rows[-1]
    assert len((run / "log.csv").read_text().splitlines()) == 3


def test_training_resumes_after_interruption(trained, tiny_dataset):
    cfg, run, _ = trained
    cfg3 = tiny_config(tiny_dataset, run, epochs=3)
    logs = []
    train(cfg3, progress=False, log=logs.append)
    assert any("resumed" in m and "2 epoch(s) done" in m for m in logs)
    rows = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [1, 2, 3]
    assert torch.load(run / "last.pt", weights_only=False)["step"] == 9


def test_onnx_export_matches_pytorch(trained, tmp_path):
    cfg, run, _ = trained
    net, ck = load_checkpoint(run / "best.pt")
    out = export_onnx(net, ck, tmp_path / "m.onnx", model_version="0.0.1")
    diffs = parity(net, out, torch.rand(5, 3, 60, 93))
    assert diffs["position_m"] < 1e-4 and diffs["rot6d"] < 1e-4 and diffs["q_cam_target"] < 1e-4, diffs
    meta = read_metadata(out)
    assert meta["input_size_wh"] == [93, 60]
    assert meta["model_version"] == "0.0.1" and meta["backbone"] == "oibar_lite"
    assert meta["normalisation"]["applied"] == "inside the graph"
    K = np.array(meta["camera"]["K_input"])
    assert K[0, 2] == pytest.approx(372.0 / 8) and K[0, 0] == pytest.approx(583.333 / 8, rel=1e-4)
    assert "q_cam_target" in meta["outputs"] and len(meta["train_mean_q_cam_target"]) == 4
    # the camera distances of training (1.5-4.1 m here) widened by 0.8x / 1.2x; the runtime's check uses them
    lo, hi = meta["train_range_m"]
    assert 1.1 < lo < 1.3 and 4.2 < hi < 5.2, (lo, hi)
    # a full-size frame through the torch-free runtime
    est = OnnxPoseEstimator(out)
    assert est.range_limits_m == (lo, hi)
    t, q = est(np.zeros((480, 744, 3), np.uint8))
    assert t.shape == (3,) and q.shape == (4,) and abs(np.linalg.norm(q) - 1) < 1e-5 and q[0] >= 0


def test_int8_variant_runs(trained, tmp_path):
    cfg, run, _ = trained
    net, ck = load_checkpoint(run / "best.pt")
    fp32 = export_onnx(net, ck, tmp_path / "m.onnx")
    q8 = quantize_int8(fp32, tmp_path / "m.int8.onnx", np.random.default_rng(0).random((8, 3, 60, 93)))
    t, q = OnnxPoseEstimator(q8).predict_batch(np.zeros((2, 60, 93, 3), np.uint8))
    assert t.shape == (2, 3) and np.all(np.isfinite(t))
    assert "quantisation" in read_metadata(q8)


def test_evaluation_tables_plots_overlays(trained, tiny_dataset, tmp_path):
    cfg, run, _ = trained
    net, ck = load_checkpoint(run / "best.pt")
    model = export_onnx(net, ck, tmp_path / "m.onnx")
    res = evaluate_mod.evaluate(
        model, [tiny_dataset / "seq01"], tmp_path / "eval", None, overlays=2, bench_s=0.3, progress=False
    )
    s = res["sequences"]["seq01"]
    assert s["model"]["frames"] == 48 and "dt_mean_pct" in s["baseline"]
    md = (tmp_path / "eval" / "eval.md").read_text()
    assert "| seq01 | OibarNet |" in md and "| seq01 | mean-pose baseline |" in md and "Latency" in md
    assert (tmp_path / "eval" / "seq01_errors.png").stat().st_size > 1000
    assert len(list((tmp_path / "eval").glob("seq01_overlay_*.png"))) == 2
    assert len((tmp_path / "eval" / "seq01_errors.csv").read_text().splitlines()) == 49


def test_missing_model_file_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(ModelFileError, match="model file not found.*make train"):
        OnnxPoseEstimator(tmp_path / "nope.onnx")
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(ModelFileError, match="not a readable ONNX"):
        OnnxPoseEstimator(tmp_path / "junk.onnx")
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        load_checkpoint(tmp_path / "best.pt")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"name: x\nexport:\n  onnx_path: {tmp_path / 'absent.onnx'}\n")
    assert evaluate_mod.main(["--config", str(cfg), "--bench-s", "0", "--out", str(tmp_path / "eval")]) == 2
    assert not (tmp_path / "eval").exists()
    assert "model file not found" in capsys.readouterr().err


def test_missing_dataset_is_a_clear_cli_error(tmp_path, capsys):
    from oibar_models import train as train_mod

    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"name: x\nrun_dir: {tmp_path / 'run'}\ndata:\n  root: {tmp_path / 'nodata'}\n")
    assert train_mod.main(["--config", str(cfg), "--no-progress"]) == 2
    assert "dataset folder not found" in capsys.readouterr().err


@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_backbones_build_and_run(name):
    net = OibarNet(name, coord_channels=(name == "darknet19")).eval()
    with torch.no_grad():
        t, r6 = net(torch.rand(2, 3, 64, 96))
    assert t.shape == (2, 3) and r6.shape == (2, 6)
    assert isinstance(net.dropout, torch.nn.Dropout) and net.dropout.p == 0.2
    n = count_parameters(net)
    expect_m = {
        "squeezenet": (0.5, 1.5),
        "darknet19": (15, 25),
        "darknet53": (35, 45),
        "resnet101": (40, 45),
        "oibar_lite": (0.5, 3),
    }[name]
    assert expect_m[0] * 1e6 < n < expect_m[1] * 1e6, n


def test_untrained_net_starts_at_the_mean_pose():
    net = OibarNet("oibar_lite", pos_mean_m=(0.0, 0.12, 5.0)).eval()
    with torch.no_grad():
        t, r6 = net(torch.rand(3, 3, 64, 96))
    np.testing.assert_allclose(t.numpy(), [[0.0, 0.12, 5.0]] * 3, atol=1e-6)
    np.testing.assert_allclose(r6.numpy(), [[1, 0, 0, 0, 1, 0]] * 3, atol=0.05)


def test_bilstm_temporal_hook():
    cnn = OibarNet("oibar_lite", width=0.5)
    for layers in (1, 2, 3):
        tnet = TemporalOibarNet(cnn, layers=layers, hidden=16)
        t, r6 = tnet(torch.rand(2, 5, 3, 64, 96))
        assert t.shape == (2, 5, 3) and r6.shape == (2, 5, 6)
        assert not any(p.requires_grad for p in tnet.cnn.parameters())
    with pytest.raises(ValueError):
        TemporalOibarNet(cnn, layers=4)
