"""The fixture finder (oibar.nav.pose.finder): a small CenterNet-style network on the whole frame,
shrunk to 192x128, that says where the box around the fixture's keypoints is (its centre and
side). It exists for the keypoint estimator's cold frames: where the direct model's window misses
a far fixture the search reads 85-97 crops; the finder's window is one. Small enough to train on
2 CPU cores in minutes (about 85 k parameters).

    python -m oibar_models.finder train  --config models/configs/finder/oibarnet_finder.yaml   (resumes)
    python -m oibar_models.finder export --config models/configs/finder/oibarnet_finder.yaml   (best -> ONNX)

Labels come from the frames' poses and the keypoint model's own keypoints (its ONNX metadata),
so the box is exactly the one the flight estimator's window_around frames. The training frames are
decoded once into a cache (the frame shrunk, uint8) beside the run. Augmentation: a turn about the
principal point (rolled views), a mirror, a shift, brightness/contrast/gamma, colour gain, noise
and blur, all seeded.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
import warnings
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import torch
from torch import nn

from oibar.geometry.rotations import quat_to_matrix
from oibar.nav.keypoints import project
from oibar.nav.pose.model_file import read_metadata

from .config import REPO_ROOT, ConfigError
from .kp_data import open_scenes
from .onnx_seal import seal_onnx

INPUT_WH = (192, 128)  # the 744x480 frame / 3.9 (x) and / 3.75 (y): cells of 8 input px
STRIDE_PX = 8
SIDE_UNIT_PX = 64.0  # log_side = log(side / this): the box at ~3 m
FRAME_WH = (744, 480)  # the camera's (SPEC); build_cache checks every scene has it


@dataclass
class FinderConfig:
    name: str = "oibarnet_finder"
    model_version: str = "0.1.0"
    keypoints_from: str = "models/oibarnet.onnx"  # its oibar.keypoints_3d_m define the box
    # training frames: [scene-set spec, rendered root] or [spec, root, "i/N"] (every N-th scene from
    # the i-th, as `make dataset-train SHARD=i/N` renders them); every frame_stride-th frame
    train_sets: list[list[str]] = field(default_factory=lambda: [["models/scenes/train.json", "data/train"]])
    frame_stride: int = 1
    val_set: list[str] = field(default_factory=lambda: ["models/scenes/val.json", "data/val"])
    val_stride: int = 4
    out_dir: str = "runs/finder"
    width: int = 12  # channels of the first block; x2, x3, x4 after
    epochs: int = 12
    batch: int = 64
    lr: float = 2e-3
    weight_decay: float = 1e-4
    seed: int = 0
    threads: int = 2
    p_turn: float = 0.5  # turn about the principal point by up to turn_deg
    turn_deg: float = 180.0
    p_mirror: float = 0.5
    shift_frac: float = 0.1  # of the input size
    p_photometric: float = 0.9
    noise_sigma_max: float = 0.04
    p_blur: float = 0.3

    def path(self, p: str) -> Path:
        q = Path(p)
        return q if q.is_absolute() else REPO_ROOT / q


def load_finder_config(path: str | Path) -> FinderConfig:
    import yaml

    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read the finder config ({exc})") from exc
    known = {f.name for f in fields(FinderConfig)}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ConfigError(f"{path}: unknown keys {unknown}; known: {sorted(known)}")
    return FinderConfig(**raw)


def _bar(it: Any, what: str, on: bool, unit: str) -> Any:
    if not on:
        return it
    from oibar.progress import progress_iter

    return progress_iter(it, what, total=len(it), unit=unit)


# ----------------------------------------------------------------------------------- labels
def box_of(uv_px: np.ndarray) -> tuple[float, float, float] | None:
    """(centre u, centre v, larger side) of the finite keypoints' bounding box, as window_around
    frames it (before its margin); None where none projects."""
    p = uv_px[np.all(np.isfinite(uv_px), axis=1)]
    if len(p) == 0:
        return None
    lo, hi = p.min(0), p.max(0)
    return float((lo[0] + hi[0]) / 2), float((lo[1] + hi[1]) / 2), float(np.max(hi - lo))


def keypoints_m(model: Path) -> np.ndarray:
    return np.asarray(read_metadata(model)["keypoints_3d_m"], float)


def build_cache(
    sets: list[list[str]],
    stride: int,
    kp_m: np.ndarray,
    cfg: FinderConfig,
    cache: Path,
    progress: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Every stride-th frame of the scene sets, shrunk to INPUT_WH (uint8), and its label row
    (u, v, side px, range m) in frame pixels. Kept in `cache` (.npz): the decode is the slow part."""
    if cache.is_file():
        with np.load(cache) as z:
            return z["images"], z["labels"]
    scenes = []
    for entry in sets:
        spec, root = entry[0], entry[1]
        names = [s["name"] for s in json.loads(cfg.path(spec).read_text())["scenes"]]
        if len(entry) > 2:
            i, n = (int(x) for x in str(entry[2]).split("/"))
            names = names[i::n]
        missing = [n for n in names if not (cfg.path(root) / n / "poses.csv").is_file()]
        if missing:
            raise ConfigError(
                f"{len(missing)} of {spec}'s scenes are not rendered in {root} (first: {missing[0]}; "
                "render them with the make target of that set)"
            )
        scenes += open_scenes(cfg.path(root), names)
    odd = [sc.name for sc in scenes if (sc.width_px, sc.height_px) != FRAME_WH]
    if odd:
        raise ConfigError(f"scenes {odd} are not {FRAME_WH[0]}x{FRAME_WH[1]} frames")
    items = [(sc, k) for sc in scenes for k in range(0, len(sc), stride)]
    images = np.zeros((len(items), INPUT_WH[1], INPUT_WH[0], 3), np.uint8)
    labels = np.full((len(items), 4), np.nan, np.float32)
    for n, (sc, k) in enumerate(_bar(items, f"finder cache {cache.name}", progress, "frame")):
        img = cv2.imread(str(sc.dir / sc.files[k]), cv2.IMREAD_COLOR)
        if img is None:
            raise ConfigError(f"{sc.dir / sc.files[k]}: not a readable image")
        images[n] = cv2.resize(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), INPUT_WH, interpolation=cv2.INTER_AREA)
        uv = project(sc.K, kp_m, quat_to_matrix(sc.q_cam_target[k]), sc.T_cam_target[k])
        box = box_of(uv)
        if box is not None:
            labels[n, :3] = box
        labels[n, 3] = sc.range_m[k]
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, images=images, labels=labels)
    tmp.replace(cache)
    return images, labels


# ------------------------------------------------------------------------------------ network
def _block(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Module:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class FinderNet(nn.Module):
    """Three stride-2 stages to cells of 8 input px, then dilated blocks for context (a far
    fixture is 2 cells wide, a near one fills the frame)."""

    def __init__(self, width: int = 12):
        super().__init__()
        c1, c2, c3, c4 = width, 2 * width, 3 * width, 4 * width
        self.body = nn.Sequential(
            _block(3, c1, 2),
            _block(c1, c2, 2),
            _block(c2, c2),
            _block(c2, c3, 2),
            _block(c3, c3),
            _block(c3, c4, dilation=2),
            _block(c4, c4, dilation=4),
            _block(c4, c4, dilation=8),
        )
        self.heat = nn.Conv2d(c4, 1, 1)
        self.offset = nn.Conv2d(c4, 2, 1)
        self.log_side = nn.Conv2d(c4, 1, 1)
        nn.init.constant_(self.heat.bias, -4.6)  # p = 0.01 a cell at the start (CenterNet's prior)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        f = self.body(x)
        return self.heat(f), torch.sigmoid(self.offset(f)), self.log_side(f)


def targets(
    boxes: np.ndarray, grid_hw: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per sample (u, v, side in input px): a Gaussian heat map on the cells (1 at the centre's
    cell), the centre's cell index, its offset in the cell and log side; index -1 where none."""
    gh, gw = grid_hw
    n = len(boxes)
    heat = np.zeros((n, 1, gh, gw), np.float32)
    idx = np.full(n, -1, np.int64)
    off = np.zeros((n, 2), np.float32)
    lside = np.zeros(n, np.float32)
    yy, xx = np.mgrid[0:gh, 0:gw]
    for b, (u, v, side) in enumerate(boxes):
        if not np.isfinite(u) or not (0 <= u < gw * STRIDE_PX and 0 <= v < gh * STRIDE_PX):
            continue
        cu, cv_ = u / STRIDE_PX, v / STRIDE_PX
        j, i = int(cu), int(cv_)
        sigma = max(0.5, side / STRIDE_PX / 6.0)
        g = np.exp(-((xx - j) ** 2 + (yy - i) ** 2) / (2 * sigma**2))
        g[i, j] = 1.0
        heat[b, 0] = g
        idx[b] = i * gw + j
        off[b] = (cu - j, cv_ - i)
        lside[b] = side
    return heat, idx, off, lside


def focal_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss, normalised by the number of centres."""
    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    pos = target.eq(1.0).float()
    neg = 1.0 - pos
    pos_loss = torch.log(p) * (1 - p) ** 2 * pos
    neg_loss = torch.log(1 - p) * p**2 * (1 - target) ** 4 * neg
    return -(pos_loss.sum() + neg_loss.sum()) / pos.sum().clamp(min=1.0)


# --------------------------------------------------------------------------------- augmentation
def augment(
    img: np.ndarray,
    box_in: np.ndarray,
    rng: np.random.Generator,
    cfg: FinderConfig,
    pp_in: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """One training draw: the shrunk frame and its box (u, v, side in input px) moved alike."""
    h, w = img.shape[:2]
    u, v, side = (float(x) for x in box_in)
    M = np.eye(3)
    if rng.random() < cfg.p_turn:  # a rolled camera turns the frame about the principal point
        a = rng.uniform(-cfg.turn_deg, cfg.turn_deg)
        M = np.vstack([cv2.getRotationMatrix2D(pp_in, a, 1.0), [0, 0, 1]]) @ M
    if rng.random() < cfg.p_mirror:
        M = np.array([[-1.0, 0, w], [0, 1, 0], [0, 0, 1]]) @ M
    dx, dy = rng.uniform(-cfg.shift_frac, cfg.shift_frac, 2) * (w, h)
    M = np.array([[1.0, 0, dx], [0, 1, dy], [0, 0, 1]]) @ M
    if not np.allclose(M, np.eye(3)):
        border = int(rng.integers(0, 2))  # black (space) or the edge replicated (Earth)
        img = cv2.warpAffine(
            img, M[:2], (w, h), flags=cv2.INTER_LINEAR,
            borderMode=(cv2.BORDER_CONSTANT, cv2.BORDER_REPLICATE)[border],
        )  # fmt: skip
        if np.isfinite(u):
            u, v = (M @ np.array([u, v, 1.0]))[:2]
    x = img.astype(np.float32) / 255.0
    if rng.random() < cfg.p_photometric:
        x = x * rng.uniform(0.5, 1.6) * rng.uniform(0.85, 1.15, 3)  # exposure, white balance
        m = x.mean()
        x = (x - m) * rng.uniform(0.7, 1.3) + m
        x = np.clip(x, 0, 1) ** rng.uniform(0.7, 1.4)
        x = x + rng.normal(0, rng.uniform(0, cfg.noise_sigma_max), x.shape)
    if rng.random() < cfg.p_blur:
        x = cv2.GaussianBlur(x, (0, 0), rng.uniform(0.3, 1.0))
    return np.clip(x, 0, 1).astype(np.float32), np.array([u, v, side], np.float32)


class FinderData(torch.utils.data.Dataset):
    def __init__(self, images: np.ndarray, labels: np.ndarray, cfg: FinderConfig, train: bool, pp_in):
        self.images, self.labels, self.cfg, self.train, self.pp_in = images, labels, cfg, train, pp_in
        self.scale = np.array([INPUT_WH[0] / FRAME_WH[0], INPUT_WH[1] / FRAME_WH[1]], np.float32)

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        u, v, side = self.labels[i, :3]
        box = np.array([u * self.scale[0], v * self.scale[1], side * self.scale[0]], np.float32)
        if self.train:
            self._draws = getattr(self, "_draws", 0) + 1
            rng = np.random.default_rng([self.cfg.seed, torch.initial_seed() % 2**63, self._draws, i])
            x, box = augment(self.images[i], box, rng, self.cfg, self.pp_in)
        else:
            x = self.images[i].astype(np.float32) / 255.0
        return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1))), torch.from_numpy(box)


def loss_of(net: FinderNet, x: torch.Tensor, box: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    heat, off, lside = net(x)
    gh, gw = heat.shape[-2:]
    t_heat, idx, t_off, t_side = targets(box.numpy(), (gh, gw))
    l_heat = focal_loss(heat, torch.from_numpy(t_heat))
    has = torch.from_numpy(idx >= 0)
    if has.any():
        sel = torch.from_numpy(np.maximum(idx, 0))
        o = off.flatten(2).gather(2, sel[:, None, None].expand(-1, 2, 1))[:, :, 0][has]
        s = lside.flatten(2).gather(2, sel[:, None, None])[:, 0, 0][has]
        l_off = (o - torch.from_numpy(t_off)[has]).abs().sum(1).mean()
        # the side in frame px (input px / the x scale), as the flight decoder reads it
        side_frame = torch.from_numpy(t_side)[has] / (INPUT_WH[0] / FRAME_WH[0])
        l_side = (s - torch.log(side_frame / SIDE_UNIT_PX)).abs().mean()
    else:
        l_off = l_side = torch.zeros(())
    loss = l_heat + l_off + l_side
    return loss, {
        "heat": float(l_heat.detach()),
        "offset": float(l_off.detach()),
        "side": float(l_side.detach()),
    }


# ------------------------------------------------------------------------------- validation
def evaluate_boxes(pred: np.ndarray, labels: np.ndarray, margin: float) -> dict[str, float]:
    """How well the finder's windows would sit: the centre error in units of the window's side
    (the keypoints' box x the crop margin), by range."""
    u, v, side, rng_m = labels.T
    ok = np.isfinite(u)
    err = np.hypot(pred[:, 0] - u, pred[:, 1] - v) / (side * margin)
    side_ratio = pred[:, 2] / side
    out: dict[str, float] = {"frames": float(ok.sum())}
    for lo, hi, tag in ((0, 99, "all"), (0, 3, "0_3m"), (3, 8, "3_8m"), (8, 99, "8m_up")):
        m = ok & (rng_m >= lo) & (rng_m < hi)
        if m.any():
            out[f"center_err_side_median_{tag}"] = float(np.median(err[m]))
            out[f"within_quarter_side_pct_{tag}"] = float(100 * np.mean(err[m] <= 0.25))
            out[f"side_ratio_median_{tag}"] = float(np.median(side_ratio[m]))
    return out


def predict(net: FinderNet, images: np.ndarray, batch: int = 128) -> np.ndarray:
    """(u, v, side, score) in frame px for each shrunk frame."""
    from oibar.nav.pose.finder import decode

    net.eval()
    out = np.zeros((len(images), 4), np.float32)
    with torch.no_grad():
        for a in range(0, len(images), batch):
            x = torch.from_numpy(images[a : a + batch].astype(np.float32).transpose(0, 3, 1, 2) / 255.0)
            heat, off, lside = (t.numpy() for t in net(x))
            for k in range(len(x)):
                ans = decode(heat[k, 0], off[k], lside[k, 0], STRIDE_PX, INPUT_WH, FRAME_WH, SIDE_UNIT_PX)
                out[a + k] = (*ans.center_px, ans.side_px, ans.score)
    return out


# ----------------------------------------------------------------------------------- training
def crop_margin(model: Path) -> float:
    return float(read_metadata(model)["crop"]["margin"])


def train(cfg: FinderConfig, progress: bool = True) -> dict[str, Any]:
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    out = cfg.path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(json.dumps(asdict(cfg), indent=1) + "\n")
    kp_model = cfg.path(cfg.keypoints_from)
    kp_m, margin = keypoints_m(kp_model), crop_margin(kp_model)
    key = hashlib.sha256(json.dumps([cfg.train_sets, cfg.frame_stride, kp_m.tolist()]).encode()).hexdigest()[
        :12
    ]
    tr_img, tr_lab = build_cache(
        cfg.train_sets, cfg.frame_stride, kp_m, cfg, out / f"cache_train_{key}.npz", progress
    )
    vkey = hashlib.sha256(json.dumps([cfg.val_set, cfg.val_stride, kp_m.tolist()]).encode()).hexdigest()[:12]
    va_img, va_lab = build_cache(
        [cfg.val_set], cfg.val_stride, kp_m, cfg, out / f"cache_val_{vkey}.npz", progress
    )
    K0 = open_scenes(
        cfg.path(cfg.val_set[1]), [json.loads(cfg.path(cfg.val_set[0]).read_text())["scenes"][0]["name"]]
    )[0].K
    pp_in = (float(K0[0, 2]) * INPUT_WH[0] / FRAME_WH[0], float(K0[1, 2]) * INPUT_WH[1] / FRAME_WH[1])
    net = FinderNet(cfg.width)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    loader = torch.utils.data.DataLoader(
        FinderData(tr_img, tr_lab, cfg, True, pp_in), batch_size=cfg.batch, shuffle=True, drop_last=True,
        generator=torch.Generator().manual_seed(cfg.seed),
    )  # fmt: skip
    total = cfg.epochs * len(loader)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, cfg.lr, total_steps=total, pct_start=0.1)
    start_epoch, best = 0, {"score": -1.0}
    last = out / "last.pt"
    if last.is_file():  # resume
        ck = torch.load(last, weights_only=False)
        net.load_state_dict(ck["net"])
        opt.load_state_dict(ck["opt"])
        sched.load_state_dict(ck["sched"])
        torch.set_rng_state(ck["torch_rng"])
        start_epoch, best = ck["epoch"] + 1, ck["best"]
    log = out / "log.jsonl"
    for epoch in range(start_epoch, cfg.epochs):
        net.train()
        t0, sums, n = time.time(), {"heat": 0.0, "offset": 0.0, "side": 0.0}, 0
        for x, box in _bar(loader, f"finder epoch {epoch + 1}/{cfg.epochs}", progress, "batch"):
            loss, parts = loss_of(net, x, box)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            for k in sums:
                sums[k] += parts[k]
            n += 1
        metrics = evaluate_boxes(predict(net, va_img), va_lab, margin)
        # chosen on validation: windows within a quarter side far out, where the search is slow
        score = metrics.get("within_quarter_side_pct_8m_up", 0.0) + metrics.get(
            "within_quarter_side_pct_all", 0.0
        )
        row = {"step": (epoch + 1) * len(loader), "epoch": epoch + 1, "train_s": time.time() - t0,
               **{f"loss_{k}": v / max(n, 1) for k, v in sums.items()}, **metrics, "score": score}  # fmt: skip
        with log.open("a") as f:
            f.write(json.dumps(row) + "\n")
        if score > best["score"]:
            best = {"epoch": epoch + 1, **metrics, "score": score}
            torch.save({"net": net.state_dict(), "cfg": asdict(cfg), "best": best}, out / "best.pt")
        torch.save(
            {"net": net.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
             "torch_rng": torch.get_rng_state(), "epoch": epoch, "best": best}, last,
        )  # fmt: skip
        print(f"finder epoch {epoch + 1}: {json.dumps({k: round(v, 3) for k, v in row.items()})}", flush=True)
    (out / "done.json").write_text(json.dumps(best, indent=1) + "\n")
    from . import tracking

    try:
        tracking.log_training(
            SimpleNamespace(name=cfg.name, path=cfg.out_dir, seed=cfg.seed), "train", cfg, out, best
        )
    except tracking.TrackingError as exc:
        print(f"finder: not tracked ({exc})", file=sys.stderr)
    return best


def export(cfg: FinderConfig, out_path: Path | None = None) -> Path:
    """best.pt -> ONNX with the finder's metadata, checked against PyTorch on a random input."""
    run = cfg.path(cfg.out_dir)
    ck = torch.load(run / "best.pt", weights_only=False)
    net = FinderNet(cfg.width)
    net.load_state_dict(ck["net"])
    net.eval()
    # beside its run, not into models/: the shipped model's finder lies there (0.35.15 on)
    out_path = out_path or run / f"{cfg.name}.onnx"
    x = torch.rand(1, 3, INPUT_WH[1], INPUT_WH[0], generator=torch.Generator().manual_seed(0))
    tmp = out_path.with_suffix(".tmp.onnx")
    with (
        warnings.catch_warnings()
    ):  # the TorchScript exporter is deprecated, and the pinned torch's stable path
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            net, (x,), str(tmp), input_names=["image"], output_names=["heat", "offset", "log_side"],
            opset_version=17, dynamo=False,
        )  # fmt: skip
    meta = {
        "kind": "finder",
        "model_version": cfg.model_version,
        "input_size_wh": list(INPUT_WH),
        "frame_size_wh": list(FRAME_WH),
        "stride_px": STRIDE_PX,
        "side_unit_px": SIDE_UNIT_PX,
        "keypoints_from": Path(cfg.keypoints_from).name,
        "validation": {k: round(v, 4) for k, v in ck["best"].items()},
    }
    worst = seal_onnx(tmp, meta, "oibar_models.finder", net, x)
    tmp.replace(out_path)
    print(f"finder: {out_path} (parity {worst:.1e}; validation {meta['validation']})")
    return out_path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_models.finder", description=__doc__.splitlines()[0])
    ap.add_argument("cmd", choices=("train", "export"))
    ap.add_argument("--config", type=Path, default=REPO_ROOT / "models/configs/finder/oibarnet_finder.yaml")
    ap.add_argument(
        "--out", type=Path, default=None, help="export: the ONNX file (default <out_dir>/<name>.onnx)"
    )
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    try:
        cfg = load_finder_config(args.config)
        if args.cmd == "train":
            best = train(cfg, progress=not args.no_progress)
            print(f"finder: best epoch {best.get('epoch')}: {json.dumps(best)}")
        else:
            export(cfg, args.out)
    except (ConfigError, FileNotFoundError) as exc:
        print(f"finder: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
