"""Raw pose estimates against the navigation filter on the synthetic test sequences, with the
paper's metrics (SPEC section 7), and how well the estimator's per-frame confidence tracks its
actual error.

Each sequence is replayed in order at its own frame times (10 Hz): JPEG frame -> PoseEstimator
-> NavFilter.update -> NavFilter.state, exactly the daemon's path. Ground truth (poses.csv) is
used only to score.

Writes into --out: filter_study.md (tables), filter_study.json, <seq>_filter.png (error over
time, raw vs filtered, and the confidence), <seq>_filter.csv (per frame).

A study, not flight code: it lives in oibar_models (tests/host/test_walls.py).

CLI: python -m oibar_models.filter_study --model PATH --data data/synthetic --seqs 1 8 --out DIR
     [--frames-limit N] [--threads 2] [--no-progress]
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from oibar.geometry.docking import docking_from_camera_pose
from oibar.geometry.rotations import quat_to_matrix
from oibar.nav.filter import FilterParams, NavFilter
from oibar.nav.pose import FrameError, ModelFileError, PoseEstimator
from oibar_hil.sequence import DatasetError, read_pose_table

from . import metrics

TRUTH_COLUMNS = ("file", "time_s", "tx_m", "ty_m", "tz_m", "qw", "qx", "qy", "qz")


class StudyError(RuntimeError):
    """Input data for the study is missing or malformed; the message names the file."""


@dataclass
class Truth:
    name: str
    dir: Path
    files: list[str]
    time_s: np.ndarray  # (N,)
    T_cam_target_m: np.ndarray  # (N, 3)
    q_cam_target: np.ndarray  # (N, 4)


def read_truth(seq_dir: Path, frames_limit: int | None = None) -> Truth:
    """poses.csv of a synthetic sequence (docs/synthetic.md), through oibar_hil.sequence (torch-free,
    unlike oibar_models.data's loaders); no manifest needed."""
    try:
        rows, num = read_pose_table(
            seq_dir / "poses.csv", TRUTH_COLUMNS[1:], required=TRUTH_COLUMNS[:1], frames_limit=frames_limit
        )
    except DatasetError as exc:
        raise StudyError(str(exc)) from exc
    return Truth(seq_dir.name, seq_dir, [r["file"] for r in rows], num[:, 0], num[:, 1:4], num[:, 4:8])


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Rank correlation with tied values given their mean rank."""

    def ranks(x):
        x = np.asarray(x, float)
        order = np.argsort(x, kind="mergesort")
        r = np.empty(len(x))
        r[order] = np.arange(len(x), dtype=float)
        _, inv, counts = np.unique(x, return_inverse=True, return_counts=True)
        sums = np.bincount(inv, weights=r)
        return sums[inv] / counts[inv]

    ra, rb = ranks(a), ranks(b)
    if ra.std() == 0 or rb.std() == 0:
        return float("nan")
    return float(np.corrcoef(ra, rb)[0, 1])


def run_sequence(est: PoseEstimator, truth: Truth, params: FilterParams, progress: bool) -> dict:
    """Replay one sequence; per-frame arrays of raw and filtered poses and the filter's verdicts."""
    nav = NavFilter(params)
    n = len(truth.files)
    out = {
        k: np.full((n, d), np.nan)
        for k, d in (
            ("T_raw", 3),
            ("q_raw", 4),
            ("T_filt", 3),
            ("q_filt", 4),
            ("r_D_raw", 3),
            ("v_D_filt", 3),
        )
    }
    conf, lat_ms, upd_ms = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    valid = np.zeros(n, bool)
    reasons, flags = [""] * n, [""] * n
    frame_errors = []
    it = range(n)
    if progress:
        from oibar.progress import progress_iter

        it = progress_iter(it, truth.name, total=n, unit="frame")
    for k in it:
        t_s = float(truth.time_s[k])
        try:
            with Image.open(truth.dir / truth.files[k]) as im:
                img = np.asarray(im.convert("RGB"))
            e = est.estimate(img, t_s)
        except (OSError, FrameError) as exc:  # the daemon skips such a frame and coasts
            frame_errors.append(f"{truth.files[k]}: {exc}")
            nav.predict(t_s)
            reasons[k] = "frame_error"
        else:
            out["T_raw"][k], out["q_raw"][k] = e.T_cam_target_m, e.q_cam_target
            if e.finite:
                out["r_D_raw"][k] = docking_from_camera_pose(e.T_cam_target_m, e.R_cam_target).r_D_m
            conf[k], lat_ms[k], flags[k] = e.confidence, e.latency_ms, "|".join(e.flags)
            t0 = time.perf_counter()
            reasons[k] = nav.update(t_s, *e.measurement(), e.confidence).reason  # as the daemon fuses
            upd_ms[k] = (time.perf_counter() - t0) * 1e3
        if nav.initialised:
            st = nav.state(t_s)
            out["T_filt"][k], out["q_filt"][k], valid[k] = st.T_cam_target_m, st.q_cam_target, st.valid
            out["v_D_filt"][k] = st.v_D_mps
    return {
        **out,
        "confidence": conf,
        "latency_ms": lat_ms,
        "update_ms": upd_ms,
        "valid": valid,
        "reasons": reasons,
        "flags": flags,
        "frame_errors": frame_errors,
        "counts": dict(nav.counts),
    }


def confidence_finding(conf: np.ndarray, dt_pct: np.ndarray, dq_deg: np.ndarray, range_m: np.ndarray) -> dict:
    """Does low confidence mark large errors? Rank correlations, and errors by confidence
    quartile. Correlation with error is expected to be negative if confidence works."""
    ok = np.isfinite(conf) & np.isfinite(dt_pct)
    c, dt, dq, r = conf[ok], dt_pct[ok], dq_deg[ok], range_m[ok]
    edges = np.quantile(c, [0.25, 0.5, 0.75])
    bins = np.digitize(c, edges, right=True)
    quart = []
    for b in range(4):
        m = bins == b
        if m.any():
            quart.append(
                {
                    "quartile": b + 1,
                    "frames": int(m.sum()),
                    "confidence_max": float(c[m].max()),
                    "dt_mean_pct": float(dt[m].mean()),
                    "dt_median_pct": float(np.median(dt[m])),
                    "dq_mean_deg": float(dq[m].mean()),
                }
            )
    return {
        "spearman_conf_dt_pct": spearman(c, dt),
        "spearman_conf_dq_deg": spearman(c, dq),
        "spearman_conf_range": spearman(c, r),
        "spearman_range_dt_pct": spearman(r, dt),
        "frames_below_0.5": int(np.sum(c < 0.5)),
        "frames": int(len(c)),
        "by_quartile": quart,
    }


def motion_metrics(truth: Truth, r: dict) -> dict:
    """What guidance feels beyond the paper's per-frame errors: the closing speed (the capture
    envelope allows 50 mm/s) and the frame-to-frame jitter of the position error. Without a
    filter the closing speed would be the difference of consecutive raw ranges."""
    R_true = np.array([quat_to_matrix(q) for q in truth.q_cam_target])
    r_true = np.array(
        [docking_from_camera_pose(T, R).r_D_m for T, R in zip(truth.T_cam_target_m, R_true, strict=True)]
    )
    v_true = np.gradient(r_true[:, 2], truth.time_s)
    closing_true = -v_true
    closing_raw = -np.diff(r["r_D_raw"][:, 2]) / np.diff(truth.time_s)
    closing_filt = -r["v_D_filt"][:, 2]
    e_raw = closing_raw - closing_true[1:]
    e_filt = (closing_filt - closing_true)[1:]
    rng_m = np.linalg.norm(truth.T_cam_target_m, axis=1)
    jit_raw = np.diff(r["T_raw"] - truth.T_cam_target_m, axis=0) / rng_m[1:, None] * 100.0
    jit_filt = np.diff(r["T_filt"] - truth.T_cam_target_m, axis=0) / rng_m[1:, None] * 100.0
    rms = lambda x: float(np.sqrt(np.nanmean(np.square(x))))  # noqa: E731
    return {
        "closing_speed_err_rms_mm_s_raw": 1e3 * rms(e_raw),
        "closing_speed_err_rms_mm_s_filtered": 1e3 * rms(e_filt),
        "closing_speed_err_p95_mm_s_raw": 1e3 * float(np.nanpercentile(np.abs(e_raw), 95)),
        "closing_speed_err_p95_mm_s_filtered": 1e3 * float(np.nanpercentile(np.abs(e_filt), 95)),
        "jitter_rms_pct_raw": rms(np.linalg.norm(jit_raw, axis=1)),
        "jitter_rms_pct_filtered": rms(np.linalg.norm(jit_filt, axis=1)),
    }


def plot_sequence(path: Path, name: str, time_s, dt_raw, dt_filt, dq_raw, dq_filt, conf) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(3, 1, figsize=(9, 7), sharex=True, gridspec_kw={"height_ratios": [3, 3, 1.4]})
    for a, raw, filt, req, lab in (
        (ax[0], dt_raw, dt_filt, metrics.POS_REQ_PCT, "position error (% of range)"),
        (ax[1], dq_raw, dq_filt, metrics.ATT_REQ_DEG, "attitude error (deg)"),
    ):
        a.plot(time_s, raw, lw=0.7, alpha=0.7, label="raw estimate")
        a.plot(time_s, filt, lw=0.9, label="filtered")
        a.axhline(req, color="r", ls="--", lw=0.8, label="requirement")
        a.set_yscale("log")
        a.set_ylabel(lab)
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=8)
    ax[2].plot(time_s, conf, lw=0.7, color="k")
    ax[2].set_ylim(-0.05, 1.05)
    ax[2].set_ylabel("confidence")
    ax[2].set_xlabel("time (s)")
    ax[2].grid(alpha=0.3)
    ax[0].set_title(f"{name}: raw vs filtered")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_csv(path: Path, truth: Truth, r: dict, dt_raw, dt_filt, dq_raw, dq_filt) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(
            [
                "frame",
                "time_s",
                "range_m",
                "confidence",
                "flags",
                "filter",
                "valid",
                "dt_raw_pct",
                "dt_filt_pct",
                "dq_raw_deg",
                "dq_filt_deg",
                "latency_ms",
            ]
        )
        rng_m = np.linalg.norm(truth.T_cam_target_m, axis=1)
        for k in range(len(truth.files)):
            w.writerow(
                [
                    k,
                    f"{truth.time_s[k]:.3f}",
                    f"{rng_m[k]:.4f}",
                    f"{r['confidence'][k]:.4f}",
                    r["flags"][k],
                    r["reasons"][k],
                    int(r["valid"][k]),
                    f"{dt_raw[k]:.4f}",
                    f"{dt_filt[k]:.4f}",
                    f"{dq_raw[k]:.4f}",
                    f"{dq_filt[k]:.4f}",
                    f"{r['latency_ms'][k]:.3f}",
                ]
            )


def study(
    model: Path,
    data_root: Path,
    seqs: list[int],
    out: Path,
    frames_limit: int | None = None,
    threads: int = 2,
    params: FilterParams | None = None,
    progress: bool = True,
) -> dict:
    params = params or FilterParams()
    est = PoseEstimator(model, threads=threads)  # fails clearly before anything is written
    truths = [read_truth(data_root / f"seq{n:02d}", frames_limit) for n in seqs]
    out.mkdir(parents=True, exist_ok=True)
    result = {
        "model": str(model),
        "model_version": est.meta.get("model_version"),
        "epochs_trained": est.meta.get("epochs_trained"),
        "filter_params": asdict(params),
        "frames_limit": frames_limit,
        "machine": f"{platform.processor() or platform.machine()}, "
        f"{platform.system()}, estimator threads {threads}",
        "sequences": {},
    }
    rows, conf_lines, motion_lines, lat_all, upd_all = [], [], [], [], []
    for truth in truths:
        r = run_sequence(est, truth, params, progress)
        have = np.all(np.isfinite(r["T_raw"]), axis=1) & np.all(np.isfinite(r["T_filt"]), axis=1)
        T, q = truth.T_cam_target_m, truth.q_cam_target
        dt_raw = metrics.position_error_pct(r["T_raw"], T)
        dq_raw = metrics.attitude_error_deg(r["q_raw"], q)
        dt_filt = metrics.position_error_pct(r["T_filt"], T)
        dq_filt = metrics.attitude_error_deg(r["q_filt"], q)
        s_raw = metrics.summarize(r["T_raw"][have], r["q_raw"][have], T[have], q[have])
        s_filt = metrics.summarize(r["T_filt"][have], r["q_filt"][have], T[have], q[have])
        rows += [(truth.name, "raw", s_raw), (truth.name, "filtered", s_filt)]
        finding = confidence_finding(r["confidence"], dt_raw, dq_raw, np.linalg.norm(T, axis=1))
        motion = motion_metrics(truth, r)
        motion_lines.append(
            f"| {truth.name} | {motion['closing_speed_err_rms_mm_s_raw']:.1f} | "
            f"{motion['closing_speed_err_rms_mm_s_filtered']:.1f} | {motion['closing_speed_err_p95_mm_s_raw']:.1f} | "
            f"{motion['closing_speed_err_p95_mm_s_filtered']:.1f} | {motion['jitter_rms_pct_raw']:.2f} | "
            f"{motion['jitter_rms_pct_filtered']:.2f} |"
        )
        lat = r["latency_ms"][np.isfinite(r["latency_ms"])]
        upd = r["update_ms"][np.isfinite(r["update_ms"])]
        lat_all.append(lat)
        upd_all.append(upd)
        result["sequences"][truth.name] = {
            "frames": len(truth.files),
            "scored_frames": int(have.sum()),
            "raw": s_raw,
            "filtered": s_filt,
            "motion": motion,
            "filter_counts": r["counts"],
            "invalid_frames": int(np.sum(~r["valid"])),
            "frame_errors": r["frame_errors"][:20],
            "confidence": finding,
        }
        plot_sequence(
            out / f"{truth.name}_filter.png",
            truth.name,
            truth.time_s,
            dt_raw,
            dt_filt,
            dq_raw,
            dq_filt,
            r["confidence"],
        )
        write_csv(out / f"{truth.name}_filter.csv", truth, r, dt_raw, dt_filt, dq_raw, dq_filt)
        c = r["counts"]
        conf_lines.append(
            f"| {truth.name} | {finding['spearman_conf_dt_pct']:+.2f} | {finding['spearman_conf_dq_deg']:+.2f} | "
            f"{finding['spearman_conf_range']:+.2f} | {finding['spearman_range_dt_pct']:+.2f} | "
            + " | ".join(f"{x['dt_mean_pct']:.1f} / {x['dq_mean_deg']:.2f}" for x in finding["by_quartile"])
            + f" | {c['fused']} / {c['gated']} / {c['reinitialised']} / {c['low_confidence']} |"
        )
    lat, upd = np.concatenate(lat_all), np.concatenate(upd_all)
    result["latency"] = {
        "estimate_mean_ms": float(lat.mean()),
        "estimate_median_ms": float(np.median(lat)),
        "estimate_p95_ms": float(np.percentile(lat, 95)),
        "filter_update_mean_ms": float(upd.mean()),
        "what": "estimate: resize 744x480 -> input size + onnxruntime, per frame, in this replay",
    }
    md = [
        f"# Navigation filter study: {model.name}",
        "",
        f"model version {result['model_version']}, epochs trained {result['epochs_trained']}; "
        f"frames per sequence: {'all' if not frames_limit else f'first {frames_limit}'}; {result['machine']}",
        "",
        metrics.markdown_table(rows),
        "",
        "Closing speed error against the truth (raw: difference of consecutive raw ranges; filtered: the "
        "filter's -v_z), and frame-to-frame jitter of the position error:",
        "",
        "| sequence | closing speed RMS raw (mm/s) | filtered (mm/s) | p95 raw (mm/s) | p95 filtered (mm/s) | "
        "jitter RMS raw (% of range) | filtered (% of range) |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
        *motion_lines,
        "",
        "Confidence against the raw estimate's error (Spearman rank correlation; negative = low confidence marks "
        "large errors), and mean error (position % / attitude deg) by confidence quartile (Q1 lowest); "
        "filter verdicts fused / gated / re-initialised / skipped for low confidence:",
        "",
        "| sequence | rho(conf, dt %) | rho(conf, dq) | rho(conf, range) | rho(range, dt %) | Q1 | Q2 | Q3 | Q4 | "
        "filter |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        *conf_lines,
        "",
        f"Estimator latency (resize + inference): mean {result['latency']['estimate_mean_ms']:.1f} ms, median "
        f"{result['latency']['estimate_median_ms']:.1f} ms, p95 {result['latency']['estimate_p95_ms']:.1f} ms; "
        f"filter update {result['latency']['filter_update_mean_ms']:.2f} ms mean.",
        "",
    ]
    (out / "filter_study.md").write_text("\n".join(md))
    (out / "filter_study.json").write_text(json.dumps(result, indent=1) + "\n")
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m oibar_models.filter_study", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--model", required=True, type=Path, help="exported OibarNet (.onnx)")
    ap.add_argument("--data", required=True, type=Path, help="dataset root holding seqNN folders")
    ap.add_argument("--seqs", required=True, type=int, nargs="+", help="sequence numbers, e.g. 1 8")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--frames-limit", type=int, help="only the first N frames of each sequence")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    if a.frames_limit is not None and a.frames_limit < 2:
        ap.error(f"--frames-limit must be >= 2, got {a.frames_limit}")
    try:
        study(a.model, a.data, a.seqs, a.out, a.frames_limit, a.threads, progress=not a.no_progress)
    except (ModelFileError, StudyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print((a.out / "filter_study.md").read_text())
    print(f"written to {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
