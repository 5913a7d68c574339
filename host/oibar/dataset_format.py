"""The rendered-sequence format's pose table (poses.csv), shared by its writers (the data-set
generator oibar_hil.dataset, the calibration toolbox's recordings oibar.calib.io) and its readers
(oibar_hil.sequence, oibar.calib.io): one row per frame, docs/synthetic.md."""

from __future__ import annotations

import csv
from pathlib import Path

POSES_COLUMNS: tuple[str, ...] = (
    "frame",
    "file",
    "time_s",
    "phase",
    "phase_name",
    "distance_m",
    "tx_m",
    "ty_m",
    "tz_m",
    "qw",
    "qx",
    "qy",
    "qz",
    "range_m",
    "sun_cam_x",
    "sun_cam_y",
    "sun_cam_z",
)


def read_pose_rows(path, required, error, hint: str) -> list[dict[str, str]]:
    """poses.csv's rows as dicts of strings, each ``required`` column present, or ``error`` (an
    exception class) with one line: no file (``hint`` says how to make one), unreadable, no rows,
    a missing column. The one reader of the table for the generator's sequences and the
    calibration toolbox's labels, which check their values each in their own way."""
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: no such file ({hint})")
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise error(f"{path}: unreadable ({exc})") from None
    if not rows:
        raise error(f"{path}: no rows")
    missing = [c for c in required if c not in rows[0]]
    if missing:
        raise error(f"{path}: missing column(s) {missing}")
    return rows
