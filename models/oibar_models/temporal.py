"""The paper's temporal-modelling study (issue 7, item 6): a BiLSTM back-end (1 to 3 layers) on the
per-frame features of the frozen, trained CNN, reported beside the CNN alone.

Protocol
  * The CNN (a checkpoint from `make train`) is frozen in eval mode; its global-average-pooled
    features (`OibarNet.features`) are extracted once per sequence, in frame order, without
    augmentation, and cached under <out>/features_<seq>_n<frames>_ck<checkpoint hash>_m<manifest
    hash>.npy, so a rerun with the same checkpoint and frames reuses them.
  * Clips are runs of consecutive frames inside one sub-sequence of the paper's split (the same
    split as the CNN's training, data.build_splits); a clip never crosses a sub-sequence
    boundary, so no clip mixes training and validation frames. Sub-sequences shorter than a clip
    give no training clip.
  * The head (TemporalHead): features standardised with the training split's mean and spread,
    BiLSTM, then the two linear heads of OibarNet; the position head outputs the same
    standardised parameterisation as the CNN's (decoded by the CNN's decode_position), so the
    graph still ends in metres. Loss: the CNN's (UncertaintyPoseLoss, range-normalised or not as
    the checkpoint was trained); Adam; the epoch with the best validation score is kept.
  * Validation and test sequences are predicted by sliding windows of the clip length: each frame
    is predicted once, by the window whose centre is nearest to it (a BiLSTM sees the most context
    there). The CNN alone is evaluated on the same frames from the same cached features (its heads
    applied per frame); a direct check runs the CNN on images and compares.
  * A control: the CNN's per-frame predictions smoothed by a centred moving average over the same
    number of frames as a clip ("CNN + moving avg"). A BiLSTM that only beats the CNN alone may
    merely be smoothing; one that also beats this control has learned more than a low-pass filter.

Writes into --out (default runs/temporal_bilstm): temporal.md (table), temporal.json (settings,
metrics, per-epoch history, sanity check, timings), predictions.npz, bilstm_L<n>.pt and
seq01_temporal_errors.png (error over time, CNN vs the BiLSTM with the best validation score).

CLI: python -m oibar_models.temporal --config models/configs/oibarnet_lite.yaml
         [--checkpoint runs/oibarnet_lite/best.pt] [--layers 1 2 3] [--out runs/temporal_bilstm]
         [--max-frames N]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

from oibar.geometry.rotations import quat_to_matrix as quat_to_matrix_np

from . import metrics
from .data import DatasetError, Sequence, build_splits, frame_cache, open_sequences, seq_name
from .engine import load_checkpoint
from .evaluate import plot_error_series
from .geometry import matrix_from_rot6d, quat_from_matrix, rot6d_from_matrix_np
from .loss import UncertaintyPoseLoss

# The fields of the data config that define the split: the study must cut the sequences exactly
# as the CNN's training did, or "validation" frames could be frames the CNN was trained on.
SPLIT_FIELDS = (
    "root",
    "train_seqs",
    "test_seqs",
    "val_fraction",
    "chunk_lengths",
    "split_seed",
    "frame_stride",
)


SMOOTHED = "CNN + moving avg"  # the smoothing control's row label


class StudyError(RuntimeError):
    """The study cannot run as asked (checkpoint / config mismatch, too few frames...)."""


# ----------------------------------------------------------------------------- features
def file_hash(path: Path, n_hex: int = 12) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:n_hex]


def images_from_uint8(frames: np.ndarray) -> torch.Tensor:
    """(N, H, W, 3) uint8 -> (N, 3, H, W) float in [0, 1], exactly as PoseDataset builds its
    (unaugmented) items, so cached features equal what the CNN sees in training/evaluation."""
    x = np.asarray(frames).astype(np.float32) / 255.0
    return torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2)))


@torch.no_grad()
def extract_features(
    net, frames: np.ndarray, batch: int = 64, progress: bool = False, desc: str = "features"
) -> np.ndarray:
    """GAP features of every frame, in order: (N, feature_dim) float32."""
    net.eval()
    out = np.empty((len(frames), net.feature_dim), np.float32)
    it = range(0, len(frames), batch)
    if progress:
        from oibar.progress import progress_iter

        it = progress_iter(it, desc, unit="batch", leave=False)
    for i in it:
        out[i : i + batch] = net.features(images_from_uint8(frames[i : i + batch])).numpy()
    return out


def sequence_features(
    net,
    seq: Sequence,
    size_wh,
    n_frames: int,
    ck_hash: str,
    out: Path,
    frame_cache_dir: Path | None,
    batch: int = 64,
    progress: bool = False,
) -> tuple[np.ndarray, bool]:
    """Features of frames [0, n_frames) of seq, cached in out; -> (features, reused_from_disk)."""
    m_hash = hashlib.sha256((seq.dir / "manifest.json").read_bytes()).hexdigest()[:8]
    path = out / f"features_{seq.name}_n{n_frames}_ck{ck_hash}_m{m_hash}.npy"
    if path.is_file():
        arr = np.load(path)
        if arr.shape == (n_frames, net.feature_dim):
            return arr, True
    frames = frame_cache(seq, size_wh, frame_cache_dir, progress)
    arr = extract_features(net, frames[:n_frames], batch, progress, f"features {seq.name}")
    out.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npy")
    np.save(tmp, arr)
    tmp.replace(path)  # atomic: an interrupted extraction never leaves a truncated cache
    return arr, False


# ----------------------------------------------------------------------------- segments, clips
@dataclass
class Segment:
    """A run of consecutive frames of one sequence that belongs to one split."""

    seq: int  # index into the study's sequence list
    frames: np.ndarray  # frame indices, increasing
    split: str  # train | val | test
    chunk: int  # sub-sequence number in split.json (-1: a whole test sequence)


def split_segments(
    split_info: dict, seq_names: list[str], items: dict[str, np.ndarray], n_frames: list[int]
) -> list[Segment]:
    """One Segment per sub-sequence (chunk) of the split, holding the frames the split's dataset
    actually uses (items[split]: (seq, frame) rows) below n_frames[seq]."""
    segs = []
    for s, name in enumerate(seq_names):
        info = split_info[name]
        val_chunks = set(info["val_chunks"])
        for c, (a, b) in enumerate(info["chunks"]):
            split = "val" if c in val_chunks else "train"
            it = items[split]
            k = np.sort(it[(it[:, 0] == s) & (it[:, 1] >= a) & (it[:, 1] < min(b, n_frames[s])), 1])
            if len(k):
                segs.append(Segment(s, k, split, c))
    return segs


def make_clips(segments: list[Segment], length: int, stride: int) -> np.ndarray:
    """Training clips: (N, 2 + length) int rows [segment index, sequence index, frame indices...].
    Windows of `length` consecutive segment frames every `stride`, plus one ending at the
    segment's end so its tail is used too; segments shorter than `length` give none."""
    if length < 2 or stride < 1:
        raise ValueError(f"clip length must be >= 2 and stride >= 1 (got {length}, {stride})")
    rows = []
    for i, seg in enumerate(segments):
        for a in window_starts(len(seg.frames), length, stride) if len(seg.frames) >= length else []:
            rows.append([i, seg.seq, *seg.frames[a : a + length]])
    return np.array(rows, dtype=np.int64).reshape(-1, 2 + length)


def window_starts(n: int, length: int, stride: int) -> np.ndarray:
    """Starts of windows of min(length, n) frames every `stride`, the last one flush with n."""
    length = min(length, n)
    starts = list(range(0, n - length + 1, stride))
    if starts[-1] != n - length:
        starts.append(n - length)
    return np.array(starts, dtype=np.int64)


def nearest_window(n: int, starts: np.ndarray, length: int) -> np.ndarray:
    """For each of n frames, the window whose centre is nearest (ties: the earlier window)."""
    centres = starts + (min(length, n) - 1) / 2.0
    return np.abs(np.arange(n)[:, None] - centres[None, :]).argmin(1)


# ----------------------------------------------------------------------------- the head
class TemporalHead(nn.Module):
    """Standardised CNN features (N, T, D) -> BiLSTM -> (position head output in the CNN's
    standardised parameterisation (N, T, 3), rot6d (N, T, 6)). Decode the position with the
    CNN's decode_position (predict_clips does)."""

    def __init__(
        self,
        feature_dim: int,
        layers: int,
        hidden: int,
        feat_mean,
        feat_std,
        rot6d_mean,
        dropout: float = 0.2,
    ):
        super().__init__()
        if not 1 <= layers <= 3:
            raise ValueError("the paper's study uses 1 to 3 BiLSTM layers")
        self.layers, self.hidden = layers, hidden
        self.register_buffer("feat_mean", torch.as_tensor(np.asarray(feat_mean), dtype=torch.float32))
        self.register_buffer("feat_std", torch.as_tensor(np.asarray(feat_std), dtype=torch.float32))
        # inter-layer dropout only exists for 2+ layers (torch warns otherwise)
        self.lstm = nn.LSTM(
            feature_dim,
            hidden,
            num_layers=layers,
            batch_first=True,
            bidirectional=True,
            dropout=dropout if layers > 1 else 0.0,
        )
        self.head_t = nn.Linear(2 * hidden, 3)
        self.head_r = nn.Linear(2 * hidden, 6)
        # start from the mean pose, as OibarNet's heads do
        nn.init.zeros_(self.head_t.weight)
        nn.init.zeros_(self.head_t.bias)
        nn.init.normal_(self.head_r.weight, std=1e-3)
        with torch.no_grad():
            self.head_r.bias.copy_(torch.as_tensor(np.asarray(rot6d_mean), dtype=torch.float32))

    def forward(self, feats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h, _ = self.lstm((feats - self.feat_mean) / self.feat_std)
        return self.head_t(h), self.head_r(h)


def predict_clips(head: TemporalHead, cnn, feats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    raw_t, r6 = head(feats)
    return cnn.decode_position(raw_t), r6


@torch.no_grad()
def predict_sequence_bilstm(
    head: TemporalHead, cnn, feats: np.ndarray, length: int, stride: int, batch: int = 256
) -> tuple[np.ndarray, np.ndarray]:
    """Sliding windows over one run of consecutive frames; each frame predicted once, by the
    window whose centre is nearest. -> T_cam_target (n, 3) m, rot6d (n, 6)."""
    head.eval()
    n = len(feats)
    L = min(length, n)
    starts = window_starts(n, L, stride)
    f = torch.from_numpy(np.ascontiguousarray(feats))
    T_w, r_w = [], []
    for i in range(0, len(starts), batch):
        clip = torch.stack([f[a : a + L] for a in starts[i : i + batch]])
        t, r = predict_clips(head, cnn, clip)
        T_w.append(t)
        r_w.append(r)
    T_w, r_w = torch.cat(T_w).numpy(), torch.cat(r_w).numpy()
    w = nearest_window(n, starts, L)
    pos = np.arange(n) - starts[w]
    return T_w[w, pos], r_w[w, pos]


@torch.no_grad()
def predict_cnn_from_features(cnn, feats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t, r = cnn.heads(torch.from_numpy(np.ascontiguousarray(feats)))
    return t.numpy(), r.numpy()


def moving_average(x: np.ndarray, length: int) -> np.ndarray:
    """Centred moving average along axis 0 over `length` frames, the window truncated at the
    ends (no padding: padding would invent frames). rot6d averages are re-orthonormalised by
    the Gram-Schmidt step of matrix_from_rot6d downstream."""
    n = len(x)
    L = min(length, n)
    c = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, 0, dtype=np.float64)])
    k = np.arange(n)
    lo = np.clip(k - (L - 1) // 2, 0, n)
    hi = np.clip(k + L // 2 + 1, 0, n)
    return ((c[hi] - c[lo]) / (hi - lo).reshape((-1,) + (1,) * (x.ndim - 1))).astype(np.float32)


def quats_from_rot6d(r6: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return quat_from_matrix(matrix_from_rot6d(torch.as_tensor(r6, dtype=torch.float32))).numpy()


# ----------------------------------------------------------------------------- the study
@dataclass
class StudySettings:
    layers: tuple[int, ...] = (1, 2, 3)
    hidden: int = 128
    clip_len: int = 32
    clip_stride: int = 8
    eval_stride: int = 8  # sliding-window stride on validation / test
    epochs: int = 15
    batch_size: int = 32  # clips
    lr: float = 1e-3
    dropout: float = 0.2  # between LSTM layers (2+ layers)
    seed: int = 0
    max_frames: int = 0  # >0: only the first N frames of every sequence (smoke runs)
    feature_batch: int = 64
    threads: int = 2


def _labels(seq: Sequence, n: int) -> dict:
    return {
        "T": seq.T_cam_target[:n].astype(np.float32),
        "q": seq.q_cam_target[:n],
        "r6": rot6d_from_matrix_np(quat_to_matrix_np(seq.q_cam_target[:n])).astype(np.float32),
    }


def _check_checkpoint_matches(cfg, ck: dict) -> None:
    ck_data, ck_model = ck["config"]["data"], ck["config"]["model"]
    bad = [
        f"data.{k}: config {getattr(cfg.data, k)!r} vs checkpoint {ck_data.get(k)!r}"
        for k in SPLIT_FIELDS
        if ck_data.get(k) != getattr(cfg.data, k)
    ]
    bad += [
        f"model.{k}: config {getattr(cfg.model, k)!r} vs checkpoint {ck_model.get(k)!r}"
        for k in ("input_width_px", "input_height_px")
        if ck_model.get(k) != getattr(cfg.model, k)
    ]
    if bad:
        raise StudyError(
            "the checkpoint was trained with another split or input size than the config "
            "(the study must reuse the CNN's split):\n  " + "\n  ".join(bad)
        )


def _summarize(T_hat, r6_hat, lab_T, lab_q) -> dict:
    return metrics.summarize(T_hat, quats_from_rot6d(r6_hat), lab_T, lab_q)


def _evaluate_segments(predict, segments, labels) -> dict:
    """Concatenate per-segment predictions over all segments; -> summary."""
    T_hat, r6_hat, T, q = [], [], [], []
    for seg in segments:
        t, r = predict(seg)
        T_hat.append(t)
        r6_hat.append(r)
        T.append(labels[seg.seq]["T"][seg.frames])
        q.append(labels[seg.seq]["q"][seg.frames])
    return _summarize(np.concatenate(T_hat), np.concatenate(r6_hat), np.concatenate(T), np.concatenate(q))


def train_head(
    cnn,
    feats: list[np.ndarray],
    labels: list[dict],
    clips: np.ndarray,
    val_segments: list[Segment],
    layers: int,
    st: StudySettings,
    range_normalised: bool,
    rot6d_mean,
    feat_mean,
    feat_std,
    progress: bool = False,
    log=print,
) -> tuple[TemporalHead, list[dict]]:
    """Adam on the clips; after each epoch, validation by sliding windows; keeps the best epoch."""
    torch.manual_seed(st.seed + layers)
    rng = np.random.default_rng(st.seed + layers)
    head = TemporalHead(cnn.feature_dim, layers, st.hidden, feat_mean, feat_std, rot6d_mean, st.dropout)
    crit = UncertaintyPoseLoss(range_normalised=range_normalised)
    opt = torch.optim.Adam(list(head.parameters()) + list(crit.parameters()), lr=st.lr)
    F = [torch.from_numpy(f) for f in feats]
    T_lab = [torch.from_numpy(lab["T"]) for lab in labels]
    r_lab = [torch.from_numpy(lab["r6"]) for lab in labels]

    def gather(rows):
        idx = torch.from_numpy(rows[:, 2:])
        s = rows[:, 1]
        # clips of one batch may come from different sequences: gather per row
        f = torch.stack([F[si][ix] for si, ix in zip(s, idx, strict=True)])
        t = torch.stack([T_lab[si][ix] for si, ix in zip(s, idx, strict=True)])
        r = torch.stack([r_lab[si][ix] for si, ix in zip(s, idx, strict=True)])
        return f, t, r

    def val_predict(seg):
        return predict_sequence_bilstm(head, cnn, feats[seg.seq][seg.frames], st.clip_len, st.eval_stride)

    history, best, best_state = [], float("inf"), None
    for epoch in range(st.epochs):
        head.train()
        t0 = time.perf_counter()
        order = rng.permutation(len(clips))
        batches = range(0, len(order), st.batch_size)
        bar = None
        if progress:
            from oibar.progress import Progress

            bar = Progress(
                f"BiLSTM-{layers} epoch {epoch + 1}/{st.epochs}",
                total=len(batches),
                unit="batch",
                leave=False,
            )
        loss_sum = 0.0
        for i in batches:
            f, t, r = gather(clips[order[i : i + st.batch_size]])
            T_hat, r6_hat = predict_clips(head, cnn, f)
            out = crit(T_hat, r6_hat, t, r)
            opt.zero_grad(set_to_none=True)
            out["loss"].backward()
            opt.step()
            loss_sum += out["loss"].item()
            if bar:
                bar.update(1)
        if bar:
            bar.close()
        val = _evaluate_segments(val_predict, val_segments, labels)
        score = metrics.score(val)
        row = {
            "epoch": epoch + 1,
            "loss": loss_sum / max(1, len(batches)),
            "val_score": score,
            "epoch_s": time.perf_counter() - t0,
            **{f"val_{k}": v for k, v in val.items()},
        }
        history.append(row)
        log(
            f"BiLSTM-{layers} epoch {epoch + 1}: loss {row['loss']:.2f}, val dt {val['dt_mean_pct']:.2f} % "
            f"dq {val['dq_mean_deg']:.2f} deg, score {score:.4f} ({row['epoch_s']:.1f} s)"
        )
        if score < best:
            best = score
            best_state = {k: v.detach().clone() for k, v in head.state_dict().items()}
    head.load_state_dict(best_state)
    head.eval()
    return head, history


def direct_check(cnn, frames: np.ndarray, feats: np.ndarray, idx: np.ndarray) -> dict:
    """The CNN run on the images themselves vs its heads on the cached features (same frames)."""
    with torch.no_grad():
        t_img, r_img = cnn(images_from_uint8(np.asarray(frames[idx])))
    t_f, r_f = predict_cnn_from_features(cnn, feats[idx])
    return {
        "frames": int(len(idx)),
        "max_abs_position_m": float(np.abs(t_img.numpy() - t_f).max()),
        "max_abs_rot6d": float(np.abs(r_img.numpy() - r_f).max()),
    }


def run_study(cfg, checkpoint: Path, out: Path, st: StudySettings, progress: bool = True, log=print) -> dict:
    t_start = time.perf_counter()
    if st.threads > 0:
        torch.set_num_threads(st.threads)
    checkpoint = Path(checkpoint)
    cnn, ck = load_checkpoint(checkpoint)
    _check_checkpoint_matches(cfg, ck)
    for p in cnn.parameters():
        p.requires_grad_(False)
    ck_hash = file_hash(checkpoint)
    out.mkdir(parents=True, exist_ok=True)
    size = (cfg.model.input_width_px, cfg.model.input_height_px)
    cache_dir = cfg.path(cfg.data.cache_dir) if cfg.data.cache_dir else None

    splits = build_splits(cfg, progress=progress)
    train_seqs = splits.train.seqs
    test_seqs = open_sequences(cfg.path(cfg.data.root), [seq_name(n) for n in cfg.data.test_seqs])
    seqs = train_seqs + test_seqs
    cap = lambda n: min(n, st.max_frames) if st.max_frames > 0 else n  # noqa: E731
    n_frames = [cap(len(s)) for s in seqs]

    # features, once per sequence (the expensive part)
    t0 = time.perf_counter()
    feats, reused = [], []
    for s, n in zip(seqs, n_frames, strict=True):
        f, r = sequence_features(cnn, s, size, n, ck_hash, out, cache_dir, st.feature_batch, progress)
        feats.append(f)
        reused.append(r)
    extract_s = time.perf_counter() - t0
    log(
        f"features: {sum(n_frames)} frames of {len(seqs)} sequences, dim {cnn.feature_dim}, "
        f"{'reused from ' + str(out) if all(reused) else f'{extract_s:.0f} s'}"
    )
    labels = [_labels(s, n) for s, n in zip(seqs, n_frames, strict=True)]

    items = {"train": splits.train.items, "val": splits.val.items}
    segs = split_segments(splits.split_info, [s.name for s in train_seqs], items, n_frames[: len(train_seqs)])
    train_segs = [g for g in segs if g.split == "train"]
    val_segs = [g for g in segs if g.split == "val"]
    test_segs = [
        Segment(len(train_seqs) + i, np.arange(n_frames[len(train_seqs) + i]), "test", -1)
        for i in range(len(test_seqs))
    ]
    clips = make_clips(train_segs, st.clip_len, st.clip_stride)
    if not len(clips) or not val_segs:
        raise StudyError(
            f"no training clips of {st.clip_len} frames or no validation frames "
            f"(max_frames={st.max_frames}): use more frames or a shorter clip"
        )
    train_frames = np.concatenate([feats[g.seq][g.frames] for g in train_segs])
    feat_mean, feat_std = train_frames.mean(0), np.maximum(train_frames.std(0), 1e-3)
    range_normalised = ck["config"]["train"].get("pos_loss") == "range_normalised"
    log(
        f"clips: {len(clips)} of {st.clip_len} frames (stride {st.clip_stride}) from {len(train_segs)} train "
        f"sub-sequences; {sum(len(g.frames) for g in val_segs)} val frames in {len(val_segs)} sub-sequences; "
        f"loss {'range-normalised' if range_normalised else 'metres'}"
    )

    # the CNN alone, from the same features; and the check that this path is the CNN itself
    def cnn_predict(seg):
        return predict_cnn_from_features(cnn, feats[seg.seq][seg.frames])

    check = _direct_check_tests(cnn, seqs, test_segs, n_frames, feats, size, cache_dir)
    seq01 = len(train_seqs)  # first test sequence (seq01 in the paper's split): the plot

    def smoothed_predict(seg):
        t, r = cnn_predict(seg)
        return moving_average(t, st.clip_len), moving_average(r, st.clip_len)

    results, preds = {}, {}

    def assess(key, fn):
        """Validation and every test sequence through one predictor."""
        results[key] = {"val": _evaluate_segments(fn, val_segs, labels)}
        for seg in test_segs:
            t, r = fn(seg)
            name = seqs[seg.seq].name
            results[key][name] = _summarize(t, r, labels[seg.seq]["T"], labels[seg.seq]["q"])
            preds[f"{name}/{key}"] = (t, r)

    for key, fn in (("CNN alone", cnn_predict), (SMOOTHED, smoothed_predict)):
        assess(key, fn)

    histories, train_s = {}, {}
    for L in st.layers:
        t0 = time.perf_counter()
        head, hist = train_head(
            cnn,
            feats,
            labels,
            clips,
            val_segs,
            L,
            st,
            range_normalised,
            ck["labels"]["rot6d_mean"],
            feat_mean,
            feat_std,
            progress,
            log,
        )
        train_s[L] = time.perf_counter() - t0
        histories[L] = hist
        key = f"BiLSTM-{L}"
        torch.save(
            {
                "state_dict": head.state_dict(),
                "layers": L,
                "hidden": st.hidden,
                "checkpoint": str(checkpoint),
                "checkpoint_sha256_12": ck_hash,
                "settings": st.__dict__,
            },
            out / f"bilstm_L{L}.pt",
        )

        def bl_predict(seg, head=head):
            return predict_sequence_bilstm(head, cnn, feats[seg.seq][seg.frames], st.clip_len, st.eval_stride)

        assess(key, bl_predict)

    bilstms = [f"BiLSTM-{L}" for L in st.layers]
    best_key = min(bilstms, key=lambda k: metrics.score(results[k]["val"]))

    _plot_errors(out, seqs[seq01], preds, labels[seq01], n_frames[seq01], best_key)
    np.savez_compressed(
        out / "predictions.npz",
        **{f"{k}/T_cam_target_m": v[0] for k, v in preds.items()},
        **{f"{k}/rot6d": v[1] for k, v in preds.items()},
    )

    rows = [
        (split, model, results[model][split])
        for split in [seqs[g.seq].name for g in test_segs] + ["val"]
        for model in results
    ]
    wall_s = time.perf_counter() - t_start
    result = {
        "checkpoint": str(checkpoint),
        "checkpoint_sha256_12": ck_hash,
        "checkpoint_epoch": ck.get("epoch"),
        "settings": st.__dict__ | {"layers": list(st.layers)},
        "eval_rule": "sliding windows of clip_len every eval_stride frames; each frame predicted once, "
        "by the window whose centre is nearest",
        "frames": {
            "train_clips": int(len(clips)),
            "train_frames_in_clips": _distinct_frames(clips),
            "val_frames": int(sum(len(g.frames) for g in val_segs)),
            **{seqs[g.seq].name: int(len(g.frames)) for g in test_segs},
        },
        "loss": "range_normalised" if range_normalised else "metres",
        "direct_check": check,
        "results": results,
        "best_bilstm_on_val": best_key,
        "history": {f"BiLSTM-{L}": h for L, h in histories.items()},
        "timing_s": {
            "features": extract_s,
            "features_reused": all(reused),
            **{f"train_BiLSTM-{L}": v for L, v in train_s.items()},
            "wall": wall_s,
        },
        "machine": f"{platform.processor() or platform.machine()}, {platform.system()}, "
        f"torch threads {torch.get_num_threads()}",
    }
    result["verdict"] = _verdict(results, best_key, [seqs[g.seq].name for g in test_segs])
    (out / "temporal.md").write_text(_report_markdown(result, rows, st, train_s))
    (out / "temporal.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    return result


def _direct_check_tests(
    cnn,
    seqs: list[Sequence],
    test_segs: list[Segment],
    n_frames: list[int],
    feats: list[np.ndarray],
    size,
    cache_dir,
) -> dict:
    """The CNN on images against its heads on the cached features, 64 frames spread over each
    test sequence: raises StudyError when they differ (stale or foreign features)."""
    checks = []
    for seg in test_segs:
        n = n_frames[seg.seq]
        idx = np.linspace(0, n - 1, min(64, n)).astype(int)
        checks.append(direct_check(cnn, frame_cache(seqs[seg.seq], size, cache_dir), feats[seg.seq], idx))
    check = {
        "frames": sum(c["frames"] for c in checks),
        "max_abs_position_m": max(c["max_abs_position_m"] for c in checks),
        "max_abs_rot6d": max(c["max_abs_rot6d"] for c in checks),
    }
    if check["max_abs_position_m"] > 1e-3 or check["max_abs_rot6d"] > 1e-4:
        raise StudyError(f"cached features do not reproduce the CNN's own predictions: {check}")
    return check


def _plot_errors(out: Path, seq: Sequence, preds: dict, label: dict, n_frames: int, best_key: str) -> None:
    """Errors over time on one test sequence: the CNN, the smoothing control and the BiLSTM
    chosen on validation (never on the test sequences)."""
    series = {}
    for key in ("CNN alone", SMOOTHED, best_key):
        t, r = preds[f"{seq.name}/{key}"]
        series[key] = (
            metrics.position_error_pct(t, label["T"]),
            metrics.attitude_error_deg(quats_from_rot6d(r), label["q"]),
        )
    plot_error_series(
        out / f"{seq.name}_temporal_errors.png",
        f"{seq.name}: CNN alone, moving-average control, {best_key} (chosen on val)",
        seq.time_s[:n_frames],
        series,
    )


def _report_markdown(result: dict, rows: list, st: StudySettings, train_s: dict) -> str:
    """temporal.md: the settings, the table, the choice on validation, the verdict, the times."""
    check, timing = result["direct_check"], result["timing_s"]
    reused = timing["features_reused"]
    md = [
        "# Temporal study: BiLSTM on frozen CNN features",
        "",
        f"checkpoint {result['checkpoint']} (epoch {result['checkpoint_epoch']}, sha256 "
        f"{result['checkpoint_sha256_12']}); clips of {st.clip_len} frames "
        f"every {st.clip_stride}; BiLSTM hidden {st.hidden}, {st.epochs} epochs, Adam lr {st.lr}, batch "
        f"{st.batch_size} clips; evaluation: {result['eval_rule']}; control: {SMOOTHED} = the CNN's per-frame "
        f"predictions averaged over a centred window of {st.clip_len} frames"
        + (f"; only the first {st.max_frames} frames per sequence" if st.max_frames else ""),
        "",
        metrics.markdown_table(rows),
        "",
        f"BiLSTM chosen on validation: {result['best_bilstm_on_val']}. Direct check (CNN on images vs heads on "
        f"cached features, {check['frames']} frames): max |d position| {check['max_abs_position_m']:.2e} m, "
        f"max |d rot6d| {check['max_abs_rot6d']:.2e}.",
        "",
        f"Verdict: {result['verdict']}",
        "",
        f"Wall time {timing['wall']:.0f} s (features {timing['features']:.0f} s{', reused' if reused else ''}; "
        "training "
        + ", ".join(f"BiLSTM-{L} {v:.0f} s" for L, v in train_s.items())
        + f"); {result['machine']}.",
        "",
    ]
    return "\n".join(md)


def _distinct_frames(clips: np.ndarray) -> int:
    L = clips.shape[1] - 2
    pairs = np.stack([np.repeat(clips[:, 1], L), clips[:, 2:].ravel()], 1)
    return int(len(np.unique(pairs, axis=0)))


def _verdict(results: dict, best_key: str, test_names: list[str]) -> str:
    """The BiLSTM chosen on validation against the CNN alone and the smoothing control, per test
    sequence: differences of the mean position (% of range) and attitude (deg) errors."""
    parts = []
    for name in test_names:
        b = results[best_key][name]
        d = {
            k: (
                b["dt_mean_pct"] - results[k][name]["dt_mean_pct"],
                b["dq_mean_deg"] - results[k][name]["dq_mean_deg"],
            )
            for k in ("CNN alone", SMOOTHED)
        }
        parts.append(
            f"{name}: {best_key} vs CNN alone {d['CNN alone'][0]:+.2f} % / {d['CNN alone'][1]:+.2f} deg, "
            f"vs {SMOOTHED} {d[SMOOTHED][0]:+.2f} % / {d[SMOOTHED][1]:+.2f} deg (negative: BiLSTM better)"
        )
    return "; ".join(parts)


def main(argv: list[str] | None = None) -> int:
    from .config import ConfigError, load_config

    ap = argparse.ArgumentParser(prog="python -m oibar_models.temporal", description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", required=True, help="the CNN's experiment config (models/configs/)")
    ap.add_argument("--checkpoint", help="CNN checkpoint (default runs/<name>/best.pt)")
    ap.add_argument("--out", default="runs/temporal_bilstm")
    d = StudySettings()
    ap.add_argument("--layers", type=int, nargs="+", default=list(d.layers))
    ap.add_argument("--hidden", type=int, default=d.hidden)
    ap.add_argument("--clip-len", type=int, default=d.clip_len)
    ap.add_argument("--clip-stride", type=int, default=d.clip_stride)
    ap.add_argument("--eval-stride", type=int, default=d.eval_stride)
    ap.add_argument("--epochs", type=int, default=d.epochs)
    ap.add_argument("--batch-size", type=int, default=d.batch_size)
    ap.add_argument("--lr", type=float, default=d.lr)
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument(
        "--max-frames", type=int, default=0, help="only the first N frames of every sequence (smoke)"
    )
    ap.add_argument("--threads", type=int, default=d.threads, help="torch threads (0: torch's default)")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    st = StudySettings(
        layers=tuple(a.layers),
        hidden=a.hidden,
        clip_len=a.clip_len,
        clip_stride=a.clip_stride,
        eval_stride=a.eval_stride,
        epochs=a.epochs,
        batch_size=a.batch_size,
        lr=a.lr,
        seed=a.seed,
        max_frames=a.max_frames,
        threads=a.threads,
    )
    try:
        cfg = load_config(a.config)
        ckpt = Path(a.checkpoint) if a.checkpoint else cfg.run_path / "best.pt"
        out = cfg.path(a.out)
        run_study(cfg, ckpt, out, st, progress=not a.no_progress)
    except (ConfigError, DatasetError, StudyError, FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print((out / "temporal.md").read_text())
    print(f"written to {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
