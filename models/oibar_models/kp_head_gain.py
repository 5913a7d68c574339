"""Measure, on the validation scenes, how much of a tilt the keypoint network's attitude head
reads, per camera range bin: the table the flight code divides the head's tilt by before it uses
the head as the fit's prior (oibar.nav.keypoints.HeadGainModel, the export's
``oibar.fusion.head_gain``; `kp_export --head-gain FILE`).

The head is read as the refining pass reads it, in a crop cut around the true pose (as
`kp_fusion` measures its error), on every `stride`-th frame. Its tilt, guidance's attitude error
about the camera's x and y, is regressed on the truth's in each range bin: both axes pooled, one
intercept per bin and axis (a constant lean is not a gain), the slope is the gain. Trained mostly
on aligned approaches, the head reads a tilt short, most close in (0.15.3: 0.84 of a 3 deg tilt
at 0.5 m on the probe); the prior then pulls every answer toward "aligned" by that much.

python -m oibar_models.kp_head_gain --model models/oibarnet.onnx [--stride 2] \
    [--val-set SPEC ROOT] [--out runs/kp_head_gain.json] [--plot runs/kp_head_gain.png]

`--min-frames` and `--range-edges` are for a toy run (a recipe's smoke build measures a handful
of frames): fewer frames per bin than MIN_FRAMES_PER_BIN give a slope that is mostly noise, and
the default bins are the fusion's error models' (kp_fusion.ERROR_RANGE_EDGES_M). The JSON
records both, so a table measured under them says so.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from oibar.geometry.docking import docking_from_camera_pose
from oibar.geometry.rotations import quat_to_matrix
from oibar.nav.error_models import HEAD_GAIN_LIMITS, HeadGainModel
from oibar.nav.keypoints import project, window_around

from .config import REPO_ROOT, ConfigError
from .data import DatasetError, load_sequence
from .kp_fusion import ERROR_RANGE_EDGES_M
from .scenes import load_set

MIN_FRAMES_PER_BIN = 50  # fewer and a bin's slope is noise (the validation set has 87-800 at stride 4)


class HeadGainError(ValueError):
    """A measurement that cannot give a gain table (too few frames, a gain outside the limits)."""


def collect(est, seqs, stride: int, progress: bool = True) -> dict[str, np.ndarray]:
    """Every `stride`-th frame: the camera range (m), the true tilt and the head's (rad, (N, 2)),
    and the scene's index; frames where the head gives no reading are left out."""
    from oibar.progress import Progress

    rng, true, head, scene = [], [], [], []
    total = sum(len(range(0, len(s), stride)) for s in seqs)
    bar_cm = Progress("head gain", total=total, unit="frame") if progress else contextlib.nullcontext(None)
    with bar_cm as bar:
        for i, seq in enumerate(seqs):
            for k in range(0, len(seq), stride):
                if bar is not None:
                    bar.update(1)
                img = np.asarray(Image.open(seq.dir / seq.files[k]).convert("RGB"))
                T, R_true = seq.T_cam_target[k], quat_to_matrix(seq.q_cam_target[k])
                win = window_around(
                    project(est.reader.K_frame, est.reader.points_m, R_true, T),
                    est.reader.out_px,
                    est.reader.margin,
                )
                R_head = est.reader.read_crop(img, win, refining=True).R_cam_target_head
                if R_head is None or not np.all(np.isfinite(R_head)):
                    continue
                rng.append(float(np.linalg.norm(T)))
                true.append(docking_from_camera_pose(T, R_true).att_rad[:2])
                head.append(docking_from_camera_pose(T, R_head).att_rad[:2])
                scene.append(i)
    return {
        "range_m": np.array(rng),
        "true_rad": np.array(true),
        "head_rad": np.array(head),
        "scene": np.array(scene),
    }


def bin_slope(true_rad: np.ndarray, head_rad: np.ndarray) -> tuple[float, float, np.ndarray]:
    """(slope, its standard error, intercept per axis) of head on truth: the probe's statistic
    (both axes pooled, each centred on its own mean) over the bin as one group."""
    from oibar_hil.rig.probe import slope_fit

    x, y = np.asarray(true_rad, float), np.asarray(head_rad, float)
    b, se = slope_fit(x, y, np.zeros(len(x)))
    if not np.isfinite(b):
        raise HeadGainError("the truth's tilt does not vary in this bin")
    return b, se, y.mean(0) - b * x.mean(0)


def gain_table(
    rows: dict[str, np.ndarray], edges_m=ERROR_RANGE_EDGES_M, min_frames: int = MIN_FRAMES_PER_BIN
) -> dict:
    """The head-gain table (HeadGainModel's input) and each bin's statistics. HeadGainError when a
    bin has fewer than `min_frames` frames or a gain outside HEAD_GAIN_LIMITS."""
    edges = np.asarray(edges_m, float)
    rng = rows["range_m"]
    gains, bins = [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = (rng >= lo) & (rng < hi)
        n = int(m.sum())
        if n < min_frames:
            raise HeadGainError(f"{lo:g}-{hi:g} m: {n} frames, at least {min_frames} needed")
        try:
            b, se, icpt = bin_slope(rows["true_rad"][m], rows["head_rad"][m])
        except HeadGainError as exc:
            raise HeadGainError(f"{lo:g}-{hi:g} m: {exc}") from exc
        if not HEAD_GAIN_LIMITS[0] <= b <= HEAD_GAIN_LIMITS[1]:
            raise HeadGainError(
                f"{lo:g}-{hi:g} m: gain {b:.3f} outside {HEAD_GAIN_LIMITS} (a reading gone wrong?)"
            )
        gains.append(round(b, 4))
        bins.append(
            {
                "range_m": [float(lo), float(hi)],
                "frames": n,
                "tilt_gain": b,
                "tilt_gain_se": se,
                "intercept_deg": np.degrees(icpt).round(4).tolist(),
                "true_tilt_sd_deg": float(np.degrees(rows["true_rad"][m].std())),
            }
        )
    table = {"range_edges_m": [float(e) for e in edges], "tilt_gain": gains}
    HeadGainModel(table)  # the flight code's own check
    return {"head_gain": table, "bins": bins}


def plot(path: Path, rows: dict[str, np.ndarray], result: dict, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bins = result["bins"]
    fig, axes = plt.subplots(1, len(bins), figsize=(2.6 * len(bins), 2.9), sharex=True, sharey=True)
    for ax, b in zip(axes, bins, strict=True):
        lo, hi = b["range_m"]
        m = (rows["range_m"] >= lo) & (rows["range_m"] < hi)
        t, h = np.degrees(rows["true_rad"][m]), np.degrees(rows["head_rad"][m])
        ax.plot(t.ravel(), h.ravel(), ".", ms=2, alpha=0.4)
        lim = np.array([-10.0, 10.0])
        ax.plot(lim, lim, "k:", lw=0.8, label="1:1")
        ax.plot(lim, b["tilt_gain"] * lim, "r-", lw=1, label=f"gain {b['tilt_gain']:.3f}")
        ax.set_title(f"{lo:g}-{hi:g} m ({b['frames']})", fontsize=9)
        ax.set_xlabel("true tilt (deg)")
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("head's tilt (deg)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def add_bin_options(ap: argparse.ArgumentParser, min_frames: int) -> None:
    """--min-frames and --range-edges, as every per-range-bin measurement of the head takes them."""
    ap.add_argument(
        "--min-frames",
        type=int,
        default=min_frames,
        help=f"the fewest frames a range bin is measured on (default {min_frames}; fewer: a toy run)",
    )
    ap.add_argument(
        "--range-edges",
        default=None,
        metavar="E0,E1,...",
        help="the range bins' rising edges in m (default: the fusion's error models', "
        + ",".join(f"{e:g}" for e in ERROR_RANGE_EDGES_M)
        + ")",
    )


def range_edges_arg(text: str | None) -> tuple[float, ...] | None:
    """--range-edges' bins (the fusion's without it), or None once what is wrong is printed."""
    if text is None:
        return tuple(ERROR_RANGE_EDGES_M)
    try:
        edges = tuple(float(e) for e in text.split(","))
        if len(edges) < 2 or any(e < 0 for e in edges) or not np.all(np.diff(edges) > 0):
            raise ValueError
    except ValueError:
        print(f"error: --range-edges: rising edges >= 0, at least two, got {text!r}", file=sys.stderr)
        return None
    return edges


def head_model(path: Path):
    """The keypoint estimator of `path` whose attitude head is to be measured, or None once what
    is wrong (no file, no keypoint model, no head) is printed."""
    from oibar.nav.pose import KeypointPoseEstimator, ModelFileError, PoseEstimator

    try:
        est = PoseEstimator(path)
    except (ModelFileError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None
    if not isinstance(est, KeypointPoseEstimator) or est.reader.R_att_ref is None:
        print(f"error: {path} has no attitude head to measure", file=sys.stderr)
        return None
    return est


def main(argv: list[str] | None = None) -> int:

    ap = argparse.ArgumentParser(
        prog="python -m oibar_models.kp_head_gain", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--model", type=Path, default=REPO_ROOT / "models/oibarnet.onnx")
    ap.add_argument("--stride", type=int, default=2, help="every n-th frame of each validation scene")
    ap.add_argument("--val-root", type=Path, default=REPO_ROOT / "data/val")
    ap.add_argument(
        "--val-set",
        nargs=2,
        type=Path,
        metavar=("SPEC", "ROOT"),
        default=None,
        help="the validation scenes (a scene set) and where they are rendered (a recipe's build); "
        "default: models/scenes/val.json under --val-root",
    )
    add_bin_options(ap, MIN_FRAMES_PER_BIN)
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "runs/kp_head_gain.json")
    ap.add_argument("--plot", type=Path, default=None, help="a PNG of the head's tilt against the truth's")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    if a.stride < 1 or a.min_frames < 2:
        print("error: --stride must be >= 1 and --min-frames >= 2", file=sys.stderr)
        return 2
    edges = range_edges_arg(a.range_edges)
    if edges is None:
        return 2
    spec, root = a.val_set or (REPO_ROOT / "models/scenes/val.json", a.val_root)
    est = head_model(a.model)
    if est is None:
        return 2
    try:
        seqs = [load_sequence(REPO_ROOT / root / s.name) for s in load_set(REPO_ROOT / spec)]
    except (DatasetError, ConfigError) as exc:
        print(f"error: {exc} (render the validation scenes: make dataset-val)", file=sys.stderr)
        return 2
    rows = collect(est, seqs, a.stride, progress=not a.no_progress)
    try:
        result = gain_table(rows, edges, a.min_frames)
    except HeadGainError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    doc = {
        "model": str(a.model),
        "measured_on": f"validation scenes ({spec}), crops around the true pose",
        "stride": a.stride,
        "min_frames_per_bin": a.min_frames,
        "frames": len(rows["range_m"]),
        **result,
    }
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(doc, indent=1) + "\n")
    if a.plot:
        plot(
            a.plot, rows, result, f"{a.model.name}: the attitude head's tilt against the truth's, validation"
        )
    print(" ".join(f"{b['range_m'][0]:g}-{b['range_m'][1]:g} m {b['tilt_gain']:.3f}" for b in result["bins"]))
    print(f"-> {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
