"""Several keypoint networks read as one graph (kpnet.EnsembleWrapper, `kp_export --ensemble`;
docs/model_history.md "Candidate 0.31.0"): the mixture of their heat maps, exported as a file the
flight estimator reads as any keypoint network, alone or as a far network."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from models_helpers import one_network_copy

from oibar_models.kpnet import FIXTURE_KEYPOINTS, EnsembleWrapper, ExportWrapper, KeypointNet

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "models/configs/keypoints/oibarnet_kp.yaml"
K = len(FIXTURE_KEYPOINTS)


def _net(seed: int, width: int = 16) -> KeypointNet:
    """Random weights, the heat-map head sharpened so that each map has a peak of its own and two
    networks place a keypoint pixels apart (a fresh head's maps are nearly flat)."""
    torch.manual_seed(seed)
    net = KeypointNet(K, width, pretrained=False).eval()
    with torch.no_grad():
        net.head[3].weight.mul_(300.0)
    return net


def test_the_ensemble_reads_the_mixture_of_its_members_heat_maps():
    """Position and spread are the mean and RMS spread of the half-and-half mixture of the two
    softmax distributions, computed here from the heat maps themselves; presence and the head's
    rotation vector are the members' means."""
    a, b = _net(1), _net(2)
    x = torch.rand(3, 3, 64, 64)
    with torch.no_grad():
        kp, spread, present, att = EnsembleWrapper([a, b])(x)
        (ha, pa, ta), (hb, pb, tb) = a(x), b(x)
    n, k, h, w = ha.shape
    stride = 64 / w
    p = (torch.softmax(ha.reshape(n, k, -1), -1) + torch.softmax(hb.reshape(n, k, -1), -1)) / 2
    p = p.reshape(n, k, h, w).double()
    ys, xs = torch.meshgrid((torch.arange(h) + 0.5) * stride, (torch.arange(w) + 0.5) * stride, indexing="ij")
    mx, my = (p * xs).sum((2, 3)), (p * ys).sum((2, 3))
    var = (p * ((xs - mx[..., None, None]) ** 2 + (ys - my[..., None, None]) ** 2)).sum((2, 3))
    assert torch.allclose(kp.double(), torch.stack([mx, my], -1), atol=1e-3)
    assert torch.allclose(spread.double(), var.sqrt(), atol=1e-3)
    apart = (ExportWrapper(a)(x)[0] - ExportWrapper(b)(x)[0]).norm(dim=-1)
    assert apart.max() > 5.0  # crop px: the members place keypoints apart here
    assert torch.allclose(present, (torch.sigmoid(pa) + torch.sigmoid(pb)) / 2, atol=1e-6)
    assert torch.allclose(att, (ta + tb) / 2, atol=1e-5)
    # the members do disagree here, and the mixture is no narrower than the narrower member
    sa, sb = ExportWrapper(a)(x)[1], ExportWrapper(b)(x)[1]
    assert (spread >= torch.minimum(sa, sb) - 1e-4).all()


def test_an_ensemble_of_one_network_twice_is_that_network():
    a = _net(1)
    x = torch.rand(2, 3, 64, 64)
    with torch.no_grad():
        one, two = ExportWrapper(a)(x), EnsembleWrapper([a, a])(x)
    for u, v in zip(one, two, strict=True):
        assert torch.allclose(u, v, atol=1e-5)
    with pytest.raises(ValueError, match="two networks or more"):
        EnsembleWrapper([a])


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """Two checkpoints of the default config's network (random weights, the attitude head) and a
    third without the head."""
    from oibar_models.kp_engine import load_kp_config

    width = load_kp_config(CONFIG).model.width
    d = tmp_path_factory.mktemp("ck")
    paths = {}
    for name, seed in (("a", 1), ("b", 2)):
        torch.save({"model": _net(seed, width).state_dict(), "step": seed * 10}, d / f"{name}.pt")
        paths[name] = d / f"{name}.pt"
    state = {k: v for k, v in _net(3, width).state_dict().items() if not k.startswith("attitude.")}
    torch.save({"model": state, "step": 30}, d / "headless.pt")
    paths["headless"] = d / "headless.pt"
    return paths


def _export(out: Path, main: Path, *members: str) -> int:
    from oibar_models.kp_export import main as export_main

    args = ["--config", str(CONFIG), "--checkpoint", str(main), "--out", str(out)]
    for m in members:
        args += ["--ensemble", m]
    return export_main(args)


def test_an_exported_ensemble_reads_as_the_mean_of_its_members_exports(checkpoints, tmp_path):
    """The file the flight code opens: one keypoint network whose keypoints are the mean of the
    two members' own exports, on the same crops; its metadata names both members."""
    import onnxruntime as ort

    from oibar.nav.pose import KeypointPoseEstimator

    (tmp_path / "oibarnet_lite.onnx").symlink_to(REPO / "models/oibarnet_lite.onnx")  # the first pass
    assert _export(tmp_path / "a.onnx", checkpoints["a"]) == 0
    assert _export(tmp_path / "b.onnx", checkpoints["b"]) == 0
    assert _export(tmp_path / "ab.onnx", checkpoints["a"], f"{CONFIG}:{checkpoints['b']}") == 0
    x = np.random.default_rng(0).random((2, 3, 128, 128), np.float32)
    runs = {
        n: ort.InferenceSession(str(tmp_path / f"{n}.onnx"), providers=["CPUExecutionProvider"]).run(
            None, {"image": x}
        )
        for n in ("a", "b", "ab")
    }
    assert np.abs(runs["a"][0] - runs["b"][0]).max() > 1.0  # the members read the crop apart
    assert np.allclose(runs["ab"][0], (runs["a"][0] + runs["b"][0]) / 2, atol=1e-3)
    assert np.allclose(runs["ab"][2], (runs["a"][2] + runs["b"][2]) / 2, atol=1e-5)
    assert np.allclose(runs["ab"][3], (runs["a"][3] + runs["b"][3]) / 2, atol=1e-4)
    est = KeypointPoseEstimator(tmp_path / "ab.onnx", warmup_runs=1)
    assert [m["steps_trained"] for m in est.meta["ensemble"]] == [10, 20]
    assert "ensemble" not in KeypointPoseEstimator(tmp_path / "a.onnx", warmup_runs=0).meta


def test_an_ensemble_serves_as_a_far_network(checkpoints, tmp_path):
    """Beside the shipped main network, an ensemble exported with the shipped far network's tables
    opens as its far network (the estimator checks the two are the same kind of network)."""
    from oibar.nav.pose import KeypointPoseEstimator
    from oibar_models.kp_export import main as export_main

    one_network_copy(tmp_path)
    far = tmp_path / "oibarnet_far.onnx"
    assert _export(far, checkpoints["a"], f"{CONFIG}:{checkpoints['b']}") == 0
    args = ["--retag", str(tmp_path / "oibarnet.onnx"), "--out", str(tmp_path / "pair.onnx")]
    assert export_main(args + ["--far-network", far.name, "--far-from-m", "8"]) == 0
    est = KeypointPoseEstimator(tmp_path / "pair.onnx", warmup_runs=1)
    assert est.reader.far_session is not None and est.reader.far_from_m == 8.0
    img = np.random.default_rng(3).integers(0, 40, (480, 744, 3), np.uint8)
    img[220:260, 350:395] = 210
    assert np.isfinite(est.estimate(img).confidence)


@pytest.mark.parametrize(
    "member, match",
    [
        ("headless", "without the attitude head"),
        ("missing", "checkpoint not found"),
    ],
)
def test_a_member_that_cannot_join_is_refused_and_nothing_is_written(
    checkpoints, tmp_path, capsys, member, match
):
    path = checkpoints.get(member, tmp_path / "nowhere.pt")
    out = tmp_path / "ab.onnx"
    assert _export(out, checkpoints["a"], f"{CONFIG}:{path}") == 2
    assert match in capsys.readouterr().err and not out.exists()
    assert not list(tmp_path.glob("*.onnx"))


def test_an_ensemble_is_not_recovered_into_one_checkpoint(checkpoints, tmp_path, capsys):
    from oibar_models.kp_recover import main as recover_main

    assert _export(tmp_path / "ab.onnx", checkpoints["a"], f"{CONFIG}:{checkpoints['b']}") == 0
    assert recover_main([str(tmp_path / "ab.onnx"), "--out", str(tmp_path / "ab.pt")]) == 2
    assert "one graph of 2 networks" in capsys.readouterr().err and not (tmp_path / "ab.pt").exists()


def test_retag_takes_no_ensemble(tmp_path, capsys):
    from oibar_models.kp_export import main as export_main

    one_network_copy(tmp_path)
    args = ["--retag", str(tmp_path / "oibarnet.onnx"), "--corner-refine-side-px", "150"]
    assert export_main([*args, "--ensemble", str(CONFIG)]) == 2
    assert "--retag takes the reading options" in capsys.readouterr().err
    assert export_main(args) == 0  # the same retag without it is taken
