"""The shipped ONNX as a checkpoint (oibar_models.kp_recover): the folded batch norms unfolded,
the network computing what the export computes, and batch statistics that keep it so in training."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from oibar_models.kp_export import export_graph
from oibar_models.kp_recover import (
    PARITY_TOL,
    RecoverError,
    calibrate,
    main,
    parity,
    recover,
)
from oibar_models.kpnet import ExportWrapper, KeypointNet, soft_argmax

REPO = Path(__file__).resolve().parents[2]
N_KP, OUT_PX = 14, 64


def _tag(path: Path, **meta) -> None:
    import onnx

    m = onnx.load(str(path))
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = "oibar." + k, json.dumps(v)
    onnx.save(m, str(path))


@pytest.fixture(scope="module")
def trained_export(tmp_path_factory):
    """A KeypointNet whose batch norms are far from the identity (what training leaves), exported
    as kp_export does (folded) with the metadata the recovery reads."""
    torch.manual_seed(7)
    net = KeypointNet(N_KP, 32, pretrained=False)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.weight.uniform_(0.5, 1.5)
                m.bias.normal_(0.0, 0.2)
                m.running_mean.normal_(0.0, 0.3)
                m.running_var.uniform_(0.5, 2.0)
    path = tmp_path_factory.mktemp("kp") / "kp.onnx"
    export_graph(net.eval(), True, OUT_PX, 17, path)
    _tag(
        path,
        kind="keypoints",
        keypoints_3d_m=np.zeros((N_KP, 3)).tolist(),
        crop={"out_px": OUT_PX, "margin": 1.25},
    )
    return net.eval(), path


def _outputs(net, x):
    with torch.no_grad():
        return [t.numpy() for t in ExportWrapper(net.eval())(torch.from_numpy(x))]


def test_the_recovered_network_computes_what_the_export_computes(trained_export):
    """Every learnable tensor is found (the batch norms from the folded biases) and the
    network's outputs match both the export's and the original network's."""
    original, path = trained_export
    net, meta, pairs = recover(path)
    assert len(pairs) == sum(isinstance(m, nn.BatchNorm2d) for m in net.modules())
    x = np.random.default_rng(0).random((3, 3, OUT_PX, OUT_PX), dtype=np.float32)
    assert parity(path, net, x) < PARITY_TOL
    for got, want in zip(_outputs(net, x), _outputs(original, x), strict=True):
        assert np.max(np.abs(got - want)) < PARITY_TOL
    # and not by accident: a network with one tensor off does not pass
    with torch.no_grad():
        net.present.bias.add_(1.0)
    assert parity(path, net, x) > PARITY_TOL


def test_calibrated_batch_norms_keep_the_function_in_training_mode(trained_export):
    """Uncalibrated, the recovered batch norms hold statistics (0, 1): in training mode (batch
    statistics) the network is another one. Calibrated on crops, it is the same network in
    evaluation and nearly so in training on crops like them."""
    _, path = trained_export
    net, _, pairs = recover(path)
    gen = torch.Generator().manual_seed(1)
    crops = torch.rand(24, 3, OUT_PX, OUT_PX, generator=gen)

    def drift(n):
        with torch.no_grad():
            kp_e, _, _ = soft_argmax(n.eval()(crops)[0])
            kp_t, _, _ = soft_argmax(n.train()(crops)[0])
        n.eval()
        return float((kp_t - kp_e).norm(dim=-1).median())

    before = drift(net)
    calibrate(net, pairs, crops)
    assert parity(path, net, crops.numpy()) < PARITY_TOL
    after = drift(net)
    assert after < 0.05 < before, (before, after)


def test_what_cannot_be_recovered_is_refused_with_the_reason(tmp_path, trained_export):
    _, path = trained_export
    with pytest.raises(RecoverError, match="no such file"):
        recover(tmp_path / "missing.onnx")
    (tmp_path / "junk.onnx").write_bytes(b"not onnx")
    with pytest.raises(RecoverError, match="not a readable ONNX"):
        recover(tmp_path / "junk.onnx")
    other = tmp_path / "other.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            nn.Sequential(nn.Conv2d(3, 4, 3), nn.ReLU()), torch.rand(1, 3, 8, 8), str(other), dynamo=False
        )
    with pytest.raises(RecoverError, match="not a keypoint model"):
        recover(other)
    _tag(other, kind="keypoints", keypoints_3d_m=np.zeros((N_KP, 3)).tolist(), crop={"out_px": OUT_PX})
    with pytest.raises(RecoverError, match="not KeypointNet's"):
        recover(other)


def test_the_shipped_model_recovers_into_a_checkpoint_training_can_start_from(tmp_path):
    """models/oibarnet.onnx -> a checkpoint (`train.init_from` reads its 'model'), within the
    export's own parity bound of the shipped file."""
    shipped = REPO / "models/oibarnet.onnx"
    out = tmp_path / "rec.pt"
    assert main([str(shipped), "--out", str(out)]) == 0
    ck = torch.load(out, weights_only=False)
    assert ck["recovered_from"]["model_version"] and ck["recovered_from"]["folded_pairs"] > 40
    net = KeypointNet(N_KP, 64, pretrained=False)
    net.load_state_dict(ck["model"])  # strict: every tensor there
    x = np.random.default_rng(2).random((2, 3, 128, 128), dtype=np.float32)
    assert parity(shipped, net, x) < PARITY_TOL
    assert main([str(tmp_path / "nope.onnx"), "--out", str(tmp_path / "x.pt")]) == 2
