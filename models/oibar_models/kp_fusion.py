"""Choose, on the validation scenes, how the keypoint estimator weighs the PnP keypoints against
an attitude prior (oibar.nav.keypoints.refine_with_prior): a grid of (whose attitude is the
prior: the direct model's, or the keypoint network's own attitude head when the model has one;
keypoint sigma in crop pixels; attitude-prior sigma in degrees; with or without the
per-keypoint error model), scored with the paper's metrics (metrics.score), "no prior" included.
The winner goes into the export's metadata (`kp_export --fusion FILE`).

The grid scores frames one by one, which is what `estimate()` returns; it cannot see an error the
prior repeats on every frame (the head's tilt shrunk toward "aligned"). That is why the
navigator's filter is fed the same keypoints' prior-free fit (oibar.nav.pose.PoseEstimate.
measurement), chosen on the closed loop of validation looks (docs/model_history.md, 2026-11-24).

The error model (oibar.nav.error_models.KeypointErrorModel) is measured here too: each keypoint's
RMS error per range bin, in crops cut around the true pose of the validation frames (errors past
the PnP inlier threshold clipped to it: RANSAC drops those anyway).
So is each prior's (PriorErrorModel): its RMS attitude error per range bin, the head's measured
as the fit uses it, its gain given back (`--head-error as-used`, the default), or as read.

python -m oibar_models.kp_fusion --model models/oibarnet.onnx [--stride 16] [--priors head]
    [--head-gain FILE | --head-crop-gain FILE] [--head-error as-used|as-read] [--pairs 2:3]
    [--out runs/oibarnet_kp/fusion.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from oibar.geometry.rotations import matrix_to_quat as quat_from_matrix_np
from oibar.geometry.rotations import quat_to_matrix as quat_to_matrix_np
from oibar.nav.pose.reader import CROP_REF_PX

from . import metrics
from .config import REPO_ROOT
from .data import load_sequence
from .scenes import load_set

SIGMA_CROP_PX = (0.5, 1.0, 2.0)  # at a 128 px crop; scaled with the model's crop (fusion_grid)
# the crop every grid before out_px was recorded was run at (a JSON without out_px); the same
# reference the estimator holds its crop-pixel thresholds to
FUSION_REF_CROP_PX = CROP_REF_PX
SIGMA_PRIOR_DEG = (1.0, 2.0, 3.0, 5.0, 8.0, None)  # None: PnP alone
ERROR_RANGE_EDGES_M = (0.0, 1.0, 1.5, 2.0, 3.0, 5.0, 8.0, 100.0)
MIN_RMS_CROP_PX = 0.1  # a floor: no keypoint is trusted beyond the heat map's resolution
PRIOR_CLIP_DEG = 20.0
MIN_RMS_DEG = 0.05


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
        est.forget()
        for k in range(0, len(seq), 1 if track else stride):
            img = np.asarray(Image.open(seq.dir / seq.files[k]).convert("RGB"))
            t_s = float(seq.time_s[k])
            prior = pred.predict(t_s) if pred else None
            if pred:
                pred.add(t_s, est.estimate(img, t_s, prior=prior))
            if k % stride:
                continue
            T, q = seq.T_cam_target[k], seq.q_cam_target[k]
            R_true = quat_to_matrix_np(q)
            uv_true = project(est.reader.K_frame, est.reader.points_m, R_true, T)
            win = window_around(uv_true, est.reader.out_px, est.reader.margin)
            reading = est.reader.read_crop(img, win, refining=True)  # as the refining pass reads it
            uv = est.reader.refined_corners(img, win, reading.uv_px)  # and moves the fixture's corners
            err = np.linalg.norm(uv - uv_true, axis=1) * win.scale
            direct = est.first.estimate(img)
            rows.append(
                {
                    "img": img,
                    "T": T,
                    "q": q,
                    "direct": direct,
                    "kp_err_crop_px": err,
                    "prior": prior,
                    # the head as read and where, for its error as the fit uses it (head_as_used)
                    "R_head": reading.R_cam_target_head,
                    "win": win,
                    "prior_err_deg": {
                        "direct": _angle_deg(direct.R_cam_target, R_true),
                        "head": _angle_deg(reading.R_cam_target_head, R_true),
                    },
                }
            )
    return rows


def _angle_deg(R: np.ndarray | None, R_true: np.ndarray) -> float:
    from oibar.geometry.rotations import rotation_angle_deg

    if R is None or not np.all(np.isfinite(R)):
        return float("nan")
    return rotation_angle_deg(np.asarray(R).T @ R_true)


def head_as_used(est, rows: list[dict], correction: dict[str, Any]) -> None:
    """Each row's head error measured again on the head as the fit takes it for its prior
    (oibar.nav.pose.fusion.Fusion.head_prior with `correction`: {"head_gain": table} or
    {"head_crop_gain": table}), in place. Dividing a reading by a gain of 0.65 also multiplies
    its noise by 1.5: 0.35.13's table of the head as read said 1.13 deg RMS under 1 m, where
    the head its fit used was 4.15 deg off (1.9x from 3 to 5 m; docs/model_card.md)."""
    for row in rows:
        R_head = row.get("R_head")
        if R_head is None or not np.all(np.isfinite(R_head)):
            continue
        rng_m = float(np.linalg.norm(row["T"]))
        R_used = est.fusion.head_prior(R_head, row["win"], rng_m, correction)
        row["prior_err_deg"]["head"] = _angle_deg(R_used, quat_to_matrix_np(row["q"]))


def prior_error_model(rows: list[dict], source: str) -> dict | None:
    """Per range bin, the RMS error (deg) of one attitude prior ("direct" or "head") on the
    validation frames, errors clipped at PRIOR_CLIP_DEG (a gross miss is the search's business,
    not the weight's); a bin with under 5 answers takes the overall RMS. None when the source
    never answered (a model without the head)."""
    err = np.minimum(np.array([r["prior_err_deg"][source] for r in rows], float), PRIOR_CLIP_DEG)
    if not np.any(np.isfinite(err)):
        return None
    rng = np.array([float(np.linalg.norm(r["T"])) for r in rows])
    overall = float(np.sqrt(np.nanmean(err**2)))
    edges = np.asarray(ERROR_RANGE_EDGES_M)
    out = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=False):
        e = err[(rng >= lo) & (rng < hi)]
        e = e[np.isfinite(e)]
        out.append(float(np.sqrt(np.mean(e**2))) if len(e) >= 5 else overall)
    return {
        "range_edges_m": list(ERROR_RANGE_EDGES_M),
        "rms_deg": np.round(np.maximum(out, MIN_RMS_DEG), 4).tolist(),
    }


def error_model(rows: list[dict], clip_crop_px: float) -> dict:
    """Per keypoint and range bin, the RMS of the (clipped) keypoint errors; a bin with fewer than
    5 answers takes the keypoint's overall RMS."""
    err = np.minimum(np.array([r["kp_err_crop_px"] for r in rows]), clip_crop_px)  # NaN stays NaN
    rng = np.array([float(np.linalg.norm(r["T"])) for r in rows])
    answered = np.isfinite(err)
    n_all = answered.sum(axis=0)
    # nanmean's figure without its warning for a keypoint never answered (NaN, filled in below)
    sq_all = (np.where(answered, err, 0.0) ** 2).sum(axis=0)
    overall = np.where(n_all > 0, np.sqrt(sq_all / np.maximum(n_all, 1)), np.nan)
    edges = np.asarray(ERROR_RANGE_EDGES_M)
    table = np.empty((err.shape[1], len(edges) - 1))
    for b, (lo, hi) in enumerate(zip(edges[:-1], edges[1:], strict=False)):
        e = err[(rng >= lo) & (rng < hi)]
        n = np.sum(np.isfinite(e), axis=0)
        # the sum over the finite answers, not nanmean: a keypoint never answered in a bin is
        # expected (it is replaced by its overall RMS below) and should not warn
        sq = np.where(np.isfinite(e), e, 0.0) ** 2
        rms = np.sqrt(sq.sum(axis=0) / np.maximum(n, 1))
        table[:, b] = np.where(n >= 5, rms, overall)
    # a keypoint never answered at all counts as the clip (as bad as a kept answer can be); when
    # none was ever answered (an untrained network on a handful of frames), every one does
    worst = float(np.nanmax(overall)) if np.any(np.isfinite(overall)) else float(clip_crop_px)
    table = np.maximum(np.nan_to_num(table, nan=worst), MIN_RMS_CROP_PX)
    return {"range_edges_m": list(ERROR_RANGE_EDGES_M), "rms_crop_px": np.round(table, 4).tolist()}


def fusion_grid(
    err_model: dict | None,
    prior_models: dict[str, dict | None],
    crop_scale: float = 1.0,
    pairs: list[tuple[float, float]] | None = None,
    pnp_alone: bool = True,
) -> list[tuple]:
    """(attitude prior, keypoint sigma, prior sigma, keypoint error model, prior error model) to
    score, for the priors named in `prior_models` (its value None: that source has no error
    model, a model without the head). The direct prior as 0.5.0 chose it (with and without the
    keypoint error model); each prior with its prior error model and the keypoint error model,
    which won in 0.5.0; the head also without its prior error model; PnP alone. `crop_scale`:
    the model's crop over FUSION_REF_CROP_PX (a 192 px crop reads the fixture over 1.5x the
    pixels, so its keypoint sigmas are 1.5x). `pairs` ((keypoint sigma at a 128 px crop, prior
    sigma deg), ...): only those, each prior with both error models, and PnP alone (the head
    only where the model has one, as in the whole grid). `pnp_alone` False leaves PnP alone out:
    a fusion that must carry a prior (candidate 0.35.8: the head is what reads a 3 m turn).
    ValueError when that leaves nothing to score."""
    alone = [(None, None, None, None, None)] if pnp_alone else []
    if pairs is not None:
        grid = [
            (source, p * crop_scale, d, err_model, pem)
            for source, pem in prior_models.items()
            if source != "head" or pem is not None
            for p, d in pairs
        ]
    else:
        grid = _whole_grid(err_model, prior_models, crop_scale)
    if not grid + alone:
        raise ValueError("no fusion to score: the model has none of the priors, and PnP alone is left out")
    return grid + alone


def _whole_grid(
    err_model: dict | None, prior_models: dict[str, dict | None], crop_scale: float
) -> list[tuple]:
    """fusion_grid's every weight pair, without PnP alone."""
    sig = [(p * crop_scale, d) for p in SIGMA_CROP_PX for d in SIGMA_PRIOR_DEG if d is not None]
    models = [None] if err_model is None else [None, err_model]
    grid = [("direct", p, d, m, None) for m in models for p, d in sig] if "direct" in prior_models else []
    for source, pem in prior_models.items():
        if pem is None:
            continue
        if source == "head":
            grid += [("head", p, d, models[-1], None) for p, d in sig]
        grid += [(source, p, d, models[-1], pem) for p, d in sig]
    return grid


def prior_sigma_scale_arg(text: str) -> dict:
    """'EDGES:SCALES' (comma-separated range edges in m, then one factor per bin) -> a
    PriorSigmaScale table, checked as the flight code will read it. ValueError when malformed."""
    from oibar.nav.error_models import PriorSigmaScale

    try:
        edges, scales = text.split(":")
        table = {
            "range_edges_m": [float(x) for x in edges.split(",")],
            "sigma_scale": [float(x) for x in scales.split(",")],
        }
    except ValueError:
        raise ValueError("give EDGES:SCALES, e.g. 0,3,8,100:1,1000,1") from None
    PriorSigmaScale(table)
    return table


def score_grid(
    est,
    rows: list[dict],
    progress: bool,
    err_model: dict | None = None,
    prior_models: dict | None = None,
    head_gain: dict | None = None,
    pairs: list[tuple[float, float]] | None = None,
    prior_sigma_scale: dict | None = None,
    pnp_alone: bool = True,
    head_crop_gain: dict | None = None,
) -> list[dict]:
    """Each fusion of the grid scored on `rows`; `head_gain` (HeadGainModel's table): the head's
    tilt divided by it wherever the head is the prior, as the flight code does with the export's;
    `head_crop_gain` (HeadCropGainModel's) likewise, in the head's crop; `prior_sigma_scale`
    (PriorSigmaScale's table): every prior's sigma scaled by it."""
    out = []
    grid = fusion_grid(
        err_model,
        {"direct": None} if prior_models is None else prior_models,
        est.reader.out_px / FUSION_REF_CROP_PX,
        pairs,
        pnp_alone,
    )
    for source, s_px, s_deg, em, pem in grid:
        fusion = {"sigma_crop_px": s_px, "sigma_prior_deg": s_deg} if s_deg is not None else {}
        if source == "head":
            fusion["attitude_prior"] = "head"
            if head_gain is not None:
                fusion["head_gain"] = head_gain
            if head_crop_gain is not None:
                fusion["head_crop_gain"] = head_crop_gain
        if em is not None:
            fusion["kp_error_model"] = em
        if pem is not None:
            fusion["prior_error_model"] = pem
        if prior_sigma_scale is not None and s_deg is not None:
            fusion["prior_sigma_scale"] = prior_sigma_scale
        T_hat, q_hat = [], []
        for row in rows:
            d = row["direct"]
            r, _ = est.search.solve(
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
            prior_em=pem is not None,
            head_gain=source == "head" and head_gain is not None,
            head_crop_gain=source == "head" and head_crop_gain is not None,
            prior_sigma_scaled="prior_sigma_scale" in fusion,
            score=metrics.score(s),
        )
        out.append(s)
        if progress:
            print(
                f"sigma_kp {s_px} px{' x error model' if em else ''}, {source} prior {s_deg} deg"
                f"{' x its error model' if pem else ''}: "
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
    ap.add_argument(
        "--priors",
        default="direct,head",
        help="attitude priors to score, comma-separated (direct, head; default both)",
    )
    ap.add_argument(
        "--head-gain",
        type=Path,
        default=None,
        help="the JSON of `python -m oibar_models.kp_head_gain`: the head's tilt divided by it "
        "wherever the head is the prior (and carried into the choice)",
    )
    ap.add_argument(
        "--head-crop-gain",
        type=Path,
        default=None,
        help="the JSON of `python -m oibar_models.kp_head_crop_gain`: the head's rotation in its crop "
        "given back its gain and bearing leak wherever the head is the prior (and carried into the "
        "choice); not with --head-gain",
    )
    ap.add_argument(
        "--pairs",
        default=None,
        help="score only these weights, KP_PX:PRIOR_DEG[,...] (keypoint sigma at a 128 px crop, "
        "prior sigma), each prior with both error models, and PnP alone; default: the whole grid",
    )
    ap.add_argument(
        "--prior-sigma-scale",
        default=None,
        metavar="EDGES:SCALES",
        help="a chosen factor on every prior's sigma by camera range (oibar.fusion.prior_sigma_scale; "
        "chosen on the validation probe, not here), e.g. 0,3,8,100:1,1000,1: from 3 to 8 m the "
        "keypoints alone decide; carried into the choice",
    )
    ap.add_argument(
        "--head-error",
        choices=("as-used", "as-read"),
        default="as-used",
        help="the head prior's error model measured on the head as the fit uses it, its gain "
        "given back (as-used, the default), or as the network reads it (as-read: what every "
        "fusion before 2026-12-07 measured; recipes that did not say so rebuild with it)",
    )
    ap.add_argument(
        "--no-pnp-alone",
        action="store_true",
        help="leave PnP alone (no attitude prior) out of the grid: the chosen fusion carries a prior",
    )
    ap.add_argument(
        "--val-set",
        nargs=2,
        type=Path,
        metavar=("SPEC", "ROOT"),
        default=(Path("models/scenes/val.json"), Path("data/val")),
        help="the validation scenes (a scene set) and where they are rendered (a recipe's build)",
    )
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    pairs = None
    if a.pairs is not None:
        try:
            pairs = [tuple(float(x) for x in p.split(":")) for p in a.pairs.split(",") if p.strip()]
            if not pairs or any(len(p) != 2 or min(p) <= 0 for p in pairs):
                raise ValueError
        except ValueError:
            print(f"error: --pairs: KP_PX:PRIOR_DEG[,...], each > 0, got {a.pairs!r}", file=sys.stderr)
            return 2
    from .kp_export import head_corrections_args

    head_gain, head_crop_gain, err = head_corrections_args(a.head_gain, a.head_crop_gain)
    if err:
        print(err, file=sys.stderr)
        return 2
    prior_sigma_scale = None
    if a.prior_sigma_scale is not None:
        try:
            prior_sigma_scale = prior_sigma_scale_arg(a.prior_sigma_scale)
        except ValueError as exc:
            print(f"error: --prior-sigma-scale {a.prior_sigma_scale!r}: {exc}", file=sys.stderr)
            return 2
    sources = [p.strip() for p in a.priors.split(",") if p.strip()]
    if not sources or any(p not in ("direct", "head") for p in sources):
        print(f"error: --priors: direct and/or head, got {a.priors!r}", file=sys.stderr)
        return 2
    est = PoseEstimator(a.model)
    if not isinstance(est, KeypointPoseEstimator):
        print(f"error: {a.model} is not a keypoint model", file=sys.stderr)
        return 2
    # the grid solves unrelated frames one by one, with no cycle to keep: the whole cold search on
    # each, none carried from one frame to the next (search.COLD_CROP_BUDGET)
    est.search.cold_crop_budget = None
    spec, root = a.val_set
    seqs = [load_sequence(REPO_ROOT / root / s.name) for s in load_set(REPO_ROOT / spec)]
    rows = collect(est, seqs, a.stride, track=not a.single)
    em = error_model(rows, float(est.reader.reproj_crop_px))
    correction = (
        {"head_gain": head_gain}
        if head_gain
        else {"head_crop_gain": head_crop_gain}
        if head_crop_gain
        else {}
    )
    head_error = "as-read" if not correction else a.head_error
    if head_error == "as-used":
        head_as_used(est, rows, correction)
    pems = {source: prior_error_model(rows, source) for source in ("direct", "head")}
    try:
        grid = score_grid(
            est,
            rows,
            not a.no_progress,
            em,
            {k: v for k, v in pems.items() if k in sources},
            head_gain,
            pairs,
            prior_sigma_scale,
            not a.no_pnp_alone,
            head_crop_gain,
        )
    except ValueError as exc:
        print(f"error: {a.model}: {exc}", file=sys.stderr)
        return 2
    best = min(grid, key=lambda g: g["score"])
    if best.get("head_gain"):
        best["head_gain"] = head_gain
    if best.get("head_crop_gain"):
        best["head_crop_gain"] = head_crop_gain
    if best.get("prior_sigma_scaled"):
        best["prior_sigma_scale"] = prior_sigma_scale
    if best.get("error_model"):
        best["kp_error_model"] = em
    if best.get("prior_em"):
        best["prior_error_model"] = pems[best["attitude_prior"]]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    for g in grid:
        g.pop("img", None)
    a.out.write_text(
        json.dumps(
            {
                "chosen_on": f"validation scenes ({spec})",
                "out_px": est.reader.out_px,  # the crop the sigmas are in (kp_export checks it)
                "frames": len(rows),
                "stride": a.stride,
                "mode": "single" if a.single else "track",
                "head_gain": head_gain,
                "head_crop_gain": head_crop_gain,
                "prior_sigma_scale": prior_sigma_scale,
                "pnp_alone": not a.no_pnp_alone,
                "head_error": head_error,
                "best": best,
                "grid": grid,
                "kp_error_model": em,
                "prior_error_models": pems,
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
