"""Choose, on the validation scenes, how the keypoint estimator weighs the PnP keypoints against
the direct model's attitude (oibar.nav.keypoints.refine_with_prior): a grid of (keypoint sigma in
crop pixels, attitude-prior sigma in degrees), scored with the paper's metrics (metrics.score),
"no prior" included. The winner goes into the export's metadata (`kp_export --fusion FILE`).

python -m oibar_models.kp_fusion --model models/oibarnet.onnx [--stride 16] [--out runs/oibarnet_kp/fusion.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from . import metrics
from .config import REPO_ROOT
from .data import load_sequence
from oibar.geometry.rotations import matrix_to_quat as quat_from_matrix_np
from .scenes import load_set

SIGMA_CROP_PX = (0.5, 1.0, 2.0)
SIGMA_PRIOR_DEG = (1.0, 2.0, 3.0, 5.0, None)     # None: PnP alone


def collect(est, seqs, stride: int) -> list[dict]:
    """Frames and the direct model's pose for each (the first pass does not depend on the weights)."""
    rows = []
    for seq in seqs:
        for k in range(0, len(seq), stride):
            img = np.asarray(Image.open(seq.dir / seq.files[k]).convert("RGB"))
            rows.append({"img": img, "T": seq.T_cam_target[k], "q": seq.q_cam_target[k], "direct": est.first.estimate(img)})
    return rows


def score_grid(est, rows: list[dict], progress: bool) -> list[dict]:
    out = []
    grid = [(p, d) for p in SIGMA_CROP_PX for d in SIGMA_PRIOR_DEG if d is not None] + [(None, None)]
    for s_px, s_deg in grid:
        fusion = {"sigma_crop_px": s_px, "sigma_prior_deg": s_deg} if s_deg is not None else {}
        T_hat, q_hat = [], []
        for row in rows:
            d = row["direct"]
            r, _ = est.solve(row["img"], d.R_cam_target, d.T_cam_target_m, fusion=fusion)
            R_, T_ = (r.R_cam_target, r.T_cam_target_m) if r is not None else (d.R_cam_target, d.T_cam_target_m)
            T_hat.append(T_)
            q_hat.append(quat_from_matrix_np(R_))
        s = metrics.summarize(np.array(T_hat), np.array(q_hat), np.array([r["T"] for r in rows]),
                              np.array([r["q"] for r in rows]))
        s.update(sigma_crop_px=s_px, sigma_prior_deg=s_deg, score=metrics.score(s))
        out.append(s)
        if progress:
            print(f"sigma_kp {s_px} px, prior {s_deg} deg: dt {s['dt_mean_pct']:.3f} % (median {s['dt_median_pct']:.3f}) "
                  f"dq {s['dq_mean_deg']:.3f} deg (median {s['dq_median_deg']:.3f}) score {s['score']:.4f}",
                  file=sys.stderr, flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    from oibar.nav.pose import KeypointPoseEstimator, PoseEstimator

    ap = argparse.ArgumentParser(prog="python -m oibar_models.kp_fusion", description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=REPO_ROOT / "models/oibarnet.onnx")
    ap.add_argument("--stride", type=int, default=16)
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "runs/oibarnet_kp/fusion.json")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    est = PoseEstimator(a.model)
    if not isinstance(est, KeypointPoseEstimator):
        print(f"error: {a.model} is not a keypoint model", file=sys.stderr)
        return 2
    seqs = [load_sequence(REPO_ROOT / "data/val" / s.name) for s in load_set(REPO_ROOT / "models/scenes/val.json")]
    rows = collect(est, seqs, a.stride)
    grid = score_grid(est, rows, not a.no_progress)
    best = min(grid, key=lambda g: g["score"])
    a.out.parent.mkdir(parents=True, exist_ok=True)
    for g in grid:
        g.pop("img", None)
    a.out.write_text(json.dumps({"chosen_on": "validation scenes (models/scenes/val.json)", "frames": len(rows),
                                 "stride": a.stride, "best": best, "grid": grid}, indent=1) + "\n")
    print(f"best: sigma_kp {best['sigma_crop_px']} crop px, prior {best['sigma_prior_deg']} deg: "
          f"dt {best['dt_mean_pct']:.3f} %, dq {best['dq_mean_deg']:.3f} deg -> {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
