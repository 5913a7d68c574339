"""The soft-argmax keypoint branch and the second training stage (init_from with widened heads)."""

from __future__ import annotations

import json

import torch
from models_helpers import tiny_config

from oibar_models.engine import load_checkpoint, train
from oibar_models.export import export_onnx, parity
from oibar_models.nets import OibarNet, soft_argmax, widen_heads_from


def test_soft_argmax_finds_the_peak_in_image_coordinates():
    logits = torch.full((1, 2, 10, 16), -30.0)
    logits[0, 0, 2, 12] = 30.0  # row 2 of 10, column 12 of 16
    logits[0, 1, 7, 3] = 30.0
    uv = soft_argmax(logits)[0]
    u_cell = lambda c, n: -1 + (2 * c + 1) / n  # noqa: E731 (cell centre in [-1, 1])
    assert torch.allclose(uv[:2], torch.tensor([u_cell(12, 16), u_cell(3, 16)]), atol=1e-5)
    assert torch.allclose(uv[2:], torch.tensor([u_cell(2, 10), u_cell(7, 10)]), atol=1e-5)
    # a moving peak moves the output: the branch is position-sensitive by construction
    logits2 = torch.roll(logits, shifts=2, dims=3)
    assert soft_argmax(logits2)[0, 0] > uv[0]


def test_widened_heads_start_from_the_old_function():
    old = OibarNet(width=0.5, coord_channels=True, pos_param="uvlogz").eval()
    new = OibarNet(width=0.5, coord_channels=True, pos_param="uvlogz", keypoints=8).eval()
    with torch.no_grad():
        old.head_t.weight.normal_(0, 0.1)
    new.load_state_dict(widen_heads_from(new, old.state_dict()))
    x = torch.rand(3, 3, 60, 93)
    for a, b in zip(old(x), new(x), strict=True):
        assert torch.allclose(a, b, atol=1e-5)
    assert new.feature_dim == old.feature_dim + 16


def test_second_stage_trains_from_the_first_and_exports(tiny_dataset, tmp_path):
    cfg1 = tiny_config(tiny_dataset, tmp_path / "stage1", pos_loss="range_normalised")
    cfg1.model.pos_param = "uvlogz"
    train(cfg1, progress=False, log=lambda m: None)
    cfg2 = tiny_config(
        tiny_dataset,
        tmp_path / "stage2",
        init_from=str(tmp_path / "stage1" / "best.pt"),
        pos_loss="range_normalised",
    )
    cfg2.model.pos_param = "uvlogz"
    cfg2.model.keypoints = 4
    logs = []
    train(cfg2, progress=False, log=logs.append)
    assert any(m.startswith("initialised from") for m in logs)
    net, ck = load_checkpoint(tmp_path / "stage2" / "best.pt")
    assert net.keypoints == 4
    rows = [json.loads(x) for x in (tmp_path / "stage2" / "log.jsonl").read_text().splitlines()]
    assert len(rows) == 2
    out = export_onnx(net, ck, tmp_path / "kp.onnx")
    diffs = parity(net, out, torch.rand(2, 3, 60, 93))
    assert max(diffs.values()) < 1e-4, diffs


def test_missing_first_stage_is_a_clear_error(tiny_dataset, tmp_path):
    import pytest

    cfg = tiny_config(tiny_dataset, tmp_path / "s2", init_from=str(tmp_path / "nope.pt"))
    with pytest.raises(FileNotFoundError, match="train that stage first"):
        train(cfg, progress=False, log=lambda m: None)


def test_keypoint_supervision_targets_are_the_projected_fixture_points(tiny_dataset, tmp_path):
    import numpy as np

    from oibar_models.engine import KeypointSupervision
    from oibar_models.geometry import rot6d_from_matrix

    cfg = tiny_config(tiny_dataset, tmp_path / "r")
    cfg.model.keypoints = 8
    net = OibarNet(width=0.5, coord_channels=True, keypoints=8)
    K = np.array([[50.0, 0, 46.5], [0, 50.0, 30.0], [0, 0, 1]])
    sup = KeypointSupervision(cfg, K, net)
    T = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 0.05]])
    r6 = rot6d_from_matrix(torch.eye(3).expand(2, 3, 3))
    uv, valid = sup.targets(T, r6)
    assert torch.allclose(uv[0, 0], torch.tensor([0.0, 0.0]), atol=1e-6), "the origin on the optical axis"
    # corner (-0.25, -0.18) at 2 m: u = 46.5 - 50 * 0.125 = 40.25 px of 93 -> 2 * 40.25 / 93 - 1
    assert torch.allclose(uv[0, 1], torch.tensor([2 * 40.25 / 93 - 1, 2 * (30 - 4.5) / 60 - 1]), atol=1e-5)
    assert valid[0].all() and not valid[1, 1:].any(), "corners out of view at 5 cm are masked"
    feats = net.features(torch.rand(2, 3, 60, 93))
    assert sup.predicted(feats).shape == (2, 5, 2)


def test_training_with_keypoint_supervision_runs(tiny_dataset, tmp_path):
    cfg = tiny_config(tiny_dataset, tmp_path / "kp", kp_loss=True, pos_loss="range_normalised")
    cfg.model.keypoints = 8
    cfg.model.pos_param = "uvlogz"
    train(cfg, progress=False, log=lambda m: None)
    ck = torch.load(tmp_path / "kp" / "last.pt", weights_only=False)
    assert "s_k" in ck["loss"] and float(ck["loss"]["s_k"]) != 0.0, "the keypoint term was trained"
