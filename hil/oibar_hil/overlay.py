"""Draw the berthing fixture's rectangular boundary and its axes from a pose onto a frame, as in
the paper's qualitative figures (green rectangle; X red, Y green, Z blue). Used to eyeball
labels and by the evaluation to show predicted poses.

CLI: python -m oibar_hil.overlay SEQ_DIR FRAME_INDEX OUT.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from oibar.geometry.camera import PinholeCamera
from oibar.geometry.fixture import fixture_corners_t
from oibar.geometry.rotations import quat_to_matrix

AXIS_LENGTH_M = 0.15


def project_fixture(T_cam_target, q_cam_target, camera: PinholeCamera | None = None) -> dict:
    """Pixel positions (pixel-corner convention) of the fixture origin, its four corners and
    its axis tips."""
    cam = camera or PinholeCamera()
    R = quat_to_matrix(q_cam_target)
    t = np.asarray(T_cam_target, dtype=float)
    pts_t = np.vstack([np.zeros(3), fixture_corners_t(), np.eye(3) * AXIS_LENGTH_M])
    uv = cam.project(pts_t @ R.T + t)
    return {"origin": uv[0], "corners": uv[1:5], "axes": uv[5:8]}


def draw_overlay(
    image: Image.Image | np.ndarray,
    T_cam_target,
    q_cam_target,
    camera: PinholeCamera | None = None,
    color=(0, 255, 0),
    width: int = 2,
) -> Image.Image:
    img = Image.fromarray(image) if isinstance(image, np.ndarray) else image.copy()
    img = img.convert("RGB")
    d = ImageDraw.Draw(img)
    p = project_fixture(T_cam_target, q_cam_target, camera)
    if np.all(np.isfinite(p["corners"])):
        pts = [tuple(c) for c in p["corners"]]
        d.line(pts + [pts[0]], fill=color, width=width)
    o = p["origin"]
    if np.all(np.isfinite(o)):
        for tip, col in zip(p["axes"], ((255, 0, 0), (0, 255, 0), (0, 96, 255)), strict=True):
            if np.all(np.isfinite(tip)):
                d.line([tuple(o), tuple(tip)], fill=col, width=width)
    return img


def main(argv: list[str] | None = None) -> int:
    from .dataset import read_poses_csv

    ap = argparse.ArgumentParser(prog="python -m oibar_hil.overlay")
    ap.add_argument("seq_dir", type=Path)
    ap.add_argument("frame", type=int)
    ap.add_argument("out", type=Path)
    a = ap.parse_args(argv)
    row = read_poses_csv(a.seq_dir / "poses.csv")[a.frame]
    T = [float(row[k]) for k in ("tx_m", "ty_m", "tz_m")]
    q = [float(row[k]) for k in ("qw", "qx", "qy", "qz")]
    draw_overlay(Image.open(a.seq_dir / row["file"]), T, q).save(a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
