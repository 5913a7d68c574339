"""oibar_models.onnx_seal: every export's last step writes the metadata and refuses a file that
onnxruntime reads otherwise than PyTorch."""

from __future__ import annotations

import warnings

import onnx
import pytest
import torch

from oibar.nav.pose import read_metadata
from oibar_models.onnx_seal import ParityError, seal_onnx


def _exported(tmp_path, net: torch.nn.Module, x: torch.Tensor):
    path = tmp_path / "net.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(net, (x,), str(path), input_names=["image"], opset_version=17, dynamo=False)
    return path


def test_a_sealed_file_carries_its_metadata_and_reads_as_the_network(tmp_path):
    torch.manual_seed(0)
    net = torch.nn.Conv2d(3, 2, 3).eval()
    x = torch.rand(1, 3, 16, 16)
    path = _exported(tmp_path, net, x)
    err = seal_onnx(path, {"kind": "test", "input_size_wh": [16, 16]}, "tests", net, x)
    assert err < 1e-5
    assert read_metadata(path) == {"kind": "test", "input_size_wh": [16, 16]}
    assert onnx.load(str(path)).producer_name == "tests"


def test_a_file_that_reads_otherwise_is_removed(tmp_path):
    torch.manual_seed(0)
    net = torch.nn.Conv2d(3, 2, 3).eval()
    x = torch.rand(1, 3, 16, 16)
    path = _exported(tmp_path, net, x)
    with torch.no_grad():
        net.bias += 0.01  # the network moved after its export: the file no longer reads as it does
    with pytest.raises(ParityError, match=r"disagree by 0\.01 \(crop px\)"):
        seal_onnx(path, {"kind": "test"}, "tests", net, x, unit="crop px")
    assert not path.exists()
