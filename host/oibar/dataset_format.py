"""The rendered-sequence format's pose table (poses.csv), shared by its writers (the data-set
generator oibar_hil.dataset, the calibration toolbox's recordings oibar.calib.io) and its readers
(oibar_hil.sequence, oibar.calib.io): one row per frame, docs/synthetic.md."""

from __future__ import annotations

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
