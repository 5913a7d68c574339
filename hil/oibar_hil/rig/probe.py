"""Does the network follow what guidance needs? A response probe on rendered frames.

The paper's metrics on the nominal sequences cannot tell: there the vehicle stays on the axis
and aligned, so a network that always answers "centred, aligned" scores well. Here the rig's
camera renders the scene with the probe tip moved sideways (and, separately, the vehicle
turned) at several ranges, and the probe fits the estimate against the truth: a slope of 1 is
a network that follows; 0 is one that ignores it.

    python -m oibar_hil.rig.probe --model models/oibarnet.onnx [--scene seq01] [--md OUT.md]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from oibar.geometry.docking import docking_from_camera_pose

RANGES_M = (3.0, 1.0, 0.5)
LATERAL_FRACTION = 0.06  # offsets of +-6 % of the range on each axis (the approach corridor)
ATT_DEG = 3.0  # pitch / yaw offsets


def probe(model_path: str | Path, scene: str = "seq01") -> list[dict]:
    from oibar.nav.pose import PoseEstimator
    from oibar_hil.rig.camera import RigCamera

    est = PoseEstimator(model_path)
    rows = []
    with RigCamera(scene=scene) as cam:
        for rng in RANGES_M:
            d = LATERAL_FRACTION * rng
            lat_true, lat_est = [], []
            for off in ((d, 0), (-d, 0), (0, d), (0, -d), (0, 0)):
                r = np.array([off[0], off[1], rng])
                e = est.estimate(cam.render(r, np.zeros(3)).image)
                s = docking_from_camera_pose(e.T_cam_target_m, e.R_cam_target)
                lat_true.append(r[:2])
                lat_est.append(s.r_D_m[:2])
            lt, le = np.array(lat_true), np.array(lat_est)
            slope = float(np.sum((lt - lt.mean(0)) * (le - le.mean(0))) / np.sum((lt - lt.mean(0)) ** 2))
            att_true, att_est = [], []
            for a in ((ATT_DEG, 0), (-ATT_DEG, 0), (0, ATT_DEG), (0, -ATT_DEG), (0, 0)):
                att = np.radians([a[0], a[1], 0.0])
                e = est.estimate(cam.render(np.array([0.0, 0.0, rng]), att).image)
                s = docking_from_camera_pose(e.T_cam_target_m, e.R_cam_target)
                att_true.append(att[:2])
                att_est.append(s.att_rad[:2])
            at, ae = np.array(att_true), np.array(att_est)
            a_slope = float(np.sum((at - at.mean(0)) * (ae - ae.mean(0))) / np.sum((at - at.mean(0)) ** 2))
            rows.append(
                {
                    "range_m": rng,
                    "lateral_offset_m": d,
                    "lateral_slope": slope,
                    "lateral_err_rms_m": float(np.sqrt(np.mean(np.sum((le - lt) ** 2, 1)))),
                    "attitude_slope": a_slope,
                    "attitude_err_rms_deg": float(np.degrees(np.sqrt(np.mean(np.sum((ae - at) ** 2, 1))))),
                }
            )
    return rows


def markdown(rows: list[dict], model: str, scene: str) -> str:
    out = [
        f"Response probe of `{model}` on scene {scene} (rendered by the rig camera): slope of the "
        f"estimate against the truth (1 = follows, 0 = ignores) and the RMS error.",
        "",
        "| range (m) | lateral offsets (m) | lateral slope | lateral RMS error (cm) | attitude offsets (deg) "
        "| attitude slope | attitude RMS error (deg) |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        out.append(
            f"| {r['range_m']:.1f} | ±{r['lateral_offset_m']:.3f} | {r['lateral_slope']:.2f} | "
            f"{r['lateral_err_rms_m'] * 100:.1f} | ±{ATT_DEG:.0f} | {r['attitude_slope']:.2f} | "
            f"{r['attitude_err_rms_deg']:.2f} |"
        )
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_hil.rig.probe", description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--scene", default="seq01")
    ap.add_argument("--md", type=Path, default=None, help="also write the table here")
    a = ap.parse_args(argv)
    try:
        rows = probe(a.model, a.scene)
    except Exception as exc:
        from oibar.nav.pose import ModelFileError

        if isinstance(exc, ModelFileError) or type(exc).__name__ == "RigCameraError":
            print(f"error: {exc}", file=sys.stderr)
            return 2
        raise
    text = markdown(rows, str(a.model), a.scene)
    print(text)
    if a.md:
        a.md.parent.mkdir(parents=True, exist_ok=True)
        a.md.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
