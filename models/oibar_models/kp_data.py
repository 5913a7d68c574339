"""Training samples for the keypoint network: a full-resolution crop around the fixture, with
the keypoints' crop coordinates and the attitude as the crop shows it as labels.

The window is the one flight cuts (oibar.nav.keypoints.window_around the projected keypoints of a
rough pose), perturbed the way a rough pose is wrong: centre shifted, side scaled, turned a little.
Any 2-D affine of the crop maps the labels exactly (they are image points), so the geometric
augmentation needs no approximation (the attitude label is taken in the window's own camera,
turn included: oibar.nav.keypoints.attitude_in_crop_deg). Photometric augmentation: brightness, contrast, gamma,
colour gain, Gaussian noise, blur, JPEG re-encoding.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from oibar.geometry.docking import R_cam_target_aligned, docking_from_camera_pose
from oibar.geometry.rotations import quat_to_matrix as quat_to_matrix_np
from oibar.nav.keypoints import (
    MIRROR_ATT,
    CropWindow,
    attitude_in_crop_deg,
    cut,
    mirror_crop_px,
    mirror_permutation,
    mirror_symmetric_attitude,
    project,
    window_around,
)

from .data import Sequence, load_sequence


@dataclass
class CropAugment:
    center_jitter: float = 0.12  # std of the window centre shift, fraction of the side
    scale_jitter: float = 0.25  # side scaled by exp(U(-a, a))
    angle_deg: float = 15.0  # in-plane turn, uniform +-
    margin: float = 1.25  # window side / keypoint bounding box (flight uses the same)
    p_photometric: float = 0.8
    p_noise: float = 0.4
    noise_sigma_max: float = 0.04
    p_blur: float = 0.3
    blur_sigma_max_px: float = 1.2
    p_jpeg: float = 0.3
    # Left-right mirror of the crop (labels mirrored with it: keypoints swapped with their twins,
    # the attitude's y and z turned over). The fixture is symmetric, so a mirrored crop is a
    # view of it too; without, 0.8.1 leans: a -0.24 deg tilt about y on validation at 2-5 m,
    # +0.12 deg on the same crops mirrored (stage 9).
    p_mirror: float = 0.0
    # Domain randomisation of the crop's pixels (oibar_models.domain: random-convolution texture,
    # Fourier-amplitude mixing, white balance, exposure, response, glare, occlusion, blur, defocus,
    # noise, compression; issue 58, part 3), on this
    # share of crops, after the photometric terms above. Off unless a config asks: every model
    # trained so far saw none, and its crops draw the same numbers as before.
    p_domain: float = 0.0
    # Share of training crops turned by any angle (uniform +-180 deg) instead of +-angle_deg: the
    # keypoints of a camera rolled about its boresight. Why: trained on +-15 deg only, a network
    # reads a view rolled past ~45 deg as unrolled, strong fit and all (docs/model_card.md, "Rolled
    # approaches"). A 2D keypoint turns with its crop exactly, so their labels stay exact; the
    # attitude head is scored only within +-angle_deg (`att_weight`), since a head kept as it is
    # (freeze = ["attitude"]) cannot read a half turn, and the loss would then push its turn into
    # the backbone. Never on validation crops. 0: no extra draw, so earlier runs draw as before.
    p_roll: float = 0.0


def open_scenes(root: Path, names: list[str] | None = None) -> list[Sequence]:
    root = Path(root)
    dirs = (
        [root / n for n in names]
        if names
        else sorted(p for p in root.iterdir() if (p / "poses.csv").is_file())
    )
    return [load_sequence(d) for d in dirs]


def off_axis_deg(points_m: np.ndarray, R: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Per target point, the angle (deg) between the fixture's outward axis (-Z_t) and the line
    from the point to the camera: 0 looking straight down the funnel."""
    to_cam_t = -(np.asarray(points_m, float) @ R.T + T) @ R  # camera - point, in F_t
    cos = -to_cam_t[:, 2] / np.linalg.norm(to_cam_t, axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def visible(
    uv: np.ndarray,
    frame_wh: tuple[int, int],
    win: CropWindow,
    off_axis: np.ndarray | None = None,
    limit_deg: np.ndarray | None = None,
) -> np.ndarray:
    """Keypoints that the crop can show: in front of the camera, inside the frame and the crop,
    and (with `off_axis`/`limit_deg`) not hidden inside the funnel."""
    w, h = frame_wh
    c = win.to_crop(np.nan_to_num(uv, nan=-1e9))
    ok = np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= w) & (uv[:, 1] >= 0) & (uv[:, 1] <= h)
    ok &= (c[:, 0] >= 0) & (c[:, 0] <= win.out_px) & (c[:, 1] >= 0) & (c[:, 1] <= win.out_px)
    if off_axis is not None and limit_deg is not None:
        ok &= off_axis <= limit_deg
    return ok


_DOMAIN: list = []


def _domain():
    """The domain-randomisation pipeline, built on first use in this process (worker)."""
    if not _DOMAIN:
        from .domain import DomainAugment

        _DOMAIN.append(DomainAugment())
    return _DOMAIN[0]


def photometric(img: np.ndarray, rng: np.random.Generator, a: CropAugment) -> np.ndarray:
    x = img.astype(np.float32) / 255.0
    if rng.random() < a.p_photometric:
        x = x * rng.uniform(0.6, 1.4) + rng.uniform(-0.1, 0.1)  # gain, offset
        m = x.mean()
        x = (x - m) * rng.uniform(0.7, 1.3) + m  # contrast
        x = x * rng.uniform(0.9, 1.1, size=3)[None, None, :]  # colour
        x = np.clip(x, 0, 1) ** rng.uniform(0.7, 1.4)  # gamma
    if rng.random() < a.p_blur:
        import cv2

        x = cv2.GaussianBlur(x, (0, 0), rng.uniform(0.3, a.blur_sigma_max_px))
    if rng.random() < a.p_noise:
        x = x + rng.normal(0, rng.uniform(0.005, a.noise_sigma_max), x.shape).astype(np.float32)
    out = (np.clip(x, 0, 1) * 255 + 0.5).astype(np.uint8)
    if a.p_domain > 0 and rng.random() < a.p_domain:
        out = _domain()(out, int(rng.integers(2**31)))
    if rng.random() < a.p_jpeg:
        buf = io.BytesIO()
        Image.fromarray(out).save(buf, format="JPEG", quality=int(rng.integers(40, 95)))
        out = np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB"))
    return out


class CropDataset(torch.utils.data.Dataset):
    """Index i -> one frame's crop. `train` draws a new perturbation each time; otherwise the
    perturbation is fixed per index (seeded), so validation is repeatable."""

    def __init__(
        self,
        scenes: list[Sequence],
        keypoints_m: np.ndarray,
        out_px: int,
        aug: CropAugment,
        train: bool,
        seed: int = 0,
        frames: list[tuple[int, int]] | None = None,
        view_limit_deg: list[float] | None = None,
    ):
        self.scenes, self.kp_m, self.out_px, self.aug, self.train, self.seed = (
            scenes,
            keypoints_m,
            out_px,
            aug,
            train,
            seed,
        )
        self.R_ref = R_cam_target_aligned()
        self.twin = mirror_permutation(keypoints_m) if aug.p_mirror > 0 else None
        if aug.p_mirror > 0 and (self.twin is None or not mirror_symmetric_attitude(self.R_ref)):
            raise ValueError(
                "augment.p_mirror needs a left-right symmetric keypoint set and reference attitude"
            )
        self.view_limit_deg = None if view_limit_deg is None else np.asarray(view_limit_deg, float)
        self.items = (
            frames if frames is not None else [(s, k) for s, sc in enumerate(scenes) for k in range(len(sc))]
        )

    def __len__(self) -> int:
        return len(self.items)

    def _draw_seed(self, i: int) -> list[int]:
        """A training draw's seed: the config's seed, this process's torch seed (the trainer seeds
        torch, and the DataLoader seeds each worker from it, handing batches out in a fixed
        order), the draw's count in this process and the index. The same run seed gives the same
        augmentation run after run (issue 61: it was unseeded), and no two draws share one."""
        self._draws = getattr(self, "_draws", 0) + 1
        return [self.seed, torch.initial_seed() % 2**63, self._draws, i]

    def window(self, uv: np.ndarray, rng: np.random.Generator) -> CropWindow:
        a = self.aug
        base = window_around(uv[np.all(np.isfinite(uv), axis=1)], self.out_px, a.margin)
        c = np.asarray(base.center_px) + rng.normal(0, a.center_jitter, 2) * base.side_px
        side = base.side_px * float(np.exp(rng.uniform(-a.scale_jitter, a.scale_jitter)))
        ang = np.radians(rng.uniform(-a.angle_deg, a.angle_deg))
        if self.train and a.p_roll > 0 and rng.random() < a.p_roll:
            ang = float(rng.uniform(-np.pi, np.pi))
        return CropWindow(tuple(c), side, self.out_px, ang)

    def __getitem__(self, i: int) -> dict:
        s, k = self.items[i]
        sc = self.scenes[s]
        rng = np.random.default_rng(self._draw_seed(i) if self.train else [self.seed, i])
        img = np.asarray(Image.open(sc.dir / sc.files[k]).convert("RGB"))
        R = quat_to_matrix_np(sc.q_cam_target[k])
        T = sc.T_cam_target[k]
        uv = project(sc.K, self.kp_m, R, T)
        win = self.window(uv, rng)
        crop = cut(img, win)
        if self.train:
            crop = photometric(crop, rng, self.aug)
        vis = visible(
            uv, (sc.width_px, sc.height_px), win, off_axis_deg(self.kp_m, R, T), self.view_limit_deg
        )
        kp = win.to_crop(np.nan_to_num(uv, nan=0.0))
        att = attitude_in_crop_deg(win, sc.K, R, self.R_ref)
        mirrored = bool(self.train and self.twin is not None and rng.random() < self.aug.p_mirror)
        if mirrored:  # A, T and R stay the frame's: validation (never mirrored) reads them
            crop = crop[:, ::-1]
            kp = mirror_crop_px(kp, self.twin, self.out_px)
            vis = vis[self.twin]
            att = att * MIRROR_ATT
        return {
            "image": torch.from_numpy(np.ascontiguousarray(crop.transpose(2, 0, 1))).float().div_(255.0),
            "kp_crop_px": torch.from_numpy(kp.astype(np.float32)),
            "att_deg": torch.from_numpy(att.astype(np.float32)),
            "mirrored": mirrored,
            # the head's loss counts this crop: its turn is one the head is trained to read (p_roll)
            "att_weight": float(abs(win.angle_rad) <= np.radians(self.aug.angle_deg) + 1e-9),
            "visible": torch.from_numpy(vis),
            "A": torch.from_numpy(win.matrix().astype(np.float64)),
            "T": torch.from_numpy(np.asarray(T, np.float64)),
            "R": torch.from_numpy(R),
            "scene": s,
            "frame": k,
        }


def off_nominal_deg(T_cam_target_m: np.ndarray, R_cam_target: np.ndarray) -> float:
    """How far a frame is from the nominal aligned approach, in guidance's terms (deg): the hypot
    of guidance's misalignment (the boresight's tilt, roll excluded) and the angle of the probe tip
    off the docking axis seen from the drogue's entrance (its range floored at 0.1 m)."""
    d = docking_from_camera_pose(T_cam_target_m, R_cam_target)
    lateral_deg = float(np.degrees(np.arctan2(d.lateral_m, max(d.range_m, 0.1))))
    return float(np.hypot(d.misalignment_deg, lateral_deg))


def frame_weights(
    scenes: list[Sequence],
    items: list[tuple[int, int]],
    far_from_m: float,
    far_weight: float,
    offaxis_weight_per_deg: float,
    offnominal_from_deg: float = 1.0,
    offnominal_weight: float = 1.0,
) -> np.ndarray:
    """How often training draws each of `items` ((scene, frame) pairs), relative: `far_weight` for
    a frame whose camera range is at least `far_from_m`, else 1, times 1 + `offaxis_weight_per_deg`
    x the fixture's bearing off the boresight (deg), times `offnominal_weight` for a frame at least
    `offnominal_from_deg` off the nominal approach (off_nominal_deg). Why: beyond 8 m the
    validation attitude error is twice the nearer bins' and follows that bearing (a parallax read
    short; docs/model_history.md, 2026-11-28), so a far-range stage spends more of its crops there;
    and a set diluted with aligned approaches teaches a network to read tilts and offsets short
    (candidate 0.18.1's probe), so a stage can give those frames back their share."""
    if far_weight <= 0 or offaxis_weight_per_deg < 0 or offnominal_weight <= 0:
        raise ValueError(
            f"frame weights need far_weight > 0, offaxis_weight_per_deg >= 0 and "
            f"offnominal_weight > 0, got {far_weight}, {offaxis_weight_per_deg} and {offnominal_weight}"
        )
    w = np.empty(len(items))
    for i, (s, k) in enumerate(items):
        T = np.asarray(scenes[s].T_cam_target[k], float)
        bearing_deg = float(np.degrees(np.arctan2(np.hypot(T[0], T[1]), T[2])))
        w[i] = (far_weight if float(np.linalg.norm(T)) >= far_from_m else 1.0) * (
            1.0 + offaxis_weight_per_deg * bearing_deg
        )
        if offnominal_weight != 1.0:
            R = quat_to_matrix_np(scenes[s].q_cam_target[k])
            if off_nominal_deg(T, R) >= offnominal_from_deg:
                w[i] *= offnominal_weight
    return w


def far_only_items(scenes: list[Sequence], first: int, from_m: float) -> list[tuple[int, int]]:
    """The (scene, frame) pairs training draws from: every frame of scenes[:first], and of
    scenes[first:] only the frames whose camera range is at least `from_m`. Why (model 0.25.0):
    the Sun-filled runs gained attitude beyond 5 m in every network trained on them, and read the
    probe's 3 m view short; their far frames alone ask for the first without the second."""
    if not from_m > 0:
        raise ValueError(f"far-only frames need a range > 0 m, got {from_m}")
    items = [(s, k) for s in range(first) for k in range(len(scenes[s]))]
    for s in range(first, len(scenes)):
        r = np.linalg.norm(np.asarray(scenes[s].T_cam_target, float), axis=1)
        items += [(s, int(k)) for k in np.flatnonzero(r >= from_m)]
    return items


def spread_frames(scenes: list[Sequence], n: int) -> list[tuple[int, int]]:
    """About n frames evenly over all scenes (repeatable validation subsets)."""
    total = sum(len(s) for s in scenes)
    step = max(1, total // max(1, n))
    flat = [(s, k) for s, sc in enumerate(scenes) for k in range(len(sc))]
    return flat[::step]
