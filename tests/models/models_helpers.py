"""Helpers for the OibarNet tests: a tiny dataset in the oibar_hil.dataset layout, drawn here
(no OpenGL needed): dark noisy frames with the fixture's rectangle projected from the label."""

from __future__ import annotations

import csv
import hashlib
import json
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from oibar.dataset_format import POSES_COLUMNS
from oibar.geometry.rotations import matrix_to_quat as quat_from_matrix_np
from oibar.geometry.rotations import rot_x, rot_y, rot_z

CAMERA = {
    "width_px": 744,
    "height_px": 480,
    "fx_px": 3.5 / 6.0e-3,
    "fy_px": 3.5 / 6.0e-3,
    "cx_px": 372.0,
    "cy_px": 240.0,
}


SHIPPED_KP = Path(__file__).resolve().parents[2] / "models" / "oibarnet.onnx"


def shipped_companions(far: bool = True) -> list[str]:
    """The files the shipped keypoint model opens beside it: its first pass, its fixture finder
    (``oibar.finder``; 0.35.15 has one) and any far network (``oibar.far_network``; 0.34.0 had
    one), that last left out with `far` False."""
    from oibar.nav.pose import read_metadata
    from oibar_models.finetune import companions

    meta = read_metadata(SHIPPED_KP)
    if not far:
        meta.pop("far_network", None)
    return companions(meta)


def link_shipped_companions(dst: Path) -> None:
    """Symlink the shipped model's companion files into `dst`, for a copy of it written there."""
    for name in shipped_companions():
        (dst / name).symlink_to(SHIPPED_KP.parent / name)


def copy_shipped(dst: Path) -> Path:
    """Copy the shipped keypoint model and every file it opens beside it into `dst` (tests that
    retag it must not touch the repository's); returns the copy of the main file."""
    import shutil

    for name in [SHIPPED_KP.name, *shipped_companions()]:
        shutil.copy(SHIPPED_KP.parent / name, dst / name)
    return dst / SHIPPED_KP.name


def one_network_copy(dst: Path) -> Path:
    """The shipped main file copied into `dst` with any far network unnamed (the main network
    alone reads every window), its first pass and finder copied beside it; returns the copy."""
    import shutil

    import onnx

    m = onnx.load(str(SHIPPED_KP))
    for p in list(m.metadata_props):
        if p.key == "oibar.far_network":
            m.metadata_props.remove(p)
    out = dst / SHIPPED_KP.name
    onnx.save(m, str(out))
    for name in shipped_companions(far=False):
        shutil.copy(SHIPPED_KP.parent / name, dst / name)
    return out


def draw_frame(T, q, rng) -> Image.Image:
    from oibar_hil.overlay import project_fixture

    img = (rng.normal(12, 4, (CAMERA["height_px"], CAMERA["width_px"], 3))).clip(0, 255).astype(np.uint8)
    im = Image.fromarray(img)
    d = ImageDraw.Draw(im)
    p = project_fixture(T, q)
    d.polygon([tuple(c) for c in p["corners"]], fill=(180, 180, 170), outline=(255, 255, 255))
    o = p["origin"]
    d.ellipse([o[0] - 4, o[1] - 4, o[0] + 4, o[1] + 4], fill=(255, 40, 40))
    for tip, col in zip(p["axes"], ((255, 0, 0), (0, 255, 0), (0, 96, 255)), strict=True):
        d.line([tuple(o), tuple(tip)], fill=col, width=3)
    return im


def write_sequence(seq_dir: Path, n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    (seq_dir / "frames").mkdir(parents=True)
    rows, files = [], {}
    for k in range(n):
        z = rng.uniform(1.5, 4.0)
        T = np.array([rng.uniform(-0.3, 0.3), 0.12 + rng.uniform(-0.2, 0.2), z])
        R = (
            rot_z(np.radians(rng.uniform(-8, 8)))
            @ rot_x(np.radians(rng.uniform(-8, 8)))
            @ rot_y(np.radians(rng.uniform(-8, 8)))
        )
        q = quat_from_matrix_np(R)
        name = f"frames/{k:06d}.jpg"
        draw_frame(T, q, rng).save(seq_dir / name, quality=95)
        files[name] = hashlib.sha256((seq_dir / name).read_bytes()).hexdigest()
        rows.append(
            [
                k,
                name,
                f"{0.1 * k:.3f}",
                2,
                "forced_translation",
                f"{z - 0.3:.6f}",
                *(f"{x:.6f}" for x in T),
                *(f"{x:.9f}" for x in q),
                f"{np.linalg.norm(T):.6f}",
                0,
                0,
                1,
            ]
        )
    with open(seq_dir / "poses.csv", "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(POSES_COLUMNS)
        w.writerows(rows)
    files["poses.csv"] = hashlib.sha256((seq_dir / "poses.csv").read_bytes()).hexdigest()
    manifest = {
        "generator": "tests/models/conftest.py",
        "frames": n,
        "config": {"camera": CAMERA},
        "files": files,
    }
    (seq_dir / "manifest.json").write_text(json.dumps(manifest))


def tiny_config(root: Path, run_dir: Path, **train):
    from oibar_models.config import from_dict

    return from_dict(
        {
            "name": "smoke",
            "run_dir": str(run_dir),
            "data": {
                "root": str(root),
                "train_seqs": [2, 3],
                "test_seqs": [1],
                "chunk_lengths": [8, 16],
                "cache_dir": str(run_dir / "cache"),
            },
            "model": {
                "backbone": "oibar_lite",
                "width": 0.5,
                "input_width_px": 93,
                "input_height_px": 60,
                "coord_channels": True,
            },
            "train": {
                "epochs": 2,
                "batch_size": 8,
                "workers": 0,
                "threads": 2,
                "max_steps_per_epoch": 3,
                **train,
            },
        }
    )
