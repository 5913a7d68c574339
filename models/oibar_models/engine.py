"""Training engine: Adam, a cyclical learning rate with 5 cycles (the paper, after Smith 2017),
a checkpoint every epoch and automatic resume after an interruption, logs as JSONL and CSV, and
a progress bar.

Run folder (runs/<name>/): config.yaml, split.json, labels.json, log.jsonl, log.csv,
last.pt (every epoch), best.pt (best validation score), done.json when training finished.
"""

from __future__ import annotations

import csv
import json
import math
import os
import random
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from . import metrics
from .data import build_splits, label_statistics
from .geometry import matrix_from_rot6d, quat_from_matrix
from .loss import UncertaintyPoseLoss
from .nets import build_model, count_parameters, widen_heads_from


def cyclical_lr(step: int, total_steps: int, cfg) -> float:
    """Triangular cycles between lr_min and a peak that starts at lr_max and shrinks by
    lr_cycle_decay per cycle: warm restarts help escape early plateaus, the decay lets the
    last cycle settle."""
    t = cfg.train
    cycle_len = max(1, math.ceil(total_steps / t.lr_cycles))
    cycle = min(step // cycle_len, t.lr_cycles - 1)
    x = (step - cycle * cycle_len) / cycle_len  # 0..1 inside the cycle
    peak = t.lr_max * (t.lr_cycle_decay**cycle)
    tri = 1.0 - abs(2.0 * x - 1.0)  # 0 -> 1 -> 0
    return t.lr_min + (peak - t.lr_min) * tri


class KeypointSupervision:
    """Projected fixture points (normalised image coordinates) as targets for the first heat
    maps of the keypoint branch; points behind the camera or outside the image are masked."""

    def __init__(self, cfg, K_input: np.ndarray, net) -> None:
        pts = np.asarray(cfg.model.keypoints_3d_m, dtype=np.float32)
        if not net.keypoints or len(pts) > net.keypoints:
            raise ValueError(f"train.kp_loss needs model.keypoints >= {len(pts)} (the supervised points)")
        self.X_t = torch.tensor(pts)
        self.K = torch.tensor(K_input, dtype=torch.float32)
        self.wh = (cfg.model.input_width_px, cfg.model.input_height_px)
        self.n_pts = len(pts)
        self.n_kp = net.keypoints
        self.base = net.feature_dim - 2 * net.keypoints

    def targets(self, T: torch.Tensor, r6: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        R = matrix_from_rot6d(r6)
        p = torch.einsum("nij,pj->npi", R, self.X_t.to(T.device)) + T[:, None, :]
        z = p[..., 2].clamp_min(1e-3)
        u = self.K[0, 0] * p[..., 0] / z + self.K[0, 2]
        v = self.K[1, 1] * p[..., 1] / z + self.K[1, 2]
        uv = torch.stack([u / self.wh[0] * 2 - 1, v / self.wh[1] * 2 - 1], -1)
        valid = ((p[..., 2] > 0.05) & (uv.abs() < 0.97).all(-1)).float()
        return uv, valid

    def predicted(self, feats: torch.Tensor) -> torch.Tensor:
        k = feats[:, self.base :]
        return torch.stack([k[:, : self.n_pts], k[:, self.n_kp : self.n_kp + self.n_pts]], -1)


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _save_atomic(obj, path: Path) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


@torch.no_grad()
def predict(net, loader, device, progress: bool = False, desc: str = "eval") -> dict:
    """Run the network over a loader; returns numpy arrays of predictions and labels."""
    net.eval()
    out = {k: [] for k in ("T_hat", "q_hat", "T", "q", "seq", "frame")}
    it = loader
    if progress:
        from oibar.progress import progress_iter

        it = progress_iter(loader, desc, unit="batch", leave=False)
    for b in it:
        T_hat, r6 = net(b["image"].to(device))
        out["T_hat"].append(T_hat.cpu().numpy())
        out["q_hat"].append(quat_from_matrix(matrix_from_rot6d(r6)).cpu().numpy())
        out["T"].append(b["T_cam_target"].numpy())
        out["q"].append(b["q_cam_target"].numpy())
        out["seq"].append(np.asarray(b["seq"]))
        out["frame"].append(np.asarray(b["frame"]))
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}


def load_checkpoint(path: str | Path, map_location="cpu"):
    """-> (net, checkpoint dict). Clear error when the file is missing or not ours."""
    from .config import from_dict

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path} (train first: `make train`)")
    try:
        ck = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:
        raise RuntimeError(f"{path}: not a readable checkpoint ({exc})") from exc
    if not isinstance(ck, dict) or "model" not in ck or "config" not in ck:
        raise RuntimeError(f"{path}: not an OibarNet checkpoint (no model/config entries)")
    cfg = from_dict(ck["config"])
    lab = ck["labels"]
    net = build_model(
        cfg.model,
        lab["pos_mean_m"],
        lab["pos_std_m"],
        lab["rot6d_mean"],
        lab.get("uvlogz_mean"),
        lab.get("uvlogz_std"),
    )
    net.load_state_dict(ck["model"])
    net.eval()
    return net, ck


def _data_loaders(cfg, splits) -> tuple[torch.utils.data.DataLoader, torch.utils.data.DataLoader]:
    """The training loader (shuffled by a generator seeded from train.seed) and the validation
    loader (thinned evenly to train.val_max_frames)."""
    g = torch.Generator()
    g.manual_seed(cfg.train.seed)
    workers = cfg.train.workers
    train_loader = torch.utils.data.DataLoader(
        splits.train,
        batch_size=cfg.train.batch_size,
        shuffle=True,
        drop_last=len(splits.train) > cfg.train.batch_size,
        num_workers=workers,
        persistent_workers=False,
        generator=g,
    )
    val_ds = splits.val
    if cfg.train.val_max_frames and len(val_ds) > cfg.train.val_max_frames:
        val_ds = torch.utils.data.Subset(
            val_ds, np.linspace(0, len(val_ds) - 1, cfg.train.val_max_frames).astype(int)
        )
    val_loader = torch.utils.data.DataLoader(val_ds, batch_size=cfg.train.batch_size, num_workers=0)
    return train_loader, val_loader


def _restore(cfg, last: Path, net, crit, opt, device, log) -> tuple[int, int, float]:
    """Resume from ``last`` (run/last.pt) when it exists, else start from train.init_from (the
    previous stage) when set. -> (epochs done, optimiser steps done, best validation score)."""
    start_epoch, step, best = 0, 0, float("inf")
    if not last.is_file() and cfg.train.init_from:
        src = cfg.path(cfg.train.init_from)
        if not src.is_file():
            raise FileNotFoundError(f"train.init_from: {src} not found (train that stage first)")
        state = torch.load(src, map_location=device, weights_only=False)["model"]
        if state["head_t.weight"].shape != net.head_t.weight.shape:
            state = widen_heads_from(net, state)
        net.load_state_dict(state)
        log(f"initialised from {src}")
    if last.is_file():
        ck = torch.load(last, map_location=device, weights_only=False)
        if ck["config"]["model"] != cfg.to_dict()["model"]:
            raise RuntimeError(
                f"{last}: was trained with another model config; use a new run_dir or delete it"
            )
        net.load_state_dict(ck["model"])
        crit.load_state_dict(ck["loss"], strict=False)  # runs from before the keypoint term lack s_k
        try:
            opt.load_state_dict(ck["optimizer"])
        except ValueError as exc:  # parameter groups changed with the loss: fresh moments
            log(f"optimizer state not restored ({exc}); Adam restarts its moment estimates")
        start_epoch, step, best = ck["epoch"], ck["step"], ck["best_score"]
        torch.set_rng_state(ck["torch_rng"])
        log(f"resumed from {last}: {start_epoch} epoch(s) done, step {step}")
    return start_epoch, step, best


def _train_epoch(
    cfg,
    epoch: int,
    net,
    crit,
    opt,
    kp_sup,
    train_loader,
    steps_per_epoch: int,
    step: int,
    total_steps: int,
    device,
    fmt,
    progress: bool,
) -> tuple[dict, int, int, float]:
    """One epoch of optimiser steps. -> (summed loss terms, images seen, step count, last lr)."""
    sums = {"loss": 0.0, "L_r": 0.0, "L_t": 0.0}
    n_img = 0
    it = iter(train_loader)
    bar = None
    if progress:
        from oibar.progress import Progress

        bar = Progress(
            f"epoch {epoch + 1}/{cfg.train.epochs}", total=steps_per_epoch, unit="batch", leave=False
        )
    for _ in range(steps_per_epoch):
        b = next(it)
        lr = cyclical_lr(step, total_steps, cfg)
        for pg in opt.param_groups:
            pg["lr"] = lr
        feats = net.features(b["image"].to(device).contiguous(memory_format=fmt))
        T_hat, r6_hat = net.heads(feats)
        T_true = b["T_cam_target"].to(device)
        out = crit(T_hat, r6_hat, T_true, b["rot6d"].to(device))
        if kp_sup is not None:
            kp_true, valid = kp_sup.targets(T_true, b["rot6d"].to(device))
            term, L_k = crit.keypoint_term(kp_sup.predicted(feats), kp_true, valid)
            out["loss"] = out["loss"] + term
            out["L_k"] = L_k
        opt.zero_grad(set_to_none=True)
        out["loss"].backward()
        opt.step()
        step += 1
        bs = len(b["image"])
        n_img += bs
        for k in sums:
            sums[k] += out[k].item()
        if bar:
            bar.update(1)
            bar.set_postfix(
                loss=f"{out['loss'].item():.2f}", dt_m=f"{out['L_t'].item() / bs:.3f}", lr=f"{lr:.1e}"
            )
    del it  # the loader's workers end here, before validation
    if bar:
        bar.close()
    return sums, n_img, step, lr


def _append_logs(run: Path, fields: list[str], row: dict) -> None:
    """One epoch's row into log.jsonl and log.csv (the header with the first row)."""
    with open(run / "log.jsonl", "a") as fh:
        fh.write(json.dumps(row) + "\n")
    csv_path = run / "log.csv"
    new_csv = not csv_path.exists()
    with open(csv_path, "a", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
        if new_csv:
            w.writeheader()
        w.writerow(row)


def train(cfg, progress: bool = True, log=print) -> dict:
    """Train ``cfg``'s model into its run folder (resuming there if it has a last.pt);
    -> the last epoch's log row."""
    run = cfg.run_path
    run.mkdir(parents=True, exist_ok=True)
    seed_everything(cfg.train.seed)
    if cfg.train.threads > 0:
        torch.set_num_threads(cfg.train.threads)
    device = pick_device(cfg.train.device)

    splits = build_splits(cfg, progress=progress)
    labels = label_statistics(splits.train)
    (run / "split.json").write_text(json.dumps(splits.split_info, indent=1) + "\n")
    (run / "labels.json").write_text(json.dumps(labels, indent=1) + "\n")
    (run / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))

    net = build_model(
        cfg.model,
        labels["pos_mean_m"],
        labels["pos_std_m"],
        labels["rot6d_mean"],
        labels["uvlogz_mean"],
        labels["uvlogz_std"],
    ).to(device)
    # channels-last roughly doubles oneDNN's CPU training speed for these convolutions (measured)
    fmt = torch.channels_last if device.type == "cpu" else torch.contiguous_format
    net = net.to(memory_format=fmt)
    if cfg.train.pos_loss not in ("metres", "range_normalised"):
        raise ValueError(f"train.pos_loss: {cfg.train.pos_loss!r} is not metres or range_normalised")
    crit = UncertaintyPoseLoss(
        cfg.train.init_s_r, cfg.train.init_s_t, range_normalised=cfg.train.pos_loss == "range_normalised"
    ).to(device)
    opt = torch.optim.Adam(
        list(net.parameters()) + list(crit.parameters()),
        lr=cfg.train.lr_max,
        weight_decay=cfg.train.weight_decay,
    )

    kp_sup = KeypointSupervision(cfg, splits.K_input, net) if cfg.train.kp_loss else None
    train_loader, val_loader = _data_loaders(cfg, splits)

    steps_per_epoch = len(train_loader)
    if cfg.train.max_steps_per_epoch:
        steps_per_epoch = min(steps_per_epoch, cfg.train.max_steps_per_epoch)
    total_steps = steps_per_epoch * cfg.train.epochs

    last = run / "last.pt"
    start_epoch, step, best = _restore(cfg, last, net, crit, opt, device, log)
    log(
        f"{cfg.name}: {cfg.model.backbone} ({count_parameters(net) / 1e6:.2f} M parameters), "
        f"{len(splits.train)} train / {len(splits.val)} val frames, {steps_per_epoch} steps/epoch, "
        f"{cfg.train.epochs} epochs, device {device}, torch threads {torch.get_num_threads()}"
    )

    fields = (
        [
            "epoch",
            "step",
            "lr",
            "loss",
            "L_r_mean",
            "L_t_mean_m",
            "s_r",
            "s_t",
            "train_images_per_s",
            "epoch_s",
        ]
        + [f"val_{k}" for k, _, _ in metrics.TABLE_COLUMNS]
        + ["val_score"]
    )
    summary = {}
    for epoch in range(start_epoch, cfg.train.epochs):
        splits.train.epoch = epoch  # new augmentation draws every epoch, reproducibly
        net.train()
        t0 = time.perf_counter()
        sums, n_img, step, lr = _train_epoch(
            cfg,
            epoch,
            net,
            crit,
            opt,
            kp_sup,
            train_loader,
            steps_per_epoch,
            step,
            total_steps,
            device,
            fmt,
            progress,
        )
        train_s = time.perf_counter() - t0
        pred = predict(net, val_loader, device, progress, "val")
        val = metrics.summarize(pred["T_hat"], pred["q_hat"], pred["T"], pred["q"]) if len(pred["T"]) else {}
        val_score = metrics.score(val) if val else float("nan")
        row = {
            "epoch": epoch + 1,
            "step": step,
            "lr": lr,
            "loss": sums["loss"] / steps_per_epoch,
            "L_r_mean": sums["L_r"] / max(1, n_img),
            "L_t_mean_m": sums["L_t"] / max(1, n_img),
            "s_r": crit.s_r.item(),
            "s_t": crit.s_t.item(),
            "train_images_per_s": n_img / train_s,
            "epoch_s": time.perf_counter() - t0,
            **{f"val_{k}": v for k, v in val.items()},
            "val_score": val_score,
        }
        _append_logs(run, fields, row)
        ck = {
            "model": net.state_dict(),
            "loss": crit.state_dict(),
            "optimizer": opt.state_dict(),
            "epoch": epoch + 1,
            "step": step,
            "best_score": best,
            "config": cfg.to_dict(),
            "labels": labels,
            "camera": splits.camera,
            "torch_rng": torch.get_rng_state(),
            "val": val,
        }
        if val and val_score < best:
            best = val_score
            ck["best_score"] = best
            _save_atomic(ck, run / "best.pt")
        _save_atomic(ck, last)
        log(
            f"epoch {epoch + 1}: loss {row['loss']:.3f}, {row['train_images_per_s']:.1f} img/s, "
            + (
                f"val dt {val['dt_mean_pct']:.2f} % dq {val['dq_mean_deg']:.2f} deg "
                f"compliance {val['compliance_pos_pct']:.1f}/{val['compliance_att_pct']:.1f} %"
                if val
                else "no val"
            )
        )
        summary = row
    if not (run / "best.pt").exists() and last.exists():
        _save_atomic(torch.load(last, weights_only=False), run / "best.pt")
    (run / "done.json").write_text(json.dumps({"epochs": cfg.train.epochs, "last": summary}, indent=1) + "\n")
    return summary
