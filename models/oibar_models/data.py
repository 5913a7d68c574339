"""Reading the synthetic dataset written by oibar_hil.dataset, the paper's split, and the online
augmentation (SPEC section 7).

Sequence folder (docs/synthetic.md): manifest.json (written last: its presence marks the
sequence complete), poses.csv (one row per frame: file, time_s, phase, tx_m..tz_m, qw..qz,
range_m), frames/NNNNNN.jpg|png at 744x480.

Frames are decoded once, resized to the network input and kept as a uint8 array on disk
(data/cache), memory-mapped by the loader: on 2 CPU cores, JPEG decoding every epoch would cost
more than the network itself.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageFilter

from oibar.geometry.camera import intrinsics, rotation_homography, scale_intrinsics
from oibar.geometry.camera import project_camera_points as project_np
from oibar.geometry.rotations import matrix_to_quat as quat_from_matrix_np
from oibar.geometry.rotations import quat_to_matrix as quat_to_matrix_np
from oibar.geometry.rotations import rot_x, rot_y, rot_z
from oibar_hil.sequence import DatasetError, read_manifest, read_pose_table, verify_files  # noqa: F401  (DatasetError re-exported)

from .geometry import rot6d_from_matrix_np
from .infer import resize_frame

POSE_COLUMNS = ("frame", "file", "time_s", "phase", "tx_m", "ty_m", "tz_m", "qw", "qx", "qy", "qz", "range_m")


@dataclass
class Sequence:
    name: str
    dir: Path
    files: list[str]
    time_s: np.ndarray  # (N,)
    phase: np.ndarray  # (N,) int
    T_cam_target: np.ndarray  # (N, 3) m
    q_cam_target: np.ndarray  # (N, 4) (w, x, y, z)
    range_m: np.ndarray  # (N,)
    K: np.ndarray  # 3x3 intrinsics at the frames' resolution (pixel-corner convention)
    width_px: int
    height_px: int

    def __len__(self) -> int:
        return len(self.files)


def seq_name(n: int) -> str:
    return f"seq{n:02d}"


def load_sequence(seq_dir: str | Path, verify_hashes: bool = False) -> Sequence:
    """Read one sequence's manifest and pose table (oibar_hil.sequence, the one reader of the
    layout); raises DatasetError with the file at fault."""
    seq_dir = Path(seq_dir)
    manifest = read_manifest(seq_dir, required=lambda m: (m["config"]["camera"], int(m["frames"])))
    cam = manifest["config"]["camera"]
    n_expected = int(manifest["frames"])
    ppath = seq_dir / "poses.csv"
    if not ppath.is_file():
        raise DatasetError(f"{ppath}: missing pose table")
    if verify_hashes:
        verify_files(seq_dir, manifest, check_trailers=False)
    rows, num = read_pose_table(
        ppath,
        ("time_s", "phase", "tx_m", "ty_m", "tz_m", "qw", "qx", "qy", "qz", "range_m"),
        required=POSE_COLUMNS,
    )
    if len(rows) != n_expected:
        raise DatasetError(
            f"{ppath}: {len(rows)} rows but the manifest says {n_expected} frames (truncated?)"
        )
    if not np.all(np.isfinite(num)):
        raise DatasetError(f"{ppath}: non-finite values")
    q = num[:, 5:9]
    if np.max(np.abs(np.linalg.norm(q, axis=1) - 1.0)) > 1e-4:
        raise DatasetError(f"{ppath}: quaternions are not unit length")
    return Sequence(
        name=seq_dir.name,
        dir=seq_dir,
        files=[r["file"] for r in rows],
        time_s=num[:, 0],
        phase=num[:, 1].astype(int),
        T_cam_target=num[:, 2:5],
        q_cam_target=q,
        range_m=num[:, 9],
        K=intrinsics(cam["fx_px"], cam["fy_px"], cam["cx_px"], cam["cy_px"]),
        width_px=int(cam["width_px"]),
        height_px=int(cam["height_px"]),
    )


def load_frame(seq: Sequence, k: int, size_wh: tuple[int, int]) -> np.ndarray:
    path = seq.dir / seq.files[k]
    try:
        with Image.open(path) as im:
            im.load()
            return resize_frame(im, size_wh)
    except FileNotFoundError as exc:
        raise DatasetError(f"{path}: frame file missing") from exc
    except (OSError, SyntaxError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot decode frame ({exc})") from exc


def frame_cache(
    seq: Sequence, size_wh: tuple[int, int], cache_dir: Path | None, progress: bool = False
) -> np.ndarray:
    """All frames of a sequence resized to size_wh, uint8 (N, H, W, 3); cached on disk, keyed by
    the manifest's hash so a re-rendered sequence is never served stale frames."""
    w, h = size_wh
    key = hashlib.sha256((seq.dir / "manifest.json").read_bytes()).hexdigest()[:12]
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"{seq.name}_{w}x{h}_{key}.npy"
        if path.is_file():
            arr = np.load(path, mmap_mode="r")
            if arr.shape == (len(seq), h, w, 3):
                return arr
    arr = np.empty((len(seq), h, w, 3), np.uint8)
    it = range(len(seq))
    if progress:
        from oibar.progress import progress_iter

        it = progress_iter(it, f"caching {seq.name} {w}x{h}", unit="frame", leave=False)
    for k in it:
        arr[k] = load_frame(seq, k, size_wh)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npy")
        np.save(tmp, arr)
        tmp.replace(path)
        return np.load(path, mmap_mode="r")
    return arr


# ----------------------------------------------------------------------------- the paper's split
def split_subsequences(n_frames: int, chunk_lengths, val_fraction: float, rng: np.random.Generator):
    """Cut [0, n_frames) into consecutive sub-sequences with lengths drawn from chunk_lengths and
    give about val_fraction of the frames to validation, whole sub-sequences only (neighbouring
    frames are near-duplicates: a per-frame split would leak). Returns (train_idx, val_idx)."""
    chunks, start = [], 0
    while start < n_frames:
        length = int(rng.choice(chunk_lengths))
        chunks.append((start, min(n_frames, start + length)))
        start += length
    # Whole sub-sequences go to validation; chunks are long against a ~3600-frame sequence, so
    # try several random orders and keep the choice closest to the wanted fraction.
    target = val_fraction * n_frames
    best: set = set()
    best_err = float("inf")
    for _ in range(64):
        pick, total = set(), 0
        for i in rng.permutation(len(chunks)):
            length = chunks[i][1] - chunks[i][0]
            if abs(total + length - target) < abs(total - target) and len(pick) < len(chunks) - 1:
                pick.add(int(i))
                total += length
        if abs(total - target) < best_err:
            best, best_err = pick, abs(total - target)
    val = best
    train_idx = [np.arange(a, b) for i, (a, b) in enumerate(chunks) if i not in val]
    val_idx = [np.arange(a, b) for i, (a, b) in enumerate(chunks) if i in val]
    cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0, int)  # noqa: E731
    return cat(train_idx), cat(val_idx), chunks, sorted(val)


# ----------------------------------------------------------------------------- augmentation
class Augmenter:
    """Online augmentation. Pose augmentations are pure camera rotations (in-plane about the
    optical axis; off-plane pitch/yaw, which shift the image and warp it by the induced
    homography); these are exact for any scene depth, so labels update as T' = R T and
    R_cam_target' = R R_cam_target. Photometric ones leave labels unchanged."""

    def __init__(self, acfg, K_input: np.ndarray, size_wh: tuple[int, int]):
        self.cfg = acfg
        self.K = K_input
        self.w, self.h = size_wh

    def pose(
        self,
        img: np.ndarray,
        T: np.ndarray,
        R: np.ndarray,
        rng: np.random.Generator,
        R_aug: np.ndarray | None = None,
    ):
        c = self.cfg
        if R_aug is None:
            for _ in range(5):  # keep the fixture origin inside the frame, away from the edge
                R_try = (
                    rot_z(np.radians(rng.uniform(-c.inplane_deg, c.inplane_deg)))
                    @ rot_x(np.radians(rng.uniform(-c.offplane_deg, c.offplane_deg)))
                    @ rot_y(np.radians(rng.uniform(-c.offplane_deg, c.offplane_deg)))
                )
                uv = project_np(self.K, (R_try @ T)[None])[0]
                if 0.1 * self.w < uv[0] < 0.9 * self.w and 0.1 * self.h < uv[1] < 0.9 * self.h:
                    R_aug = R_try
                    break
            if R_aug is None:
                return img, T, R
        img2 = warp_homography(img, rotation_homography(self.K, R_aug))
        return img2, R_aug @ T, R_aug @ R

    def photometric(self, img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        c = self.cfg
        if c.p_blur > 0 and rng.random() < c.p_blur:
            sigma = rng.uniform(0.2, c.blur_sigma_max_px)
            img = np.asarray(Image.fromarray(img).filter(ImageFilter.GaussianBlur(sigma)))
        x = img.astype(np.float32) / 255.0
        x = x * (1 + rng.uniform(-c.brightness, c.brightness))
        m = x.mean()
        x = (x - m) * (1 + rng.uniform(-c.contrast, c.contrast)) + m
        x = x * (1 + rng.uniform(-c.colour, c.colour, size=3)).astype(np.float32)
        x = x + rng.normal(0, rng.uniform(0, c.noise_sigma_max), x.shape).astype(np.float32)
        return np.clip(x, 0, 1)

    def __call__(self, img, T, R, rng):
        if rng.random() < self.cfg.p_pose:
            img, T, R = self.pose(img, T, R, rng)
        if rng.random() < self.cfg.p_photometric:
            return self.photometric(img, rng), T, R
        return img.astype(np.float32) / 255.0, T, R


def warp_homography(img: np.ndarray, H_old_to_new: np.ndarray, border: str = "reflect") -> np.ndarray:
    """Resample img so that old pixel x lands on H x (pixel-corner convention, as PIL's
    transform uses).

    Uncovered pixels are filled by reflecting the image across its edges (``border="black"``:
    zeros). Black bands were a shortcut: they told the network how far the image had been
    shifted, it learned the band instead of the fixture and then ignored real lateral offsets in
    the closed loop (docs/model_history.md, "lateral response")."""
    if border == "black":
        Hinv = np.linalg.inv(H_old_to_new)
        Hinv = Hinv / Hinv[2, 2]
        im = Image.fromarray(img)
        out = im.transform(
            im.size, Image.Transform.PERSPECTIVE, tuple(Hinv.flatten()[:8]), Image.Resampling.BILINEAR
        )
        return np.asarray(out)
    h, w = img.shape[:2]
    py, px = h // 2, w // 2
    padded = np.pad(img, ((py, py), (px, px), (0, 0)), mode="reflect")
    # the same mapping on the padded canvas: shift in, apply H, shift out
    S = np.array([[1.0, 0.0, px], [0.0, 1.0, py], [0.0, 0.0, 1.0]])
    H_pad = S @ H_old_to_new @ np.linalg.inv(S)
    Hinv = np.linalg.inv(H_pad)
    Hinv = Hinv / Hinv[2, 2]
    im = Image.fromarray(padded)
    out = im.transform(
        im.size, Image.Transform.PERSPECTIVE, tuple(Hinv.flatten()[:8]), Image.Resampling.BILINEAR
    )
    return np.asarray(out)[py : py + h, px : px + w]


# ----------------------------------------------------------------------------- torch datasets
class PoseDataset(torch.utils.data.Dataset):
    """Frames of several sequences (index lists per sequence) at the network input size.
    Item: image (3, H, W) float in [0, 1], T_cam_target (3,), rot6d (6,), q_cam_target (4,),
    range_m, seq (int), frame (int)."""

    def __init__(
        self,
        seqs: list[Sequence],
        indices: list[np.ndarray],
        size_wh,
        cache_dir=None,
        augment=None,
        seed: int = 0,
        progress: bool = False,
    ):
        self.seqs = seqs
        self.size_wh = tuple(size_wh)
        self.frames = [frame_cache(s, self.size_wh, cache_dir, progress) for s in seqs]
        self.items = (
            np.concatenate([np.stack([np.full(len(ix), i), ix], 1) for i, ix in enumerate(indices)])
            if indices
            else np.zeros((0, 2), int)
        )
        self.augment = augment
        self.seed = seed
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        s, k = (int(x) for x in self.items[i])
        seq = self.seqs[s]
        img = np.asarray(self.frames[s][k])
        T = seq.T_cam_target[k].copy()
        R = quat_to_matrix_np(seq.q_cam_target[k])
        if self.augment is not None:
            rng = np.random.default_rng([self.seed, self.epoch, i])  # reproducible per epoch
            x, T, R = self.augment(img, T, R, rng)
        else:
            x = img.astype(np.float32) / 255.0
        return {
            "image": torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1))),
            "T_cam_target": torch.tensor(T, dtype=torch.float32),
            "rot6d": torch.tensor(rot6d_from_matrix_np(R), dtype=torch.float32),
            "q_cam_target": torch.tensor(quat_from_matrix_np(R), dtype=torch.float32),
            "range_m": torch.tensor(float(np.linalg.norm(T)), dtype=torch.float32),
            "seq": s,
            "frame": k,
        }


def input_intrinsics(seq: Sequence, size_wh) -> np.ndarray:
    return scale_intrinsics(seq.K, size_wh[0] / seq.width_px, size_wh[1] / seq.height_px)


@dataclass
class Splits:
    train: PoseDataset
    val: PoseDataset
    split_info: dict
    K_input: np.ndarray
    camera: dict


def open_sequences(root: Path, names: list[str], verify_hashes: bool = False) -> list[Sequence]:
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder not found (run `make dataset` first)")
    return [load_sequence(root / n, verify_hashes) for n in names]


def build_splits(cfg, progress: bool = False) -> Splits:
    d = cfg.data
    size = (cfg.model.input_width_px, cfg.model.input_height_px)
    seqs = open_sequences(cfg.path(d.root), [seq_name(n) for n in d.train_seqs], d.verify_hashes)
    rng = np.random.default_rng(d.split_seed)
    tr, va, info = [], [], {}
    for s in seqs:
        t_idx, v_idx, chunks, val_chunks = split_subsequences(len(s), d.chunk_lengths, d.val_fraction, rng)
        tr.append(t_idx[:: d.frame_stride])
        va.append(v_idx[:: d.frame_stride])
        info[s.name] = {
            "frames": len(s),
            "chunks": chunks,
            "val_chunks": val_chunks,
            "train_frames": int(len(tr[-1])),
            "val_frames": int(len(va[-1])),
        }
    K_in = input_intrinsics(seqs[0], size)
    cache = cfg.path(d.cache_dir) if d.cache_dir else None
    aug = Augmenter(cfg.augment, K_in, size) if cfg.augment.enabled else None
    train = PoseDataset(seqs, tr, size, cache, aug, cfg.train.seed, progress)
    val = PoseDataset(seqs, va, size, cache, None, cfg.train.seed, progress)
    cam = {
        "fx_px": float(seqs[0].K[0, 0]),
        "fy_px": float(seqs[0].K[1, 1]),
        "cx_px": float(seqs[0].K[0, 2]),
        "cy_px": float(seqs[0].K[1, 2]),
        "width_px": seqs[0].width_px,
        "height_px": seqs[0].height_px,
        "pixel_convention": "continuous, origin at the top-left corner of the image",
    }
    return Splits(train, val, info, K_in, cam)


def label_statistics(ds: PoseDataset) -> dict:
    """Mean and spread of the training labels (network output scaling) and the mean pose (the
    trivial baseline)."""
    T = np.concatenate([s.T_cam_target[ix] for s, ix in _per_seq(ds)])
    q = np.concatenate([s.q_cam_target[ix] for s, ix in _per_seq(ds)])
    from .metrics import mean_pose

    T_mean, q_mean = mean_pose(T, q)
    R_mean = quat_to_matrix_np(q_mean)
    z = np.maximum(T[:, 2], 1e-3)
    uvz = np.stack([T[:, 0] / z, T[:, 1] / z, np.log(z)], 1)
    return {
        "pos_mean_m": T.mean(0).tolist(),
        "pos_std_m": np.maximum(T.std(0), 0.05).tolist(),
        "uvlogz_mean": uvz.mean(0).tolist(),
        "uvlogz_std": np.maximum(uvz.std(0), 0.02).tolist(),
        "mean_T_cam_target": T_mean.tolist(),
        "mean_q_cam_target": q_mean.tolist(),
        "rot6d_mean": rot6d_from_matrix_np(R_mean).tolist(),
        "frames": int(len(T)),
        "range_m": [float(np.linalg.norm(T, axis=1).min()), float(np.linalg.norm(T, axis=1).max())],
    }


def _per_seq(ds: PoseDataset):
    for i, s in enumerate(ds.seqs):
        yield s, ds.items[ds.items[:, 0] == i, 1]
