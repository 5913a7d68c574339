"""A trainable checkpoint from a keypoint model's ONNX export: the shipped file is the checkpoint.

Training keeps best.pt and last.pt under runs/, which a fresh machine does not have, and the
project commits only the ONNX export. The export folds each batch norm into the convolution
before it (W' = W gamma / sigma, b' = beta - mu gamma / sigma), so its weights cannot be loaded
into KeypointNet by name. This recovers them:

1. A fresh KeypointNet of the export's shape is exported the same way with every batch norm set
   to the identity: its folded weights are its own, so each initializer names its parameter.
2. The two graphs are walked node by node (the same operators in the same order, or the export is
   refused as another architecture) and each of the export's initializers lands on its parameter.
3. Each folded pair gets W = W' and a batch norm that adds b'. With `--calibrate DATA` the batch
   norms also get the statistics (mean mu, variance v) of their input on DATA's crops, with
   gamma = sqrt(v + eps) and beta = b' + mu: the same function in evaluation, and in training
   (batch statistics) close to it, so fine-tuning starts from the shipped network rather than
   from a jolt. Without it the running statistics are (0, 1), right in evaluation only.

The result is checked before it is written: its outputs against the export's onnxruntime
outputs on random and, with --calibrate, real crops.

python -m oibar_models.kp_recover models/oibarnet.onnx --out runs/recovered/oibarnet.pt [--calibrate data/train]

The checkpoint is what `train.init_from` takes (a second stage from the shipped model).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .kp_export import ATT_OUTPUT, export_graph
from .kpnet import ExportWrapper, KeypointNet

PARITY_TOL = 1e-3  # crop px, probability or degree: what export_onnx itself holds the export to


class RecoverError(RuntimeError):
    """The file is not a keypoint export this code can recover (with the reason)."""


def _read(path: Path):
    import onnx

    if not Path(path).is_file():
        raise RecoverError(f"{path}: no such file")
    try:
        m = onnx.load(str(path))
    except Exception as exc:  # noqa: BLE001 - a damaged file: one clear error
        raise RecoverError(f"{path}: not a readable ONNX file ({exc})") from exc
    meta = {p.key.removeprefix("oibar."): p.value for p in m.metadata_props if p.key.startswith("oibar.")}
    meta = {k: json.loads(v) for k, v in meta.items()}
    if meta.get("kind") != "keypoints":
        raise RecoverError(f"{path}: not a keypoint model export (oibar.kind = {meta.get('kind')!r})")
    if meta.get("ensemble"):
        names = ", ".join(str(e.get("name")) for e in meta["ensemble"])
        raise RecoverError(
            f"{path}: one graph of {len(meta['ensemble'])} networks ({names}; kp_export --ensemble): "
            "a checkpoint holds one, so recover or train each member from its own"
        )
    return m, meta


def folded_pairs(net: KeypointNet, out_px: int) -> list[tuple[str, str]]:
    """(conv, batch norm) module names where the batch norm reads the convolution's output
    directly: the pairs the export folds."""
    names = {id(m): n for n, m in net.named_modules()}
    produced: dict[int, str] = {}
    pairs: list[tuple[str, str]] = []
    hooks = []

    def hook(mod, inp, out):
        if isinstance(mod, nn.Conv2d):
            produced[id(out)] = names[id(mod)]
        elif isinstance(mod, nn.BatchNorm2d) and id(inp[0]) in produced:
            pairs.append((produced[id(inp[0])], names[id(mod)]))

    for m in net.modules():
        if isinstance(m, nn.Conv2d | nn.BatchNorm2d):
            hooks.append(m.register_forward_hook(hook))
    try:
        with torch.no_grad():
            net.eval()(torch.zeros(1, 3, out_px, out_px))
    finally:
        for h in hooks:
            h.remove()
    return pairs


def recover(path: Path) -> tuple[KeypointNet, dict, list[tuple[str, str]]]:
    """The export at `path` -> (KeypointNet in eval mode computing what it computes, its
    metadata, the folded (conv, batch norm) pairs). Batch norms carry the folded bias and
    running statistics (0, 1): see `calibrate`."""
    import onnx
    from onnx import numpy_helper

    m, meta = _read(path)
    inits = {i.name: numpy_helper.to_array(i) for i in m.graph.initializer}
    n_kp = len(meta.get("keypoints_3d_m") or [])
    out_px = int((meta.get("crop") or {}).get("out_px", 0))
    if not n_kp or not out_px:
        raise RecoverError(f"{path}: its metadata lacks oibar.keypoints_3d_m or oibar.crop.out_px")
    width = int(inits["net.lateral.0.weight"].shape[0]) if "net.lateral.0.weight" in inits else 64
    attitude = ATT_OUTPUT in [o.name for o in m.graph.output]
    opset = max(o.version for o in m.opset_import if o.domain in ("", "ai.onnx"))

    net = KeypointNet(n_kp, width, pretrained=False).eval()
    pairs = folded_pairs(net, out_px)
    mods = dict(net.named_modules())
    gen = torch.Generator().manual_seed(0)
    for bn_name in (b for _, b in pairs):
        bn = mods[bn_name]
        assert isinstance(bn, nn.BatchNorm2d)
        with torch.no_grad():
            bn.weight.fill_(1.0)
            # distinct biases: the exporter merges equal constants (zeros) into Identity nodes
            bn.bias.copy_(torch.rand(bn.bias.shape, generator=gen))
            bn.running_mean.zero_()
            bn.running_var.fill_(1.0 - bn.eps)
    params = {k: v.detach().numpy() for k, v in net.state_dict().items()}

    with tempfile.TemporaryDirectory() as tmp:
        ref_path = Path(tmp) / "ref.onnx"
        export_graph(net, attitude, out_px, opset, ref_path)
        ref = onnx.load(str(ref_path))
    ref_inits = {i.name: numpy_helper.to_array(i) for i in ref.graph.initializer}

    # each reference initializer -> the parameter it is (by name, or by value for a folded one)
    conv_of = {f"{c}.weight": c for c, _ in pairs}
    ref_param: dict[str, str] = {}
    for name, arr in ref_inits.items():
        key = name.removeprefix("net.")
        if key in params:
            ref_param[name] = key
            continue
        hits = [
            k
            for k in conv_of
            if params[k].shape == arr.shape and np.allclose(params[k], arr, rtol=1e-5, atol=1e-7)
        ]
        if len(hits) == 1:
            ref_param[name] = hits[0]

    a_nodes, r_nodes = list(m.graph.node), list(ref.graph.node)
    if [n.op_type for n in a_nodes] != [n.op_type for n in r_nodes]:
        raise RecoverError(
            f"{path}: its graph is not KeypointNet's (width {width}, {n_kp} keypoints, "
            f"{'with' if attitude else 'without'} the attitude head): it cannot be recovered by this code"
        )
    state = {k: torch.from_numpy(np.array(v, copy=True)) for k, v in params.items()}
    filled: set[str] = set()
    for an, rn in zip(a_nodes, r_nodes, strict=True):
        w_key = None
        for j, (ai, ri) in enumerate(zip(an.input, rn.input, strict=True)):
            if ri not in ref_inits:
                continue
            if ai not in inits or inits[ai].shape != ref_inits[ri].shape:
                raise RecoverError(
                    f"{path}: node {an.name or an.op_type} input {j} differs from KeypointNet's"
                )
            val = torch.from_numpy(np.array(inits[ai], copy=True))
            if ri in ref_param:
                key = ref_param[ri]
                state[key] = val
                filled.add(key)
                w_key = key if key in conv_of else w_key
            elif an.op_type == "Conv" and j == 2 and w_key is not None:
                bn = dict(pairs)[conv_of[w_key]]  # the folded bias: the batch norm adds it
                state[f"{bn}.bias"] = val
                filled.add(f"{bn}.bias")
    bn_names = {b for _, b in pairs}
    learnable = [k for k, _ in net.named_parameters()]
    missing = [k for k in learnable if k not in filled and k.rsplit(".", 1)[0] not in bn_names]
    if missing:
        raise RecoverError(f"{path}: no weights found for {missing[:5]}{' ...' if len(missing) > 5 else ''}")
    net.load_state_dict(state)
    return net.eval(), meta, pairs


def calibrate(net: KeypointNet, pairs: list[tuple[str, str]], crops: torch.Tensor) -> None:
    """Give each folded batch norm its input's statistics on `crops` (N, 3, S, S) while keeping
    the network's evaluation-mode function: gamma = sqrt(v + eps), beta = b' + mu."""
    mods = dict(net.named_modules())
    stats: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
    hooks = []

    def hook_for(name):
        def hook(mod, inp, out):
            x = inp[0].double()
            stats[name] = (x.mean(dim=(0, 2, 3)), x.var(dim=(0, 2, 3), unbiased=False))

        return hook

    for _, b in pairs:
        hooks.append(mods[b].register_forward_hook(hook_for(b)))
    try:
        with torch.no_grad():
            net.eval()(crops)
    finally:
        for h in hooks:
            h.remove()
    with torch.no_grad():
        for _, b in pairs:
            bn = mods[b]
            mu, v = stats[b]
            bn.running_mean.copy_(mu.float())
            bn.running_var.copy_(v.float())
            bn.weight.copy_(torch.sqrt(v + bn.eps).float())
            bn.bias.add_(mu.float())


def parity(path: Path, net: KeypointNet, x: np.ndarray) -> float:
    """Largest difference between the export's outputs (onnxruntime) and the network's on x."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(None, {sess.get_inputs()[0].name: x.astype(np.float32)})
    attitude = len(got) == 4
    with torch.no_grad():
        want = [t.numpy() for t in ExportWrapper(net.eval(), attitude=attitude)(torch.from_numpy(x))]
    return max(float(np.max(np.abs(a - b))) for a, b in zip(got, want, strict=True))


def calibration_crops(data_root: Path, meta: dict, n: int) -> torch.Tensor:
    """n crops of the scenes under data_root, cut around the true pose as validation cuts them."""
    from .kp_data import CropAugment, CropDataset, open_scenes, spread_frames

    scenes = open_scenes(data_root)
    if not scenes:
        raise RecoverError(f"{data_root}: no rendered scenes (make dataset-train writes them)")
    kp = np.asarray(meta["keypoints_3d_m"], float)
    aug = CropAugment(margin=float(meta["crop"]["margin"]))
    ds = CropDataset(
        scenes, kp, int(meta["crop"]["out_px"]), aug, train=False, frames=spread_frames(scenes, n)
    )
    return torch.stack([ds[i]["image"] for i in range(len(ds))])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m oibar_models.kp_recover", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("onnx", type=Path, help="a keypoint model export (models/oibarnet.onnx)")
    ap.add_argument("--out", type=Path, required=True, help="the checkpoint to write (.pt)")
    ap.add_argument(
        "--calibrate",
        type=Path,
        default=None,
        help="rendered scenes (data/train) whose crops give the batch norms their statistics",
    )
    ap.add_argument("--crops", type=int, default=256, help="calibration crops (default 256)")
    a = ap.parse_args(argv)
    try:
        net, meta, pairs = recover(a.onnx)
        rng = np.random.default_rng(0)
        px = int(meta["crop"]["out_px"])
        checks = {"random": rng.random((4, 3, px, px), dtype=np.float32)}
        if a.calibrate is not None:
            crops = calibration_crops(a.calibrate, meta, a.crops)
            calibrate(net, pairs, crops)
            checks["real"] = crops[:16].numpy()
    except RecoverError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    errs = {k: parity(a.onnx, net, x) for k, x in checks.items()}
    if not all(e < PARITY_TOL for e in errs.values()):
        print(f"error: the recovered network differs from {a.onnx} by {errs}", file=sys.stderr)
        return 1
    a.out.parent.mkdir(parents=True, exist_ok=True)
    ck = {
        "model": net.state_dict(),
        "step": meta.get("steps_trained"),
        "val": meta.get("val", {}),
        "recovered_from": {
            "path": str(a.onnx),
            "model_version": meta.get("model_version"),
            "folded_pairs": len(pairs),
            "calibrated_on": str(a.calibrate) if a.calibrate else None,
            "parity": errs,
        },
    }
    tmp = a.out.with_suffix(".tmp")
    torch.save(ck, tmp)
    tmp.replace(a.out)
    print(
        f"{a.out}: {a.onnx} ({meta.get('model_version')}) as a checkpoint: {len(pairs)} batch norms unfolded"
        f"{f', calibrated on {a.crops} crops' if a.calibrate else ''}; "
        + ", ".join(f"{k} crops within {e:.1e}" for k, e in errs.items())
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
