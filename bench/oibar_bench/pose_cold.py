"""Cold frames at the flight setting (issue 58, item 4): a frame with nothing carried, no
prediction and no earlier fit (a cold start, a lost track), read by the shipped estimator as the
daemon reads it (``PoseEstimator(model).estimate(frame)``, the crop budget it flies). Goal: the
95th percentile of its latency within one 10 Hz cycle (100 ms) on 2 cores. Each frame's crops
are tallied by the search stage that read them (oibar.nav.pose.search.STAGES), which is where
a slow frame's time went.

Frames: the validation scenes (models/scenes/val.json), every VAL_STRIDE-th rendered frame of
each: read from data/val when rendered (`make dataset-val`), else rendered here. Quick mode:
sequence 1's approach frames (pose.shipped's).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .core import Context, Result, Target, measurement
from .pose import SHIPPED_KP, approach_frames_dir

VAL_STRIDE = 16  # of data/val's frames (each scene's every 8th render step): ~18 frames a scene
COLD_TARGET = Target("<=", 100.0, "ms", "issue 58: p95 of a cold frame within one 10 Hz cycle")
FAR_FROM_M = 8.0  # the far network's range: where the direct model's window misses most
SEARCH = ("placed", "found", "weak_turned", "steps", "turn", "zoom", "scan")  # the stages that look for a fit

COLUMNS = [
    ("what", "frames"),
    ("frames", "n"),
    ("median_ms", "median (ms)"),
    ("p90_ms", "p90 (ms)"),
    ("p95_ms", "p95 (ms)"),
    ("max_ms", "max (ms)"),
    ("crops", "crops a frame: median / p95 / max"),
    ("target", "target (p95)"),
    ("gap", "gap"),
]
STAGE_COLUMNS = [
    ("stage", "stage"),
    ("reached", "frames reaching it"),
    ("share_pct", "share of frames (%)"),
    ("crops_pct", "share of all crops (%)"),
    ("per_frame", "crops a frame reaching it: median / max"),
    ("deepest_p95_ms", "p95 latency of the frames whose search ended there (ms)"),
]


def _val_frames(ctx: Context) -> tuple[list[tuple[Path, float, float]], str]:
    """(frame file, t_s, true range m) of every VAL_STRIDE-th validation frame, and where from."""
    from dataclasses import replace

    from oibar_hil.dataset import generate_dataset
    from oibar_models.data import load_sequence
    from oibar_models.scenes import load_set

    specs = load_set(ctx.root / "models" / "scenes" / "val.json")
    data = ctx.root / "data" / "val"
    if all((data / s.name / "manifest.json").is_file() for s in specs):
        seqs = [load_sequence(data / s.name) for s in specs]
        picks = [(q, k) for q in seqs for k in range(0, len(q), VAL_STRIDE)]
        where = f"data/val, every {VAL_STRIDE}th frame of its {len(specs)} scenes"
    else:
        out = ctx.tmp / "val_cold"
        coarse = [replace(s, frame_stride=s.frame_stride * VAL_STRIDE) for s in specs]
        ctx.progress(f"pose cold: rendering {len(coarse)} validation scenes, every {VAL_STRIDE}th frame")
        generate_dataset(out, coarse, workers=2, progress=False)
        seqs = [load_sequence(out / s.name) for s in coarse]
        picks = [(q, k) for q in seqs for k in range(len(q))]
        where = f"the {len(specs)} validation scenes rendered here, every {VAL_STRIDE}th frame of data/val's"
    frames = [
        (q.dir / q.files[k], float(q.time_s[k]), float(np.linalg.norm(q.T_cam_target[k]))) for q, k in picks
    ]
    return frames, where


def _quick_frames(ctx: Context) -> tuple[list[tuple[Path, float, float]], str]:
    seq_dir, where = approach_frames_dir(ctx, 40)
    if seq_dir is None:
        return [], where
    return [(f, 0.1 * i, np.nan) for i, f in enumerate(sorted(seq_dir.iterdir()))], where


def cold_run(ctx: Context) -> dict:
    """Every frame alone through the shipped estimator: latency, crops and crops by stage."""
    if "cold_run" in ctx.shared:
        return ctx.shared["cold_run"]
    from PIL import Image

    from oibar.nav.pose import PoseEstimator

    frames, where = _quick_frames(ctx) if ctx.quick else _val_frames(ctx)
    est = PoseEstimator(ctx.root / SHIPPED_KP, threads=ctx.threads)
    lat, crops, ranges, stages = [], [], [], []
    for i, (path, t_s, range_m) in enumerate(frames):
        img = np.asarray(Image.open(path).convert("RGB"))  # one at a time: 635 frames are 0.7 GB
        est.forget()  # nothing carried: each frame is a cold start
        t0 = time.perf_counter()
        e = est.estimate(img, t_s)
        lat.append((time.perf_counter() - t0) * 1e3)
        crops.append(e.crops)
        ranges.append(range_m)
        stages.append(est.last_crops)
        if i % 100 == 0:
            ctx.progress(f"pose cold: frame {i + 1}/{len(frames)}")
    run = {
        "lat": np.array(lat),
        "crops": np.array(crops),
        "range_m": np.array(ranges),
        "stages": stages,
        "where": where,
    }
    ctx.shared["cold_run"] = run
    return run


def _run_or_why(ctx: Context) -> tuple[dict | None, str]:
    """The cold run both tables read, or None and why there is none."""
    if not (ctx.root / SHIPPED_KP).is_file():
        return None, f"{SHIPPED_KP} does not exist: no cold-frame tables."
    run = cold_run(ctx)
    if not len(run["lat"]):
        return None, f"No frames: {run['where']}."
    return run, ""


def _latency_row(what: str, lat: np.ndarray, crops: np.ndarray) -> dict:
    p50, p90, p95 = (float(np.percentile(lat, q)) for q in (50, 90, 95))
    c50, c95 = (float(np.percentile(crops, q)) for q in (50, 95))
    return {
        "what": what,
        "frames": int(len(lat)),
        "median_ms": p50,
        "p90_ms": p90,
        "p95_ms": p95,
        "max_ms": float(lat.max()),
        "crops": f"{c50:.0f} / {c95:.0f} / {int(crops.max())}",
        "target": COLD_TARGET,
        "measured": p95,
    }


@measurement("pose.cold", "Cold frames at the flight setting (each frame alone)", COLUMNS)
def cold_latency(ctx: Context) -> Result:
    from oibar.nav.pose.search import COLD_CROP_BUDGET

    run, why = _run_or_why(ctx)
    if run is None:
        return Result([], [why])
    lat, crops, rng = run["lat"], run["crops"], run["range_m"]
    rows = [_latency_row("all", lat, crops)]
    if np.isfinite(rng).all():
        for name, m in (
            (f"under {FAR_FROM_M:g} m", rng < FAR_FROM_M),
            (f"from {FAR_FROM_M:g} m", rng >= FAR_FROM_M),
        ):
            if m.any():
                rows.append(_latency_row(name, lat[m], crops[m]))
    notes = [
        f"Frames: {run['where']}. Each read alone (`forget()` first, no prediction), the crop budget the "
        f"daemon flies (COLD_CROP_BUDGET {COLD_CROP_BUDGET}: the search steps and the cold search count; "
        "a search not done by then goes on in the next frame, flagged `searching`); "
        f"{ctx.threads} onnxruntime threads. A crop is one 128x128 window through a keypoint network.",
        "The stage table below says where the crops went. A tracked frame reads 1-3 crops (pose.shipped).",
    ]
    return Result(rows, notes)


def _stage_rows(stages: list[dict[str, int]], lat: np.ndarray) -> list[dict]:
    from oibar.nav.pose.search import STAGES

    total = max(1, sum(sum(s.values()) for s in stages))
    # where each frame's search ended: its deepest search stage (the checks after a found fit
    # follow any of them)
    deepest = [max((SEARCH.index(k) for k in s if k in SEARCH), default=-1) for s in stages]
    rows = []
    for name in STAGES:
        per = np.array([s[name] for s in stages if name in s])
        last = lat[np.array(deepest) == SEARCH.index(name)] if name in SEARCH else np.array([])
        rows.append(
            {
                "stage": name,
                "reached": int(len(per)),
                "share_pct": 100.0 * len(per) / max(1, len(stages)),
                "crops_pct": 100.0 * float(per.sum()) / total if len(per) else 0.0,
                "per_frame": f"{np.median(per):.0f} / {per.max()}" if len(per) else "-",
                "deepest_p95_ms": float(np.percentile(last, 95)) if len(last) else None,
            }
        )
    return rows


@measurement("pose.cold_stages", "Where a cold frame's crops go (search stages)", STAGE_COLUMNS)
def cold_stages(ctx: Context) -> Result:
    run, why = _run_or_why(ctx)
    if run is None:
        return Result([], [why])
    notes = [
        "Stages in the order a frame may reach them (oibar.nav.pose.search.STAGES): placed (a window a "
        "pose placed: none on a cold frame), found (the fixture finder's window), weak_turned (a weak "
        "fit of a turned fixture read in the window it turns upright; files whose keypoints read any "
        "turn only), steps (SEARCH_STEPS around the direct model's window), turn (its window turned, "
        "TURN_STEPS_DEG), zoom and scan (the cold search, under the budget), upright (a found fit read "
        "upside down), zoom_out (a found fit read larger), refine.",
        f"A frame's search ends at the deepest of {', '.join(SEARCH[:-1])} and {SEARCH[-1]} it reached: "
        "the p95 column shows which of them make the slow frames.",
    ]
    return Result(_stage_rows(run["stages"], run["lat"]), notes)
