"""6D representation, quaternions, the learned-uncertainty loss, the paper's metrics, the
cyclical learning rate and the configs."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from oibar.geometry.rotations import matrix_to_quat, rotvec_to_matrix
from oibar.geometry.rotations import quat_to_matrix as quat_to_matrix_np
from oibar_models import metrics
from oibar_models.config import ConfigError, from_dict, load_config, parse_override
from oibar_models.engine import cyclical_lr
from oibar_models.geometry import matrix_from_rot6d, quat_from_matrix, rot6d_from_matrix
from oibar_models.loss import UncertaintyPoseLoss

CONFIGS = sorted((Path(__file__).resolve().parents[2] / "models" / "configs").glob("*.yaml"))


def random_rotations(n, seed=0):
    rng = np.random.default_rng(seed)
    out = [rotvec_to_matrix(v) for v in rng.normal(size=(n, 3)) * 1.5]
    # the four Shepperd branches: near 180 deg about each axis, and the identity
    out += [rotvec_to_matrix(np.array(a) * (math.pi - 1e-3)) for a in ((1, 0, 0), (0, 1, 0), (0, 0, 1))]
    out.append(np.eye(3))
    return np.array(out)


def test_rot6d_roundtrip_and_gram_schmidt():
    R = torch.tensor(random_rotations(50))
    R2 = matrix_from_rot6d(rot6d_from_matrix(R))
    assert torch.allclose(R, R2, atol=1e-9)
    # any non-degenerate 6-vector gives a proper rotation
    r6 = torch.randn(100, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    M = matrix_from_rot6d(r6)
    eye = torch.eye(3, dtype=torch.float64).expand(100, 3, 3)
    assert torch.allclose(M.transpose(1, 2) @ M, eye, atol=1e-6)  # eps in the norms
    assert torch.allclose(torch.linalg.det(M), torch.ones(100, dtype=torch.float64), atol=1e-6)
    # the first column keeps the first predicted column's direction
    assert torch.allclose(M[:, :, 0], r6[:, :3] / r6[:, :3].norm(dim=1, keepdim=True), atol=1e-6)


def test_quaternion_matches_hil_convention():
    R = random_rotations(60)
    q = quat_from_matrix(torch.tensor(R)).numpy()
    for Ri, qi in zip(R, q, strict=True):
        np.testing.assert_allclose(qi, matrix_to_quat(Ri), atol=1e-7)
        assert qi[0] >= 0
    np.testing.assert_allclose(quat_to_matrix_np(q), R, atol=1e-9)


def test_loss_formula_and_uncertainty_gradient():
    crit = UncertaintyPoseLoss(init_s_r=0.3, init_s_t=-0.2)
    T_hat = torch.tensor([[0.0, 0.0, 1.0], [1.0, 1.0, 1.0]])
    T = torch.tensor([[0.0, 0.0, 4.0], [1.0, 1.0, 1.0]])  # position errors 3, 0 m
    r_hat = torch.tensor([[1.0, 0, 0, 0, 1, 0], [0, 1.0, 0, 1, 0, 0]])
    r = torch.tensor([[1.0, 0, 0, 0, 1, 0], [1.0, 0, 0, 0, 1, 0]])  # 6D errors 0, 2
    out = crit(T_hat, r_hat, T, r)
    L_t, L_r = 3.0, 2.0
    expect = L_r * math.exp(-0.6) + L_t * math.exp(0.4) + 2 * (0.3 - 0.2)
    assert float(out["L_t"]) == pytest.approx(L_t)
    assert float(out["L_r"]) == pytest.approx(L_r)
    assert float(out["loss"].detach()) == pytest.approx(expect, rel=1e-6)
    out["loss"].backward()
    # dL/ds_t = -2 L_t exp(-2 s_t) + 2
    assert float(crit.s_t.grad) == pytest.approx(-2 * L_t * math.exp(0.4) + 2, rel=1e-6)


def test_metrics_named_as_in_the_paper():
    T = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 2.0]])
    T_hat = T + np.array([[0.3, 0.4, 0.0], [0.0, 0.0, 0.2]])  # 0.5 m (5 %), 0.2 m (10 %)
    q = np.array([[1.0, 0, 0, 0]] * 2)
    a = np.radians(4.0)
    q_hat = np.array(
        [[math.cos(a / 2), math.sin(a / 2), 0, 0], [-math.cos(3 * a / 4), 0, 0, -math.sin(3 * a / 4)]]
    )
    np.testing.assert_allclose(metrics.position_error_m(T_hat, T), [0.5, 0.2])
    np.testing.assert_allclose(metrics.position_error_pct(T_hat, T), [5.0, 10.0])
    np.testing.assert_allclose(metrics.attitude_error_deg(q_hat, q), [4.0, 6.0], atol=1e-9)  # sign-invariant
    s = metrics.summarize(T_hat, q_hat, T, q)
    assert s["dt_mean_m"] == pytest.approx(0.35)
    assert s["dt_median_pct"] == pytest.approx(7.5)
    assert s["compliance_pos_pct"] == 50.0 and s["compliance_att_pct"] == 50.0
    assert "| seq01 | OibarNet |" in metrics.markdown_table([("seq01", "OibarNet", s)])


def test_mean_pose_baseline():
    R = [rotvec_to_matrix(np.array([0, 0, a])) for a in np.radians([-10, 0, 10])]
    q = np.array([matrix_to_quat(r) for r in R])
    q[1] = -q[1]  # same rotation, other sign: must not matter
    T_mean, q_mean = metrics.mean_pose(np.array([[0, 0, 1.0], [0, 0, 2.0], [0, 0, 3.0]]), q)
    np.testing.assert_allclose(T_mean, [0, 0, 2.0])
    np.testing.assert_allclose(q_mean, [1, 0, 0, 0], atol=1e-12)


def test_cyclical_learning_rate_has_five_cycles():
    cfg = from_dict({"train": {"lr_max": 1e-3, "lr_min": 1e-5, "lr_cycles": 5, "lr_cycle_decay": 0.5}})
    lrs = np.array([cyclical_lr(s, 1000, cfg) for s in range(1000)])
    peaks = [i for i in range(1, 999) if lrs[i] > lrs[i - 1] and lrs[i] >= lrs[i + 1]]
    assert len(peaks) == 5
    assert lrs.max() == pytest.approx(1e-3, rel=1e-2)
    assert lrs[peaks[-1]] == pytest.approx(1e-5 + (1e-3 / 16 - 1e-5), rel=1e-2)
    assert lrs.min() >= 1e-5 - 1e-12


@pytest.mark.parametrize("path", CONFIGS, ids=[p.stem for p in CONFIGS])
def test_shipped_configs_load(path):
    cfg = load_config(path)
    assert cfg.model.dropout == 0.2 and cfg.train.lr_cycles == 5
    assert 1 not in cfg.data.train_seqs and 8 not in cfg.data.train_seqs


def test_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("model:\n  backbon: resnet101\n")
    with pytest.raises(ConfigError, match="unknown key"):
        load_config(bad)
    bad.write_text("train:\n  epochs: many\n")
    with pytest.raises(ConfigError, match="expected a number"):
        load_config(bad)
    ok = tmp_path / "ok.yaml"
    ok.write_text("name: x\n")
    cfg = load_config(ok, parse_override(["train.epochs=3", "model.backbone=darknet19"]))
    assert cfg.train.epochs == 3 and cfg.model.backbone == "darknet19"
