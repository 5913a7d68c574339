"""The fixture finder's trainer (oibar_models.finder) and its flight reader (oibar.nav.pose.finder)
agree: labels -> targets -> the flight decoder gives the labels back, augmentation moves the box
with the image, and the exported file reads a frame as the trained network does."""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest
import torch

from oibar.nav.pose.finder import FixtureFinder, decode
from oibar_models import finder as F
from oibar_models.config import ConfigError


def test_targets_and_the_flight_decoder_give_the_labels_back():
    rng = np.random.default_rng(0)
    grid = (F.INPUT_WH[1] // F.STRIDE_PX, F.INPUT_WH[0] // F.STRIDE_PX)
    sx, sy = F.INPUT_WH[0] / F.FRAME_WH[0], F.INPUT_WH[1] / F.FRAME_WH[1]
    for _ in range(20):
        u, v, side = (
            rng.uniform(5, F.FRAME_WH[0] - 5),
            rng.uniform(5, F.FRAME_WH[1] - 5),
            rng.uniform(15, 400),
        )
        box_in = np.array([[u * sx, v * sy, side * sx]], np.float32)
        heat, idx, off, s_in = F.targets(box_in, grid)
        assert idx[0] >= 0 and heat[0, 0].max() == 1.0
        logit = np.where(heat[0, 0] == 1.0, 5.0, -5.0)
        offset = np.zeros((2, *grid), np.float32)
        i, j = divmod(int(idx[0]), grid[1])
        offset[:, i, j] = off[0]
        log_side = np.full(grid, np.log(s_in[0] / sx / F.SIDE_UNIT_PX), np.float32)
        a = decode(logit, offset, log_side, F.STRIDE_PX, F.INPUT_WH, F.FRAME_WH, F.SIDE_UNIT_PX)
        np.testing.assert_allclose(a.center_px, (u, v), atol=1e-3)
        assert a.side_px == pytest.approx(side, rel=1e-5) and a.score > 0.99
    # a centre outside the frame has no cell
    assert F.targets(np.array([[-5.0, 10.0, 20.0]], np.float32), grid)[1][0] == -1


def test_augmentation_moves_the_box_with_the_image():
    cfg = replace(F.FinderConfig(), p_turn=1.0, p_mirror=0.5, p_photometric=0.0, p_blur=0.0)
    w, h = F.INPUT_WH
    for seed in range(12):
        rng = np.random.default_rng(seed)
        u, v = rng.uniform(50, w - 50), rng.uniform(40, h - 40)
        img = np.zeros((h, w, 3), np.uint8)
        cv2.circle(img, (round(u), round(v)), 6, (255, 255, 255), -1)
        u, v = round(u), round(v)  # the disc's centre, exactly
        x, box = F.augment(img, np.array([u, v, 12.0], np.float32), rng, cfg, (w / 2 - 3.0, h / 2 + 2.0))
        mass = x[:, :, 0]
        if mass.sum() < 0.5 * np.pi * 36:  # turned or shifted out of the frame
            continue
        yy, xx = np.mgrid[0:h, 0:w]
        centroid = ((mass * xx).sum() / mass.sum(), (mass * yy).sum() / mass.sum())
        np.testing.assert_allclose(centroid, box[:2], atol=1.0, err_msg=f"seed {seed}")
        assert box[2] == 12.0


def test_the_exported_finder_reads_a_frame_as_the_network(tmp_path):
    torch.manual_seed(1)
    net = F.FinderNet(8)
    net.eval()
    cfg = replace(F.FinderConfig(), width=8, out_dir=str(tmp_path / "run"), name="finder_test")
    (tmp_path / "run").mkdir()
    torch.save({"net": net.state_dict(), "best": {"epoch": 1, "score": 0.5}}, tmp_path / "run" / "best.pt")
    path = F.export(cfg, tmp_path / "finder.onnx")
    finder = FixtureFinder(path, threads=1)
    assert finder.meta["kind"] == "finder" and finder.frame_wh == F.FRAME_WH
    frame = np.random.default_rng(2).integers(0, 255, (F.FRAME_WH[1], F.FRAME_WH[0], 3), dtype=np.uint8)
    got = finder.find(frame)
    small = cv2.resize(frame, F.INPUT_WH, interpolation=cv2.INTER_AREA)[None]
    want = F.predict(net, small)[0]
    np.testing.assert_allclose(got.center_px, want[:2], atol=1e-2)
    assert got.side_px == pytest.approx(want[2], rel=1e-3) and got.score == pytest.approx(want[3], abs=1e-4)
    with pytest.raises(ValueError, match="reads 744x480 frames"):
        finder.find(frame[:240])


def test_the_shipped_finder_config_loads_with_the_finders_own_loader():
    # it lives in models/configs/finder/, apart from the whole-frame configs, whose loader rejects it
    cfg = F.load_finder_config(F.REPO_ROOT / "models/configs/finder/oibarnet_finder.yaml")
    assert cfg.name == "oibarnet_finder" and cfg.epochs > 0 and cfg.train_sets
    assert all(not s[1].startswith(("data/test", "data/frozen")) for s in cfg.train_sets + [cfg.val_set])


def test_a_config_with_a_typo_or_scenes_not_rendered_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("epoch: 3\n")
    with pytest.raises(ConfigError, match="unknown keys \\['epoch'\\]"):
        F.load_finder_config(bad)
    spec = tmp_path / "set.json"
    spec.write_text(json.dumps({"set": "t", "scenes": [{"name": "tr000"}, {"name": "tr001"}]}))
    cfg = F.FinderConfig()
    with pytest.raises(ConfigError, match="2 of .* are not rendered in .*nowhere"):
        F.build_cache([[str(spec), str(tmp_path / "nowhere")]], 1, np.zeros((3, 3)), cfg, tmp_path / "c.npz")
    with pytest.raises(ConfigError, match="1 of"):
        F.build_cache(
            [[str(spec), str(tmp_path / "nowhere"), "1/2"]], 1, np.zeros((3, 3)), cfg, tmp_path / "c.npz"
        )
    assert not (tmp_path / "c.npz").exists()


def test_the_threshold_sweep_reads_the_finders_crop_only_where_its_thresholds_allow(
    tmp_path, tiny_dataset, monkeypatch
):
    """oibar_models.finder_sweep: the same model file read cold without its finder and at each
    setting of finder_place.FINDER_*; a score bar no answer reaches (2) reads no finder crop, none (0)
    reads one on every frame, and the module's thresholds are as they were afterwards."""
    import shutil
    from pathlib import Path

    from oibar.nav.pose import finder_place as S
    from oibar_models import finder_sweep
    from oibar_models.kp_evaluate import SETS
    from oibar_models.kp_export import retag

    root = Path(__file__).resolve().parents[2]
    for f in (root / "models").glob("oibarnet*.onnx"):
        shutil.copy(f, tmp_path / f.name)
    torch.manual_seed(3)
    cfg = replace(F.FinderConfig(), width=8, out_dir=str(tmp_path / "run"), name="finder_test")
    (tmp_path / "run").mkdir()
    torch.save({"net": F.FinderNet(8).state_dict(), "best": {"epoch": 1}}, tmp_path / "run" / "best.pt")
    F.export(cfg, tmp_path / "finder_test.onnx")
    model = tmp_path / "oibarnet.onnx"
    retag(model, model, {"finder": {"file": "finder_test.onnx"}})
    (tmp_path / "val.json").write_text(json.dumps({"scenes": [{"paper": 3}]}))
    monkeypatch.setitem(SETS, "val", (str(tmp_path / "val.json"), str(tiny_dataset)))
    monkeypatch.setenv("OIBAR_TRACKING", "0")
    before = (S.FINDER_MIN_SCORE, S.FINDER_SAME_FRAC, S.FINDER_SAME_SIDE)
    out = tmp_path / "sweep"
    argv = ["--model", str(model), "--stride", "16", "--min-score", "0", "2", "--same-frac", "0"]
    assert finder_sweep.main([*argv, "--same-side", "1", "--out", str(out), "--no-progress"]) == 0
    rows = {r["label"]: r for r in json.loads((out / "sweep.json").read_text())}
    assert rows["no finder"]["found_pct"] == 0.0 and rows["no finder"]["frames"] == 3
    assert rows["min_score 0 same_frac 0 same_side 1"]["found_pct"] == 100.0
    assert rows["min_score 2 same_frac 0 same_side 1"]["found_pct"] == 0.0
    assert all(r["crops_mean"] >= 1 and r["latency_ms_p95"] > 0 for r in rows.values())
    assert (out / "sweep.png").stat().st_size > 0 and "latency p95 (ms)" in (out / "sweep.md").read_text()
    assert before == (S.FINDER_MIN_SCORE, S.FINDER_SAME_FRAC, S.FINDER_SAME_SIDE)
    # a model that names no finder (0.34.0's, kept beside its records) is refused with one line, exit 2
    no_finder = root / "models" / "registry" / "oibarnet-0.34.0" / "oibarnet.onnx"
    assert finder_sweep.main(["--model", str(no_finder), "--out", str(out)]) == 2
