"""A sequence as the camera rolled about its boresight would see it: every frame turned about the
principal point and every pose turned with it. Exact for a pinhole camera (rolling it only turns
the image; what the turn brings in from outside the frame reads black), so any sequence in the
generator's layout, a lab recording's too, gets rolled looks with exact labels: a validation run
at the roll of a held one, say (issue 58, rolled views; docs/calibration.md, "The schedule").

    python -m oibar_models.rolled SRC --roll-deg 90 --out DIR

Exit status: 0 written, 2 bad arguments or an unreadable sequence.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import shutil
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from oibar.geometry.rotations import matrix_to_quat, quat_to_matrix

from .data import DatasetError, load_sequence

POSE_COLUMNS = ("tx_m", "ty_m", "tz_m")
QUAT_COLUMNS = ("qw", "qx", "qy", "qz")
SUN_COLUMNS = ("sun_cam_x", "sun_cam_y", "sun_cam_z")  # the Sun's direction in the camera frame
JPEG_QUALITY = 95


def roll_matrix(roll_deg: float) -> np.ndarray:
    """The camera's roll about its boresight (+z), turning +x towards +y (+u towards +v)."""
    a = np.radians(roll_deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def rolled_frame(img: np.ndarray, roll_deg: float, cx_px: float, cy_px: float) -> np.ndarray:
    """`img` as the camera rolled by roll_deg sees it: turned about the principal point (cx, cy
    in the generator's convention, pixel edges), from +u towards +v; outside reads black."""
    import cv2

    c = np.array([cx_px - 0.5, cy_px - 0.5])  # OpenCV counts from pixel centres
    rot = roll_matrix(roll_deg)[:2, :2]
    M = np.hstack([rot, (c - rot @ c)[:, None]])
    h, w = img.shape[:2]
    return cv2.warpAffine(img, M, (w, h), flags=cv2.INTER_LINEAR, borderValue=(0, 0, 0))


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def roll_sequence(src: Path, out: Path, roll_deg: float) -> Path:
    """Write `src` rolled by `roll_deg` into the folder `out` (made; must not hold a sequence)."""
    seq = load_sequence(src, verify_hashes=True)
    if (out / "manifest.json").exists():
        raise DatasetError(f"{out}: holds a sequence already")
    (out / "frames").mkdir(parents=True, exist_ok=True)
    manifest = json.loads((src / "manifest.json").read_text())
    cam = manifest["config"]["camera"]
    files: dict[str, str] = {}
    for name in seq.files:
        img = np.asarray(Image.open(src / name).convert("RGB"))
        im = Image.fromarray(rolled_frame(img, roll_deg, float(cam["cx_px"]), float(cam["cy_px"])))
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        if Path(name).suffix.lower() in (".jpg", ".jpeg"):
            im.save(out / name, quality=JPEG_QUALITY)
        else:
            im.save(out / name)
        files[name] = _sha256(out / name)
    _write_poses(src / "poses.csv", out / "poses.csv", roll_matrix(roll_deg))
    files["poses.csv"] = _sha256(out / "poses.csv")
    if (src / "spec.json").is_file():
        shutil.copy(src / "spec.json", out / "spec.json")
    manifest["files"] = files
    manifest["rolled"] = {"from": str(src), "roll_deg": float(roll_deg), "about": "the principal point"}
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    load_sequence(out, verify_hashes=True)  # reads back as any sequence does
    return out


def _write_poses(src: Path, dst: Path, R_roll: np.ndarray) -> None:
    """poses.csv with T and q turned by R_roll (and the Sun's camera direction where given)."""
    with open(src, newline="") as fh:
        reader = csv.DictReader(fh)
        fields = list(reader.fieldnames or [])
        rows = list(reader)
    for row in rows:
        T = R_roll @ np.array([float(row[c]) for c in POSE_COLUMNS])
        R = R_roll @ quat_to_matrix(np.array([float(row[c]) for c in QUAT_COLUMNS]))
        q = matrix_to_quat(R)
        q = q if q[0] >= 0 else -q
        row.update({c: f"{x:.6f}" for c, x in zip(POSE_COLUMNS, T, strict=True)})
        row.update({c: f"{x:.9f}" for c, x in zip(QUAT_COLUMNS, q, strict=True)})
        if all(row.get(c) not in (None, "") for c in SUN_COLUMNS):
            sun = R_roll @ np.array([float(row[c]) for c in SUN_COLUMNS])
            row.update({c: f"{x:.6f}" for c, x in zip(SUN_COLUMNS, sun, strict=True)})
    with open(dst, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields, lineterminator="\n")
        w.writeheader()
        w.writerows(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_models.rolled", description=__doc__.split("\n\n")[0])
    ap.add_argument("src", type=Path, help="a sequence folder (manifest.json, poses.csv, frames/)")
    ap.add_argument("--roll-deg", type=float, required=True, help="the camera's roll about its boresight")
    ap.add_argument("--out", type=Path, required=True, help="the rolled sequence's folder")
    a = ap.parse_args(argv)
    if not np.isfinite(a.roll_deg):
        ap.error("--roll-deg must be a finite number of degrees")
    try:
        out = roll_sequence(a.src, a.out, a.roll_deg)
    except (DatasetError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"written: {out} ({a.src.name} rolled by {a.roll_deg:g} deg)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
