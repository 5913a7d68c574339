"""ONNX export of a trained OibarNet, with the metadata the runtime needs, a parity check against
PyTorch, and an optional statically quantised INT8 variant.

Graph: input `image` (N, 3, H, W) float32 RGB in [0, 1] (the frame resized with
infer.resize_frame); outputs `position_m` (N, 3) = T_cam_target in metres, `q_cam_target`
(N, 4) (w, x, y, z; w >= 0), `R_cam_target` (N, 3, 3), `rot6d` (N, 6). Metadata keys `oibar.*`
(JSON values): input size, normalisation, camera intrinsics, output convention, model version,
backbone, training-label means (the trivial baseline).

CLI: python -m oibar_models.export --config models/configs/X.yaml [--checkpoint PATH] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

from oibar.geometry.camera import intrinsics, scale_intrinsics

from . import __version__
from .infer import METADATA_PREFIX, OnnxPoseEstimator
from .nets import INPUT_MEAN, INPUT_STD, OibarNet, PoseOutputs

OUTPUT_NAMES = ["position_m", "q_cam_target", "R_cam_target", "rot6d"]


def metadata_for(net: OibarNet, ck: dict, model_version: str) -> dict:
    cfg, cam = ck["config"], ck.get("camera") or {}
    w, h = cfg["model"]["input_width_px"], cfg["model"]["input_height_px"]
    meta = {
        "model_version": model_version,
        "library_version": __version__,
        "name": cfg["name"],
        "backbone": cfg["model"]["backbone"],
        "input_size_wh": [w, h],
        "input": "image: float32 (N, 3, H, W), RGB, values in [0, 1] = uint8 / 255, after resizing the "
        "camera frame with PIL bilinear (oibar.nav.pose.resize_frame)",
        "normalisation": {"mean": list(INPUT_MEAN), "std": list(INPUT_STD), "applied": "inside the graph"},
        "outputs": {
            "position_m": "T_cam_target: fixture origin in the camera frame (OpenCV axes: +X right, +Y down, "
            "+Z forward), metres",
            "q_cam_target": "unit quaternion (w, x, y, z), w >= 0, of R_cam_target (p_cam = R p_t + T)",
            "R_cam_target": "rotation matrix, Gram-Schmidt of rot6d",
            "rot6d": "Zhou et al. 6D: first two columns of R_cam_target",
        },
        "epochs_trained": ck.get("epoch"),
        "train_mean_T_cam_target": ck["labels"]["mean_T_cam_target"],
        "train_mean_q_cam_target": ck["labels"]["mean_q_cam_target"],
        "val": ck.get("val", {}),
        "pretrained_weights": "none: trained from scratch",
    }
    if "range_m" in ck["labels"]:
        # camera distances seen in training: the runtime flags answers far outside (oibar.nav.pose)
        lo, hi = ck["labels"]["range_m"]
        meta["train_range_m"] = [round(0.8 * lo, 3), round(1.2 * hi, 3)]
    if cam:
        K = intrinsics(cam["fx_px"], cam["fy_px"], cam["cx_px"], cam["cy_px"])
        Ks = scale_intrinsics(K, w / cam["width_px"], h / cam["height_px"])
        meta["camera"] = {**cam, "K_frame": K.tolist(), "K_input": Ks.tolist()}
    return meta


def export_onnx(
    net: OibarNet, ck: dict, out_path: str | Path, opset: int = 17, model_version: str = "0.1.0"
) -> Path:
    import onnx

    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    cfg = ck["config"]
    h, w = cfg["model"]["input_height_px"], cfg["model"]["input_width_px"]
    wrapper = PoseOutputs(net.eval()).eval()
    dummy = torch.rand(1, 3, h, w)
    tmp = out_path.with_suffix(".tmp.onnx")
    with (
        warnings.catch_warnings()
    ):  # the TorchScript exporter is deprecated but is the pinned torch's stable path
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            wrapper,
            dummy,
            str(tmp),
            input_names=["image"],
            output_names=OUTPUT_NAMES,
            dynamic_axes={n: {0: "batch"} for n in ["image"] + OUTPUT_NAMES},
            opset_version=opset,
            dynamo=False,
        )
    m = onnx.load(str(tmp))
    for k, v in metadata_for(net, ck, model_version).items():
        p = m.metadata_props.add()
        p.key, p.value = METADATA_PREFIX + k, json.dumps(v)
    m.producer_name = "oibar_models.export"
    m.model_version = (
        int(model_version.split(".")[0]) * 10000
        + int(model_version.split(".")[1]) * 100
        + int(model_version.split(".")[2])
    )
    onnx.checker.check_model(m)
    onnx.save(m, str(out_path))
    tmp.unlink(missing_ok=True)
    return out_path


@torch.no_grad()
def parity(net: OibarNet, onnx_path: str | Path, images: torch.Tensor) -> dict:
    """Max absolute differences between PyTorch and onnxruntime on the same inputs."""
    t, q, R, r6 = PoseOutputs(net.eval())(images)
    est = OnnxPoseEstimator(onnx_path)
    o = est.run(images.numpy().astype(np.float32))
    return {
        "position_m": float(np.abs(o["position_m"] - t.numpy()).max()),
        "q_cam_target": float(np.abs(o["q_cam_target"] - q.numpy()).max()),
        "R_cam_target": float(np.abs(o["R_cam_target"] - R.numpy()).max()),
        "rot6d": float(np.abs(o["rot6d"] - r6.numpy()).max()),
    }


def quantize_int8(onnx_path: str | Path, out_path: str | Path, calib_images: np.ndarray) -> Path:
    """Static (QDQ) INT8 quantisation calibrated on real frames; metadata is carried over."""
    import onnx
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter(
                [{"image": calib_images[i : i + 1].astype(np.float32)} for i in range(len(calib_images))]
            )

        def get_next(self):
            return next(self.it, None)

    out_path = Path(out_path)
    pre = out_path.with_suffix(".pre.onnx")
    quant_pre_process(str(onnx_path), str(pre), skip_symbolic_shape=True)
    quantize_static(
        str(pre),
        str(out_path),
        Reader(),
        quant_format=QuantFormat.QDQ,
        activation_type=QuantType.QUInt8,
        weight_type=QuantType.QInt8,
        per_channel=True,
    )
    pre.unlink(missing_ok=True)
    src, dst = onnx.load(str(onnx_path)), onnx.load(str(out_path))
    del dst.metadata_props[:]
    for p in src.metadata_props:
        q = dst.metadata_props.add()
        q.key, q.value = p.key, p.value
    q = dst.metadata_props.add()
    q.key, q.value = METADATA_PREFIX + "quantisation", json.dumps("INT8 static QDQ, per-channel weights")
    onnx.save(dst, str(out_path))
    return out_path


def main(argv: list[str] | None = None) -> int:
    from .config import ConfigError, load_config
    from .engine import load_checkpoint

    ap = argparse.ArgumentParser(prog="python -m oibar_models.export", description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", required=True)
    ap.add_argument("--checkpoint", help="default: runs/<name>/best.pt")
    ap.add_argument("--out", help="default: export.onnx_path or models/<name>.onnx")
    ap.add_argument(
        "--int8", action="store_true", help="also write <out>.int8.onnx (calibrated on validation frames)"
    )
    a = ap.parse_args(argv)
    try:
        cfg = load_config(a.config)
        ckpt = Path(a.checkpoint) if a.checkpoint else cfg.run_path / "best.pt"
        net, ck = load_checkpoint(ckpt)
    except (ConfigError, FileNotFoundError, RuntimeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(a.out) if a.out else cfg.onnx_file
    export_onnx(net, ck, out, cfg.export.opset, cfg.export.model_version)
    h, w = cfg.model.input_height_px, cfg.model.input_width_px
    diffs = parity(net, out, torch.rand(4, 3, h, w))
    print(
        f"wrote {out} ({out.stat().st_size / 2**20:.2f} MiB); parity vs PyTorch (max abs): "
        + ", ".join(f"{k} {v:.2e}" for k, v in diffs.items())
    )
    if a.int8 or cfg.export.int8:
        from .data import build_splits

        splits = build_splits(cfg)
        idx = np.linspace(0, len(splits.val) - 1, min(200, len(splits.val))).astype(int)
        calib = np.stack([splits.val[int(i)]["image"].numpy() for i in idx])
        q8 = quantize_int8(out, out.with_suffix(".int8.onnx"), calib)
        print(f"wrote {q8} ({q8.stat().st_size / 2**20:.2f} MiB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
