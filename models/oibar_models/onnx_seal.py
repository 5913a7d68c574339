"""The last step of every export of ours: the `oibar.*` metadata written into the ONNX file, the
file checked, and onnxruntime's answer compared with PyTorch's on the same input, so that no file
leaves an export reading otherwise than the network it came from."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

METADATA_PREFIX = "oibar."


class ParityError(RuntimeError):
    """onnxruntime and PyTorch disagree on an exported file (it has been removed)."""


def seal_onnx(
    path: Path, meta: dict[str, Any], producer: str, module: torch.nn.Module, x: torch.Tensor,
    tol: float = 1e-3, unit: str = "",
) -> float:  # fmt: skip
    """Write `meta` (each key as oibar.KEY, its value JSON) and `producer` into the ONNX file at
    `path` (input `image`), check it, and run it on `x` against `module(x)`: the largest absolute
    difference over the outputs. At `tol` or more the file is removed and ParityError raised
    (`unit` says what the difference is in)."""
    import onnx
    import onnxruntime as ort

    m = onnx.load(str(path))
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = METADATA_PREFIX + k, json.dumps(v)
    m.producer_name = producer
    onnx.checker.check_model(m)
    onnx.save(m, str(path))
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"image": x.numpy()})
    with torch.no_grad():
        want = [t.numpy() for t in module(x)]
    err = max(float(np.max(np.abs(a - b))) for a, b in zip(got, want, strict=True))
    if not err < tol:
        path.unlink(missing_ok=True)
        raise ParityError(f"ONNX and PyTorch disagree by {err:.3g}{f' ({unit})' if unit else ''}")
    return err
