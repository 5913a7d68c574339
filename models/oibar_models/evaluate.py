"""Evaluation of an exported OibarNet as in the paper (SPEC section 7): per test sequence, mean
and median position error (m and % of range), mean and median attitude error, compliance with
5 % and 5 deg, beside the trivial mean-pose baseline; error-over-time plots; overlay frames
(oibar_hil.overlay: ground truth green, prediction magenta); single-stream latency on this
machine. It evaluates the ONNX file (what flies), not a checkpoint.

Writes into --out (default runs/<name>/eval): eval.md, eval.json, <seq>_errors.csv,
<seq>_errors.png, <seq>_overlay_<frame>.png.

CLI: python -m oibar_models.evaluate --config models/configs/X.yaml [--model X.onnx] [--out DIR]
"""

from __future__ import annotations

import argparse
import csv
import json
import platform
import sys
from pathlib import Path

import numpy as np

from . import metrics
from .data import DatasetError, frame_cache, load_sequence, seq_name
from .infer import ModelFileError, OnnxPoseEstimator, benchmark


def predict_sequence(est: OnnxPoseEstimator, frames: np.ndarray, batch: int = 32, progress: bool = False):
    T, q = [], []
    it = range(0, len(frames), batch)
    if progress:
        from oibar.progress import progress_iter

        it = progress_iter(it, "predict", unit="batch", leave=False)
    for i in it:
        t_i, q_i = est.predict_batch(np.asarray(frames[i : i + batch]))
        T.append(t_i)
        q.append(q_i)
    return np.concatenate(T), np.concatenate(q)


def plot_errors(path: Path, name: str, time_s, dt_pct, dq_deg, dt_pct_base=None, dq_deg_base=None) -> None:
    series = {"OibarNet": (dt_pct, dq_deg)}
    if dt_pct_base is not None:
        series["mean-pose baseline"] = (dt_pct_base, dq_deg_base)
    plot_error_series(path, name, time_s, series)


def plot_error_series(path: Path, name: str, time_s, series: dict) -> None:
    """Position (% of range) and attitude (deg) errors over time, one line per label in
    ``series`` (label -> (dt_pct, dq_deg)), log scale, the requirements dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    for i, (label, (dt_pct, dq)) in enumerate(series.items()):
        alpha = 0.85 if i == 0 else 0.6
        ax[0].plot(time_s, dt_pct, lw=0.8, alpha=alpha, label=label)
        ax[1].plot(time_s, dq, lw=0.8, alpha=alpha, label=label)
    ax[0].axhline(metrics.POS_REQ_PCT, color="r", ls="--", lw=0.8, label="requirement")
    ax[1].axhline(metrics.ATT_REQ_DEG, color="r", ls="--", lw=0.8, label="requirement")
    ax[0].set_ylabel("position error (% of range)")
    ax[1].set_ylabel("attitude error (deg)")
    ax[1].set_xlabel("time (s)")
    ax[0].set_title(name)
    for a in ax:
        a.set_yscale("log")
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_overlays(out: Path, seq, T_hat, q_hat, n: int) -> list[str]:
    from PIL import Image

    from oibar_hil.overlay import draw_overlay

    files = []
    for k in np.linspace(0, len(seq) - 1, n).astype(int) if n > 0 else []:
        with Image.open(seq.dir / seq.files[k]) as im:
            img = draw_overlay(im, seq.T_cam_target[k], seq.q_cam_target[k], color=(0, 255, 0))
        img = draw_overlay(img, T_hat[k], q_hat[k], color=(255, 0, 255))
        p = out / f"{seq.name}_overlay_{k:06d}.png"
        img.save(p)
        files.append(p.name)
    return files


def evaluate(
    model_path: Path,
    seq_dirs: list[Path],
    out: Path,
    cache_dir: Path | None,
    overlays: int = 4,
    bench_s: float = 5.0,
    progress: bool = True,
) -> dict:
    est = OnnxPoseEstimator(model_path)  # fails clearly before anything is written
    out.mkdir(parents=True, exist_ok=True)
    meta = est.meta
    T_base = np.array(meta["train_mean_T_cam_target"])
    q_base = np.array(meta["train_mean_q_cam_target"])
    rows, result = [], {"model": str(model_path), "metadata": meta, "sequences": {}}
    for d in seq_dirs:
        seq = load_sequence(d)
        frames = frame_cache(seq, est.size_wh, cache_dir, progress)
        T_hat, q_hat = predict_sequence(est, frames, progress=progress)
        n = len(seq)
        s_model = metrics.summarize(T_hat, q_hat, seq.T_cam_target, seq.q_cam_target)
        s_base = metrics.summarize(
            np.tile(T_base, (n, 1)), np.tile(q_base, (n, 1)), seq.T_cam_target, seq.q_cam_target
        )
        rows += [(seq.name, "OibarNet", s_model), (seq.name, "mean-pose baseline", s_base)]
        dt_pct = metrics.position_error_pct(T_hat, seq.T_cam_target)
        dq = metrics.attitude_error_deg(q_hat, seq.q_cam_target)
        dt_pct_b = metrics.position_error_pct(np.tile(T_base, (n, 1)), seq.T_cam_target)
        dq_b = metrics.attitude_error_deg(np.tile(q_base, (n, 1)), seq.q_cam_target)
        with open(out / f"{seq.name}_errors.csv", "w", newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(
                [
                    "frame",
                    "time_s",
                    "phase",
                    "range_m",
                    "dt_m",
                    "dt_pct",
                    "dq_deg",
                    "tx_hat_m",
                    "ty_hat_m",
                    "tz_hat_m",
                    "qw_hat",
                    "qx_hat",
                    "qy_hat",
                    "qz_hat",
                ]
            )
            dt = metrics.position_error_m(T_hat, seq.T_cam_target)
            for k in range(n):
                w.writerow(
                    [
                        k,
                        f"{seq.time_s[k]:.3f}",
                        seq.phase[k],
                        f"{seq.range_m[k]:.4f}",
                        f"{dt[k]:.5f}",
                        f"{dt_pct[k]:.4f}",
                        f"{dq[k]:.4f}",
                        *(f"{x:.5f}" for x in T_hat[k]),
                        *(f"{x:.6f}" for x in q_hat[k]),
                    ]
                )
        plot_errors(
            out / f"{seq.name}_errors.png",
            f"{seq.name}: errors over time",
            seq.time_s,
            dt_pct,
            dq,
            dt_pct_b,
            dq_b,
        )
        ov = write_overlays(out, seq, T_hat, q_hat, overlays)
        result["sequences"][seq.name] = {"model": s_model, "baseline": s_base, "overlays": ov}
    if bench_s > 0:
        result["latency"] = {
            "model_only": benchmark(model_path, threads=2, seconds=bench_s, with_preprocess=False),
            "with_preprocess": benchmark(model_path, threads=2, seconds=bench_s, with_preprocess=True),
            "machine": f"{platform.processor() or platform.machine()}, {platform.system()}",
        }
    md = [
        f"# Evaluation of {model_path.name}",
        "",
        f"backbone {meta.get('backbone')}, input {meta['input_size_wh'][0]}x{meta['input_size_wh'][1]}, "
        f"epochs trained {meta.get('epochs_trained')}, model version {meta.get('model_version')}",
        "",
        metrics.markdown_table(rows),
        "",
    ]
    if "latency" in result:
        lm, lp = result["latency"]["model_only"], result["latency"]["with_preprocess"]
        md += [
            f"Latency (onnxruntime, 2 threads, batch 1): model only {lm['mean_ms']:.1f} ms mean "
            f"({lm['inferences_per_s']:.1f} /s); with resize from 744x480 {lp['mean_ms']:.1f} ms "
            f"({lp['inferences_per_s']:.1f} /s)",
            "",
        ]
    (out / "eval.md").write_text("\n".join(md))
    (out / "eval.json").write_text(json.dumps(result, indent=1) + "\n")
    return result


def main(argv: list[str] | None = None) -> int:
    from .config import ConfigError, load_config

    ap = argparse.ArgumentParser(prog="python -m oibar_models.evaluate", description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", required=True)
    ap.add_argument("--model", help="ONNX file (default: the config's export path)")
    ap.add_argument("--out", help="output folder (default runs/<name>/eval)")
    ap.add_argument("--seqs", help="paper sequence numbers, e.g. 1,8 (default: the config's test_seqs)")
    ap.add_argument("--overlays", type=int, default=4, help="overlay frames per sequence")
    ap.add_argument("--bench-s", type=float, default=5.0, help="seconds per latency benchmark (0: skip)")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    try:
        cfg = load_config(a.config)
        model = Path(a.model) if a.model else cfg.onnx_file
        nums = [int(x) for x in a.seqs.split(",")] if a.seqs else cfg.data.test_seqs
        root = cfg.path(cfg.data.root)
        dirs = [root / seq_name(n) for n in nums]
        for p in cfg.data.extra_test_dirs:  # optional extras (e.g. envelope mode): skipped when not rendered
            if cfg.path(p).is_dir():
                dirs.append(cfg.path(p))
            else:
                print(f"note: {cfg.path(p)} not rendered, skipped", file=sys.stderr)
        out = Path(a.out) if a.out else cfg.run_path / "eval"
        res = evaluate(
            model,
            dirs,
            out,
            cfg.path(cfg.data.cache_dir) if cfg.data.cache_dir else None,
            a.overlays,
            a.bench_s,
            not a.no_progress,
        )
    except (ConfigError, DatasetError, ModelFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print((out / "eval.md").read_text())
    print(f"written to {out}")
    return 0 if res["sequences"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
