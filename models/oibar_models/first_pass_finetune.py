"""Fine-tuning the first pass (the direct model, oibarnet_lite) on lab recordings beside the
keypoint network (issue 58 item 5).

Why: a keypoint file fine-tuned on a new look still carries the shipped first pass, which never
saw it. On the lab demonstration's validation run (lb009, Mitsuba's lab look: grey print, spot
lamp, black background) the shipped first pass reads the fixture 1.5-10x as far as it is under 7 m, so
the estimator flags 44 of 75 frames `direct_disagrees` (confidence x0.3) however right its fit
is, until a run of three strong fits within 5 s overrules it; and where PnP fails, its fallback
answer is the first pass's own: 10x the range at 0.5 m, and upright on a rolled approach.

The shipped ONNX is the checkpoint: its weights go back into OibarNet (`recover`; the export
folded the batch norms into the convolutions, so their statistics stay fixed, which suits a few
hundred frames), is fine-tuned on the lab frames at the network's input
size (the flight code's own resize), a share of them rolled about the principal point by any
angle with the label rolled alike (oibar_models.rolled), and exported with the same outputs and
the shipped file's metadata, marked `oibar.finetune`.

python -m oibar_models.first_pass_finetune --init models/oibarnet_lite.onnx --data DIR [DIR ...] \
    --out FILE [--steps 600] [--lr 2e-4] [--roll-share 0.5] [--seed 0]

Exit status: 0 written, 2 bad arguments, an unreadable model or sequence.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from .data import DatasetError, Sequence, load_sequence
from .geometry import rot6d_from_matrix_np
from .nets import OibarNet, PoseOutputs

# The schedule: STEPS steps of BATCH frames at a peak rate of LR (cosine to LR / 40), ROLL_SHARE
# of the frames rolled by any angle. Chosen on the lab demonstration's validation runs
# (docs/calibration.md, "The first pass, fine-tuned too").
STEPS = 600
BATCH = 16
LR = 2e-4
ROLL_SHARE = 0.0
PARITY_TOL = 1e-4  # metres, or units of rot6d: the recovered network and the export against the file
OUTPUTS = ("position_m", "rot6d")
EXPORT_OUTPUTS = ("position_m", "q_cam_target", "R_cam_target", "rot6d")


class FirstPassError(RuntimeError):
    """A first-pass file or data this code cannot use (with the reason)."""


def read_meta(path: Path) -> tuple[Any, dict]:
    """(the ONNX model, its oibar.* metadata decoded, as the flight code reads it)."""
    import onnx

    from oibar.nav.pose import ModelFileError, read_metadata

    try:
        meta = read_metadata(path)
    except ModelFileError as exc:
        raise FirstPassError(str(exc)) from exc
    m = onnx.load(str(path))
    names = [o.name for o in m.graph.output]
    if any(n not in names for n in OUTPUTS):
        raise FirstPassError(f"{path}: not a direct-model export (its outputs are {names})")
    return m, meta


def recover(path: Path) -> tuple[OibarNet, dict]:
    """The file's network as a trainable OibarNet computing what the file computes, checked
    against onnxruntime on random frames; and its metadata. The export folds each batch norm into
    the convolution before it: the convolution gets the folded weights and its batch norm becomes
    the identity plus the folded bias (statistics fixed: `freeze_batch_norms`)."""
    from onnx import numpy_helper

    m, meta = read_meta(path)
    if meta.get("backbone") != "oibar_lite":
        raise FirstPassError(f"{path}: backbone {meta.get('backbone')!r}; this code recovers oibar_lite only")
    inits = {i.name: numpy_helper.to_array(i) for i in m.graph.initializer}
    # the exporter stores equal constants once (all-zero biases of an untrained network) and
    # names the others as Identity nodes of it
    for n in m.graph.node:
        if n.op_type == "Identity" and n.input[0] in inits:
            inits[n.output[0]] = inits[n.input[0]]
    # the convolutions' (weight, bias) in the graph's order, which is the forward pass's
    convs = [
        (inits[n.input[1]], inits[n.input[2]] if len(n.input) > 2 else None)
        for n in m.graph.node
        if n.op_type == "Conv"
    ]
    try:
        stem = convs[0][0]
        uv_mean, uv_std = inits["net.uvlogz_mean"], inits["net.uvlogz_std"]
        head_in = int(inits["net.head_t.weight"].shape[1])
    except (KeyError, IndexError) as exc:
        raise FirstPassError(f"{path}: not the oibar_lite graph this code knows ({exc} missing)") from exc
    shape = {"coord_channels": stem.shape[1] == 5, "pos_param": "uvlogz"}
    width = stem.shape[0] / 16
    # the heads read the pooled features and, with a keypoint branch, 2 coordinates per keypoint
    keypoints = (head_in - OibarNet("oibar_lite", width, **shape).feature_dim) // 2  # type: ignore[arg-type]
    net = OibarNet(
        "oibar_lite",
        width,
        uvlogz_mean=tuple(float(v) for v in uv_mean),
        uvlogz_std=tuple(float(v) for v in uv_std),
        keypoints=max(0, keypoints),
        **shape,  # type: ignore[arg-type]
    )
    w, h = meta["input_size_wh"]
    names = conv_order(net, (h, w))
    if len(names) != len(convs):
        raise FirstPassError(f"{path}: {len(convs)} convolutions, OibarNet of its shape has {len(names)}")
    mods = dict(net.named_modules())
    state = net.state_dict()
    for name, (W, b) in zip(names, convs, strict=True):
        conv = mods[name]
        bn_name = name[:-1] + "1" if name.endswith(".0") else ""
        bn = mods.get(bn_name)
        if not isinstance(conv, nn.Conv2d) or tuple(conv.weight.shape) != W.shape:
            raise FirstPassError(f"{path}: a convolution of shape {W.shape} where OibarNet has {name}")
        state[f"{name}.weight"] = torch.from_numpy(W.copy())
        if isinstance(bn, nn.BatchNorm2d) and b is not None:
            state[f"{bn_name}.weight"] = torch.ones(W.shape[0])
            state[f"{bn_name}.bias"] = torch.from_numpy(b.copy())
            state[f"{bn_name}.running_mean"] = torch.zeros(W.shape[0])
            state[f"{bn_name}.running_var"] = torch.full((W.shape[0],), 1.0 - bn.eps)
        elif b is not None:
            state[f"{name}.bias"] = torch.from_numpy(b.copy())
    for head in ("head_t", "head_r"):
        state[f"{head}.weight"] = torch.from_numpy(inits[f"net.{head}.weight"].copy())
        state[f"{head}.bias"] = torch.from_numpy(inits[f"net.{head}.bias"].copy())
    net.load_state_dict(state)
    net.eval()
    x = np.random.default_rng(0).random((2, 3, h, w), dtype=np.float32)
    diff = parity(path, net, x)
    if diff > PARITY_TOL:
        raise FirstPassError(f"{path}: the recovered network differs from the file by {diff:.2e}")
    return net, meta


def conv_order(net: nn.Module, hw: tuple[int, int]) -> list[str]:
    """The names of net's convolutions in the order its forward pass runs them."""
    names = {id(mod): n for n, mod in net.named_modules()}
    order: list[str] = []
    hooks = [
        mod.register_forward_hook(lambda mod, i, o: order.append(names[id(mod)]))
        for mod in net.modules()
        if isinstance(mod, nn.Conv2d)
    ]
    try:
        with torch.no_grad():
            net.eval()(torch.zeros(1, 3, *hw))
    finally:
        for hk in hooks:
            hk.remove()
    return order


def freeze_batch_norms(net: nn.Module) -> None:
    """Batch norms in evaluation mode (the recovered statistics) while the rest trains: a batch of
    16 frames of a few lab runs is too narrow a sample to renormalise by."""
    for mod in net.modules():
        if isinstance(mod, nn.BatchNorm2d):
            mod.eval()


def parity(path: Path, net: nn.Module, x: np.ndarray) -> float:
    """Largest difference between the file's position_m / rot6d (onnxruntime) and net's on x."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = dict(zip([o.name for o in sess.get_outputs()], sess.run(None, {"image": x}), strict=True))
    with torch.no_grad():
        want = net.eval()(torch.from_numpy(x))
    return max(float(np.max(np.abs(got[n] - w.numpy()))) for n, w in zip(OUTPUTS, want, strict=True))


class LabFrames:
    """Every frame of the sequences at the network's input size (uint8, in memory) with its
    label, and augmented batches: a share rolled by any angle about the principal point (the
    pose rolled with it, exact for a pinhole camera), brightness, contrast and gamma jittered,
    all from one seeded generator."""

    def __init__(self, seqs: list[Sequence], size_wh: tuple[int, int], camera: dict, progress: bool = False):
        from PIL import Image

        from oibar.geometry.rotations import quat_to_matrix
        from oibar.nav.pose import resize_frame

        self.size_wh = (int(size_wh[0]), int(size_wh[1]))
        w, h = self.size_wh
        # the principal point at the input size (the generator's convention: pixel edges)
        self.cx_px = float(camera["cx_px"]) * w / float(camera["width_px"])
        self.cy_px = float(camera["cy_px"]) * h / float(camera["height_px"])
        images, T, R = [], [], []
        items = [(s, k) for s in seqs for k in range(len(s))]
        it: Any = items
        if progress:
            from oibar.progress import progress_iter

            it = progress_iter(items, "frames", total=len(items), unit="frame", leave=False)
        for s, k in it:
            images.append(resize_frame(Image.open(s.dir / s.files[k]), self.size_wh))
            T.append(s.T_cam_target[k])
            R.append(quat_to_matrix(s.q_cam_target[k]))
        if not images:
            raise FirstPassError("no training frames")
        self.images = np.stack(images)
        self.T_m = np.asarray(T, float)
        self.R = np.asarray(R, float)

    def __len__(self) -> int:
        return len(self.images)

    def batch(self, rng: np.random.Generator, n: int, roll_share: float) -> dict[str, torch.Tensor]:
        from .rolled import roll_matrix, rolled_frame

        idx = rng.integers(0, len(self), n)
        imgs, T, r6 = [], [], []
        for i in idx:
            img, T_m, R = self.images[i], self.T_m[i], self.R[i]
            if rng.random() < roll_share:
                roll_deg = float(rng.uniform(-180.0, 180.0))
                img = rolled_frame(img, roll_deg, self.cx_px, self.cy_px)
                Rz = roll_matrix(roll_deg)
                T_m, R = Rz @ T_m, Rz @ R
            x = img.astype(np.float32) / 255.0
            x = x * rng.uniform(0.8, 1.2) + rng.uniform(-0.05, 0.05)  # gain and offset
            x = np.clip(x, 0.0, 1.0) ** rng.uniform(0.85, 1.15)  # gamma
            imgs.append(x.transpose(2, 0, 1))
            T.append(T_m)
            r6.append(rot6d_from_matrix_np(R))
        return {
            "image": torch.from_numpy(np.ascontiguousarray(np.stack(imgs), dtype=np.float32)),
            "T_m": torch.tensor(np.asarray(T), dtype=torch.float32),
            "rot6d": torch.tensor(np.asarray(r6), dtype=torch.float32),
        }


def keypoint_supervision(net: OibarNet, meta: dict):
    """The trainer's keypoint targets (engine.KeypointSupervision: the fixture's origin and rim
    corners projected into the input image) for `net`'s soft-argmax branch, or None without one."""
    from types import SimpleNamespace

    from .config import ModelConfig
    from .engine import KeypointSupervision

    if not net.keypoints:
        return None
    w, h = meta["input_size_wh"]
    cfg = SimpleNamespace(model=ModelConfig(input_width_px=int(w), input_height_px=int(h)))
    return KeypointSupervision(cfg, np.asarray(meta["camera"]["K_input"], float), net)


def batch_loss(crit, net: OibarNet, b: dict[str, torch.Tensor], kp_sup) -> dict[str, torch.Tensor]:
    """The trainer's loss (loss.UncertaintyPoseLoss: position error as a share of the range, the
    paper's metric; the 6D attitude error; the keypoints' mean image error in half-widths of the
    image where the network has them, which is what tells the fixture's roll), its terms weighted
    alike (`crit` is not trained) and taken as batch means."""
    feats = net.features(b["image"])
    T_hat, r6_hat = net.heads(feats)
    out = crit(T_hat, r6_hat, b["T_m"], b["rot6d"])
    n = len(b["image"])
    terms = {"dt_frac": out["L_t"] / n, "dr6": out["L_r"] / n}
    loss = out["loss"]
    if kp_sup is not None:
        kp_true, valid = kp_sup.targets(b["T_m"], b["rot6d"])
        kp_term, terms["dkp"] = crit.keypoint_term(kp_sup.predicted(feats), kp_true, valid)
        loss = loss + kp_term
        terms["dkp"] = terms["dkp"] / n
    return {"loss": loss / n, **terms}


def schedule(steps: int, lr: float):
    """The keypoint trainer's schedule (kp_engine.lr_at): a warm-up over 5 % of the steps, then
    cosine from `lr` to lr / 40."""
    from .kp_engine import KpTrain

    return KpTrain(steps=steps, lr=lr, lr_min=lr / 40, warmup_steps=max(1, steps // 20))


def finetune(
    net: OibarNet,
    frames: LabFrames,
    steps: int = STEPS,
    lr: float = LR,
    roll_share: float = ROLL_SHARE,
    batch: int = BATCH,
    seed: int = 0,
    progress: bool = False,
    log=None,
    kp_sup=None,
) -> list[dict]:
    """`steps` Adam steps on `frames` (`kp_sup`: keypoint_supervision's targets, or None);
    -> one row per 50 steps (a tenth of them when fewer than 500), and the last."""
    from .kp_engine import lr_at
    from .loss import UncertaintyPoseLoss

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    crit = UncertaintyPoseLoss(range_normalised=True).requires_grad_(False)  # weights stay exp(0) = 1
    sched = schedule(steps, lr)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    net.train()
    freeze_batch_norms(net)
    rows: list[dict] = []
    bar = None
    if progress:
        from oibar.progress import Progress

        bar = Progress("first pass", total=steps, unit="step", leave=False)
    sums = {"dt_frac": 0.0, "dr6": 0.0, "dkp": 0.0}
    n = 0
    t0 = time.perf_counter()
    every = max(1, min(50, steps // 10))
    for step in range(steps):
        for g in opt.param_groups:
            g["lr"] = lr_at(step, sched)
        out = batch_loss(crit, net, frames.batch(rng, batch, roll_share), kp_sup)
        opt.zero_grad(set_to_none=True)
        out["loss"].backward()
        opt.step()
        for k in sums:
            sums[k] += float(out.get(k, 0.0))
        n += 1
        if bar:
            bar.update(1)
        if (step + 1) % every == 0 or step + 1 == steps:
            row = {
                "step": step + 1,
                "lr": opt.param_groups[0]["lr"],
                "dt_pct": 100 * sums["dt_frac"] / n,
                "dr6": sums["dr6"] / n,
                "dkp": sums["dkp"] / n,
                "elapsed_s": round(time.perf_counter() - t0, 1),
            }
            rows.append(row)
            if log:
                log(
                    f"first pass step {row['step']}: position {row['dt_pct']:.2f} % of range, "
                    f"rot6d {row['dr6']:.4f}, keypoints {row['dkp']:.4f}"
                )
            sums = {k: 0.0 for k in sums}
            n = 0
    if bar:
        bar.close()
    net.eval()
    return rows


def export(net: nn.Module, src: Path, out: Path, finetune_meta: dict) -> Path:
    """`net` as a flight first-pass file at `out`: the outputs, input and metadata of `src`, and
    `oibar.finetune`; written atomically after its outputs match the module's."""
    import onnx
    import onnxruntime as ort

    m_src, meta = read_meta(src)
    w, h = meta["input_size_wh"]
    opset = max(o.version for o in m_src.opset_import if o.domain in ("", "ai.onnx"))
    wrapper = PoseOutputs(net.eval()).eval()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp.onnx")
    # the TorchScript exporter is deprecated but is the pinned torch's stable path
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            wrapper,
            torch.rand(1, 3, h, w),
            str(tmp),
            input_names=["image"],
            output_names=list(EXPORT_OUTPUTS),
            dynamic_axes={n: {0: "batch"} for n in ("image", *EXPORT_OUTPUTS)},
            opset_version=opset,
            dynamo=False,
        )
    m = onnx.load(str(tmp))
    new = {
        **meta,
        "model_version": f"{meta.get('model_version', '0.0.0')}+finetune",
        "finetune": finetune_meta,
    }
    for k, v in new.items():
        p = m.metadata_props.add()
        p.key, p.value = "oibar." + k, json.dumps(v)
    m.producer_name = "oibar_models.first_pass_finetune"
    onnx.checker.check_model(m)
    onnx.save(m, str(tmp))
    x = np.random.default_rng(1).random((2, 3, h, w), dtype=np.float32)
    sess = ort.InferenceSession(str(tmp), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"image": x})
    with torch.no_grad():
        want = [t.numpy() for t in wrapper(torch.from_numpy(x))]
    diff = max(float(np.max(np.abs(a - b))) for a, b in zip(got, want, strict=True))
    if diff > PARITY_TOL:
        tmp.unlink(missing_ok=True)
        raise FirstPassError(f"{out}: the export differs from the network by {diff:.2e}")
    tmp.replace(out)
    return out


def camera_of(seqs: list[Sequence], meta: dict) -> dict:
    """The camera the frames were taken with: the file's (the sequences must match it)."""
    cam = meta.get("camera") or {}
    if not all(k in cam for k in ("cx_px", "cy_px", "width_px", "height_px")):
        raise FirstPassError("the first pass's metadata has no camera (oibar.camera)")
    for s in seqs:
        if (s.width_px, s.height_px) != (cam["width_px"], cam["height_px"]):
            raise FirstPassError(
                f"{s.dir}: frames {s.width_px}x{s.height_px}, the model's camera {cam['width_px']}x{cam['height_px']}"
            )
    return cam


def run(
    init: Path,
    data: list[Path],
    out: Path,
    steps: int = STEPS,
    lr: float = LR,
    roll_share: float = ROLL_SHARE,
    seed: int = 0,
    threads: int = 0,
    progress: bool = False,
    log=print,
    provenance: dict | None = None,
) -> dict:
    """Recover `init`, fine-tune it on `data`, export to `out`; -> the file's oibar.finetune."""
    if threads > 0:
        torch.set_num_threads(threads)
    net, meta = recover(init)
    seqs = [load_sequence(p) for p in data]
    frames = LabFrames(seqs, tuple(meta["input_size_wh"]), camera_of(seqs, meta), progress)
    log(f"first pass: {len(frames)} frames of {len(seqs)} sequences, {steps} steps at {lr:g}")
    rows = finetune(
        net, frames, steps, lr, roll_share, BATCH, seed, progress, log, keypoint_supervision(net, meta)
    )
    info = {
        "from_model_version": meta.get("model_version"),
        "steps": steps,
        "lr": lr,
        "batch": BATCH,
        "roll_share": roll_share,
        "seed": seed,
        "frames": len(frames),
        "last": rows[-1] if rows else {},
        "ships": False,
        **(provenance or {}),
    }
    export(net, init, out, info)
    return info


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m oibar_models.first_pass_finetune", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument(
        "--init", type=Path, required=True, help="the first pass to start from (a direct-model ONNX)"
    )
    ap.add_argument("--data", nargs="+", type=Path, required=True, help="training sequences (folders)")
    ap.add_argument("--out", type=Path, required=True, help="the fine-tuned file to write")
    ap.add_argument("--steps", type=int, default=STEPS, help=f"training steps (default {STEPS})")
    ap.add_argument("--lr", type=float, default=LR, help=f"peak learning rate (default {LR:g})")
    ap.add_argument(
        "--roll-share",
        type=float,
        default=ROLL_SHARE,
        help=f"share of frames rolled by any angle (default {ROLL_SHARE:g})",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    if a.steps < 1 or not (a.lr > 0 and math.isfinite(a.lr)):
        ap.error("--steps must be >= 1 and --lr a finite number > 0")
    if not 0.0 <= a.roll_share <= 1.0:
        ap.error("--roll-share must be in [0, 1]")
    try:
        run(a.init, a.data, a.out, a.steps, a.lr, a.roll_share, a.seed, a.threads, not a.no_progress)
    except (FirstPassError, DatasetError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"written: {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
