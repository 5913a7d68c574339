"""Choose, on the validation scenes, how the keypoint estimator weighs the PnP keypoints against
an attitude prior (oibar.nav.keypoints.refine_with_prior): a grid of (whose attitude is the
prior: the direct model's, or the keypoint network's own attitude head when the model has one;
keypoint sigma in crop pixels; attitude-prior sigma in degrees; with or without the
per-keypoint error model), scored with the paper's metrics (metrics.score), "no prior" included.
The winner goes into the export's metadata (`kp_export --fusion FILE`).

The error model (oibar.nav.keypoints.KeypointErrorModel) is measured here too: each keypoint's
RMS error per range bin, in crops cut around the true pose of the validation frames (errors past
the PnP inlier threshold clipped to it: RANSAC drops those anyway).

python -m oibar_models.kp_fusion --model models/oibarnet.onnx [--stride 16] [--out runs/oibarnet_kp/fusion.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from oibar.geometry.rotations import matrix_to_quat as quat_from_matrix_np
from oibar.geometry.rotations import quat_to_matrix as quat_to_matrix_np

from . import metrics
from .config import REPO_ROOT
from .data import load_sequence
from .scenes import load_set

SIGMA_CROP_PX = (0.5, 1.0, 2.0)
SIGMA_PRIOR_DEG = (1.0, 2.0, 3.0, 5.0, 8.0, None)  # None: PnP alone
ERROR_RANGE_EDGES_M = (0.0, 1.0, 1.5, 2.0, 3.0, 5.0, 8.0, 100.0)
MIN_RMS_CROP_PX = 0.1  # a floor: no keypoint is trusted beyond the heat map's resolution


def collect(est, seqs, stride: int, track: bool = True) -> list[dict]:
    """Every `stride`-th frame, the direct model's pose for each (the first pass does not depend
    on the weights), the keypoints' errors in a crop around the true pose (crop pixels, NaN where
    not found) and, with `track`, the pose predicted from the estimator's answers on every frame
    before it (kp_evaluate.Predictor), as the daemon's filter gives it: the grid then scores the
    weights on the frames the estimator really crops, not on first-pass misses it never meets
    in flight."""
    from oibar.nav.keypoints import project, window_around

    from .kp_evaluate import Predictor

    rows = []
    for seq in seqs:
        pred = Predictor() if track else None
        for k in range(0, len(seq), 1 if track else stride):
            img = np.asarray(Image.open(seq.dir / seq.files[k]).convert("RGB"))
            t_s = float(seq.time_s[k])
            prior = pred.predict(t_s) if pred else None
            if pred:
                pred.add(t_s, est.estimate(img, t_s, prior=prior))
            if k % stride:
                continue
            T, q = seq.T_cam_target[k], seq.q_cam_target[k]
            uv_true = project(est.K_frame, est.points_m, quat_to_matrix_np(q), T)
            win = window_around(uv_true, est.out_px, est.margin)
            uv, _, _ = est.keypoints(img, win)
            err = np.linalg.norm(uv - uv_true, axis=1) * win.scale
            rows.append(
                {
                    "img": img,
                    "T": T,
                    "q": q,
                    "direct": est.first.estimate(img),
                    "kp_err_crop_px": err,
                    "prior": prior,
                }
            )
    return rows


def error_model(rows: list[dict], clip_crop_px: float) -> dict:
    """Per keypoint and range bin, the RMS of the (clipped) keypoint errors; a bin with fewer than
    5 answers takes the keypoint's overall RMS."""
    err = np.minimum(np.array([r["kp_err_crop_px"] for r in rows]), clip_crop_px)  # NaN stays NaN
    rng = np.array([float(np.linalg.norm(r["T"])) for r in rows])
    overall = np.sqrt(np.nanmean(err**2, axis=0))
    edges = np.asarray(ERROR_RANGE_EDGES_M)
    table = np.empty((err.shape[1], len(edges) - 1))
    for b, (lo, hi) in enumerate(zip(edges[:-1], edges[1:], strict=False)):
        e = err[(rng >= lo) & (rng < hi)]
        n = np.sum(np.isfinite(e), axis=0)
        with np.errstate(invalid="ignore"):
            rms = np.sqrt(np.nanmean(e**2, axis=0)) if len(e) else np.full(err.shape[1], np.nan)
        table[:, b] = np.where(n >= 5, rms, overall)
    table = np.maximum(np.nan_to_num(table, nan=float(np.nanmax(overall))), MIN_RMS_CROP_PX)
    return {"range_edges_m": list(ERROR_RANGE_EDGES_M), "rms_crop_px": np.round(table, 4).tolist()}


def fusion_grid(err_model: dict | None, head: bool) -> list[tuple]:
    """(attitude prior, keypoint sigma, prior sigma, error model) to score. The head's prior is
    tried with the error model only when there is one (it won with the direct prior, 0.5.0)."""
    models = [None] if err_model is None else [None, err_model]
    grid = [
        ("direct", p, d, m) for m in models for p in SIGMA_CROP_PX for d in SIGMA_PRIOR_DEG if d is not None
    ]
    if head:
        grid += [("head", p, d, models[-1]) for p in SIGMA_CROP_PX for d in SIGMA_PRIOR_DEG if d is not None]
    grid.append((None, None, None, None))
    return grid


def score_grid(est, rows: list[dict], progress: bool, err_model: dict | None = None) -> list[dict]:
    out = []
    grid = fusion_grid(err_model, getattr(est, "R_att_ref", None) is not None)
    for source, s_px, s_deg, em in grid:
        fusion = {"sigma_crop_px": s_px, "sigma_prior_deg": s_deg} if s_deg is not None else {}
        if source == "head":
            fusion["attitude_prior"] = "head"
        if em is not None:
            fusion["kp_error_model"] = em
        T_hat, q_hat = [], []
        for row in rows:
            d = row["direct"]
            r, _ = est.solve(
                row["img"], d.R_cam_target, d.T_cam_target_m, fusion=fusion, prior=row.get("prior")
            )
            R_, T_ = (
                (r.R_cam_target, r.T_cam_target_m) if r is not None else (d.R_cam_target, d.T_cam_target_m)
            )
            T_hat.append(T_)
            q_hat.append(quat_from_matrix_np(R_))
        s = metrics.summarize(
            np.array(T_hat),
            np.array(q_hat),
            np.array([r["T"] for r in rows]),
            np.array([r["q"] for r in rows]),
        )
        s.update(
            attitude_prior=source,
            sigma_crop_px=s_px,
            sigma_prior_deg=s_deg,
            error_model=em is not None,
            score=metrics.score(s),
        )
        out.append(s)
        if progress:
            print(
                f"sigma_kp {s_px} px{' x error model' if em else ''}, {source} prior {s_deg} deg: "
                f"dt {s['dt_mean_pct']:.3f} % (median {s['dt_median_pct']:.3f}) "
                f"dq {s['dq_mean_deg']:.3f} deg (median {s['dq_median_deg']:.3f}) score {s['score']:.4f}",
                file=sys.stderr,
                flush=True,
            )
    return out


def main(argv: list[str] | None = None) -> int:
    from oibar.nav.pose import KeypointPoseEstimator, PoseEstimator

    ap = argparse.ArgumentParser(
        prog="python -m oibar_models.kp_fusion", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--model", type=Path, default=REPO_ROOT / "models/oibarnet.onnx")
    ap.add_argument("--stride", type=int, default=16)
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "runs/oibarnet_kp/fusion.json")
    ap.add_argument("--single", action="store_true", help="score every frame alone (no predicted pose)")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    est = PoseEstimator(a.model)
    if not isinstance(est, KeypointPoseEstimator):
        print(f"error: {a.model} is not a keypoint model", file=sys.stderr)
        return 2
    seqs = [
        load_sequence(REPO_ROOT / "data/val" / s.name) for s in load_set(REPO_ROOT / "models/scenes/val.json")
    ]
    rows = collect(est, seqs, a.stride, track=not a.single)
    em = error_model(rows, float(est.reproj_crop_px))
    grid = score_grid(est, rows, not a.no_progress, em)
    best = min(grid, key=lambda g: g["score"])
    if best.get("error_model"):
        best["kp_error_model"] = em
    a.out.parent.mkdir(parents=True, exist_ok=True)
    for g in grid:
        g.pop("img", None)
    a.out.write_text(
        json.dumps(
            {
                "chosen_on": "validation scenes (models/scenes/val.json)",
                "frames": len(rows),
                "stride": a.stride,
                "mode": "single" if a.single else "track",
                "best": best,
                "grid": grid,
                "kp_error_model": em,
            },
            indent=1,
        )
        + "\n"
    )
    print(
        f"best: sigma_kp {best['sigma_crop_px']} crop px, {best['attitude_prior']} prior "
        f"{best['sigma_prior_deg']} deg: "
        f"dt {best['dt_mean_pct']:.3f} %, dq {best['dq_mean_deg']:.3f} deg -> {a.out}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
