"""Choose the fixture finder's thresholds on validation (issue 58, item 4: cold frames within one
10 Hz cycle). Every frame of the validation scenes is read cold at the flight setting
(`forget()`, then `estimate(rgb, t_s)` with the daemon's crop budget), once without the finder
(the same model file, `finder=False`) and once per setting of oibar.nav.pose.finder_place's FINDER_*
thresholds; each setting is one run in the experiment tracker (experiment "finder_sweep").

    python -m oibar_models.finder_sweep --model CANDIDATE/oibarnet.onnx --stride 16 \
        --min-score 0.2 0.3 0.5 --same-frac 0.15 --same-side 1.25 [--out runs/finder_sweep]

The model file must name its finder (oibar.finder, `kp_export --retag ... --finder NAME`). Writes
sweep.md (the table), sweep.json and sweep.png (latency p95 against silent failures) into --out.
Exit codes: 0 done, 2 bad arguments or files.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
from PIL import Image

from . import metrics
from .config import REPO_ROOT
from .data import DatasetError, load_sequence
from .kp_evaluate import SETS, TRACK_MIN_CONFIDENCE
from .scenes import load_set

FAR_M = 8.0  # the far frames, where the direct model's window misses and the search is slow
THRESHOLDS = {
    "min_score": "FINDER_MIN_SCORE",
    "same_frac": "FINDER_SAME_FRAC",
    "same_side": "FINDER_SAME_SIDE",
}


def read_cold(est, seqs, stride: int, progress: bool, what: str) -> dict[str, np.ndarray]:
    """Every stride-th frame of each sequence, each alone at the flight setting."""
    rows: dict[str, list] = {k: [] for k in ("dt_pct", "dq_deg", "conf", "lat_ms", "crops", "found", "rng_m")}
    items = [(seq, k) for seq in seqs for k in range(0, len(seq), stride)]
    it: Iterable[tuple[Any, int]] = items
    if progress:
        from oibar.progress import progress_iter

        it = progress_iter(items, what, total=len(items), unit="frame", leave=False)
    for seq, k in it:
        img = np.asarray(Image.open(seq.dir / seq.files[k]).convert("RGB"))
        est.forget()
        t0 = time.perf_counter()
        e = est.estimate(img, float(seq.time_s[k]))
        rows["lat_ms"].append((time.perf_counter() - t0) * 1e3)
        T, q = seq.T_cam_target[k], seq.q_cam_target[k]
        if e.finite:
            rows["dt_pct"].append(float(metrics.position_error_pct(e.T_cam_target_m[None], T[None])[0]))
            rows["dq_deg"].append(float(metrics.attitude_error_deg(e.q_cam_target[None], q[None])[0]))
        else:
            rows["dt_pct"].append(np.nan)
            rows["dq_deg"].append(np.nan)
        rows["conf"].append(e.confidence)
        rows["crops"].append(e.crops)
        rows["found"].append("found" in est.last_crops)
        rows["rng_m"].append(float(np.linalg.norm(T)))
    return {k: np.asarray(v) for k, v in rows.items()}


def summary(r: dict[str, np.ndarray]) -> dict[str, float]:
    out = ~((r["dt_pct"] <= 5.0) & (r["dq_deg"] <= 5.0))  # no answer counts as out of bounds
    far = r["rng_m"] >= FAR_M
    return {
        "frames": float(len(out)),
        "dt_mean_pct": float(np.nanmean(r["dt_pct"])),
        "dq_mean_deg": float(np.nanmean(r["dq_deg"])),
        "within_bounds_pct": float(100 * np.mean(~out)),
        "silent_failures": float(np.sum(out & (r["conf"] >= TRACK_MIN_CONFIDENCE))),
        "latency_ms_median": float(np.median(r["lat_ms"])),
        "latency_ms_p95": float(np.percentile(r["lat_ms"], 95)),
        "latency_ms_p95_far": float(np.percentile(r["lat_ms"][far], 95)) if far.any() else float("nan"),
        "crops_mean": float(np.mean(r["crops"])),
        "crops_mean_far": float(np.mean(r["crops"][far])) if far.any() else float("nan"),
        "found_pct": float(100 * np.mean(r["found"])),
    }


COLUMNS = [
    ("frames", "frames", "{:.0f}"),
    ("dt_mean_pct", "dt mean (%)", "{:.2f}"),
    ("dq_mean_deg", "dq mean (deg)", "{:.2f}"),
    ("within_bounds_pct", "within 5 % and 5 deg (%)", "{:.2f}"),
    ("silent_failures", "silent failures", "{:.0f}"),
    ("latency_ms_median", "latency median (ms)", "{:.0f}"),
    ("latency_ms_p95", "latency p95 (ms)", "{:.0f}"),
    ("latency_ms_p95_far", f"p95 >= {FAR_M:g} m (ms)", "{:.0f}"),
    ("crops_mean", "crops mean", "{:.1f}"),
    ("found_pct", "finder's crop read (%)", "{:.1f}"),
]


def plot(path: Path, rows: list[tuple[str, dict]]) -> None:
    """One row per setting: the cold latency p95 (all frames, far frames) against one 10 Hz
    cycle, and the share of frames within bounds with the silent failures written beside it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    y = np.arange(len(rows))
    labels = [label for label, _ in rows]
    fig, ax = plt.subplots(1, 2, figsize=(10, 0.45 * len(rows) + 1.6), sharey=True)
    ax[0].barh(y - 0.2, [s["latency_ms_p95"] for _, s in rows], 0.4, label="all frames")
    ax[0].barh(y + 0.2, [s["latency_ms_p95_far"] for _, s in rows], 0.4, label=f"from {FAR_M:g} m")
    ax[0].axvline(100.0, ls="--", c="k", lw=0.8, label="one 10 Hz cycle")
    ax[0].set_xlabel("cold frame latency, p95 (ms)")
    ax[0].legend(fontsize=8)
    ax[1].barh(y, [s["within_bounds_pct"] for _, s in rows], 0.6, color="tab:green")
    for k, (_, s) in enumerate(rows):
        ax[1].annotate(f"{s['silent_failures']:.0f} silent", (s["within_bounds_pct"], k), fontsize=8,
                       xytext=(-60, -3), textcoords="offset points", color="w")  # fmt: skip
    lo = min(s["within_bounds_pct"] for _, s in rows)
    ax[1].set_xlim(max(0.0, lo - 5.0), 100.0)
    ax[1].set_xlabel("frames within 5 % and 5 deg (%)")
    ax[0].set_yticks(y, labels, fontsize=8)
    ax[0].invert_yaxis()
    for a in ax:
        a.grid(alpha=0.3, axis="x")
    fig.suptitle("fixture finder thresholds: validation scenes, each frame alone (flight setting)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from oibar.nav.pose import KeypointPoseEstimator, ModelFileError, read_metadata
    from oibar.nav.pose import finder_place as S

    ap = argparse.ArgumentParser(
        prog="python -m oibar_models.finder_sweep", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--model", type=Path, required=True, help="a keypoint model file that names its finder")
    ap.add_argument("--set", default="val", choices=[k for k in SETS if k.startswith("val")])
    ap.add_argument("--stride", type=int, default=16, help="every n-th frame of each scene (default 16)")
    for k, const in THRESHOLDS.items():
        ap.add_argument(f"--{k.replace('_', '-')}", type=float, nargs="+", default=[getattr(S, const)],
                        help=f"values of finder_place.{const} (default {getattr(S, const)})")  # fmt: skip
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "runs/finder_sweep")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    if a.stride < 1:
        ap.error("--stride must be >= 1")
    spec, root = SETS[a.set]
    try:
        seqs = [load_sequence(REPO_ROOT / root / s.name) for s in load_set(REPO_ROOT / spec)]
        if read_metadata(a.model).get("kind") != "keypoints":
            raise ModelFileError(f"{a.model}: not a keypoint model")
        base = KeypointPoseEstimator(a.model, finder=False)
        est = KeypointPoseEstimator(a.model, finder=True)
    except DatasetError as exc:
        print(f"error: {exc}\n(render it: make dataset-{a.set.replace('_', '-')})", file=sys.stderr)
        return 2
    except ModelFileError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    a.out.mkdir(parents=True, exist_ok=True)
    progress = not a.no_progress
    grid = [
        dict(zip(THRESHOLDS, v, strict=True))
        for v in itertools.product(a.min_score, a.same_frac, a.same_side)
    ]
    rows: list[tuple[str, dict]] = [
        ("no finder", summary(read_cold(base, seqs, a.stride, progress, "no finder")))
    ]
    settings: list[dict] = [{}]
    saved = {c: getattr(S, c) for c in THRESHOLDS.values()}
    try:
        for g in grid:
            for k, v in g.items():
                setattr(S, THRESHOLDS[k], v)
            label = " ".join(f"{k} {v:g}" for k, v in g.items())
            rows.append((label, summary(read_cold(est, seqs, a.stride, progress, label))))
            settings.append(g)
    finally:
        for c, v in saved.items():
            setattr(S, c, v)
    table = metrics.markdown_table([(a.set, label, s) for label, s in rows], COLUMNS)
    head = (
        f"Fixture finder thresholds: {a.model}, {a.set} every {a.stride}-th frame, "
        "each frame alone (flight setting)\n\n"
    )
    (a.out / "sweep.md").write_text(head + table + "\n")
    (a.out / "sweep.json").write_text(
        json.dumps(
            [{"label": lb, "setting": g, **s} for (lb, s), g in zip(rows, settings, strict=True)], indent=1
        )
        + "\n"
    )
    plot(a.out / "sweep.png", rows)
    print(head + table)
    from . import tracking

    try:
        for (label, s), g in zip(rows, settings, strict=True):
            tracking.log_evaluation(
                SimpleNamespace(name="finder_sweep", path=a.out, seed=0), label, a.model, a.out, s,
                {"set": a.set, "stride": a.stride, "finder": bool(g), **g}, kind="sweep",
            )  # fmt: skip
    except tracking.TrackingError as exc:
        print(f"finder_sweep: not tracked ({exc})", file=sys.stderr)
    print(f"written: {a.out / 'sweep.md'}, {a.out / 'sweep.json'}, {a.out / 'sweep.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
