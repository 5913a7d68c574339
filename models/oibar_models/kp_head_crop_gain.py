"""Measure, on probe frames of scenes the network did not train on, how the keypoint network's
attitude head reads an out-of-plane rotation in its own crop, per camera range bin: the table the
flight code inverts before it uses the head as the fit's prior (oibar.nav.error_models.
HeadCropGainModel, the export's ``oibar.fusion.head_crop_gain``; `kp_export --head-crop-gain FILE`).

Per range bin, the head's out-of-plane rotation in the crop (x and y, deg) is fitted as

    head = gain * truth + bearing_leak * bearing      (crop frame; each scene and range centred)

on the response probe's frames (oibar_hil.rig.probe.offsets: the vehicle moved sideways and, apart,
turned) at two ranges of the bin (its near edge, no nearer than 0.5 m, and its middle), rendered
by the rig camera and read in windows cut on the true pose. Both kinds are needed: a sideways step
changes the view and the bearing together, a turn the bearing alone, so only the two together part
the head's reading of a view (gain) from the keystone an off-centre affine crop shows (leak).

Why not the docking-frame gain (kp_head_gain): measured on the validation sequences, where turns
come with the approach's views, it cannot tell the two apart, and a head fine-tuned on randomised
looks reads a 3 m turn at 0.88 there and a view at 0.64 (0.35.6). One gain on the tilt then gives
either the turn or the view back, never both (docs/model_card.md, "Can a gain give the turn back?").

python -m oibar_models.kp_head_crop_gain --model M.onnx --spec models/scenes/train.json \
    --scenes tr001,tr005,... [--out runs/kp_head_crop_gain.json] [--plot P.png]

Exit 0 with the table, 1 when the measurement gives none (too few frames, a value outside the
flight code's limits), 2 on bad input (a missing model, an unknown scene).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

import numpy as np

from .config import REPO_ROOT
from .kp_fusion import ERROR_RANGE_EDGES_M

CLOSEST_M = 0.5  # the probe's and the approaches' nearest range: a bin's near edge is no nearer
FARTHEST_M = 12.0  # the far bin's "middle" is taken up to here (the approaches start at 10-12 m)
MIN_FRAMES_PER_BIN = 50  # fewer and the fit is noise (24 scenes give 864 a bin)


class HeadCropGainError(ValueError):
    """A measurement that cannot give a table (too few frames, a value outside the limits)."""


def bin_ranges_m(edges_m=ERROR_RANGE_EDGES_M) -> list[tuple[float, float]]:
    """The two ranges each bin is probed at: its near edge (no nearer than CLOSEST_M) and the
    middle between that and its far edge (no farther than FARTHEST_M)."""
    out = []
    for lo, hi in zip(edges_m[:-1], edges_m[1:], strict=True):
        near = max(float(lo), CLOSEST_M)
        out.append((near, round(0.5 * (near + min(float(hi), FARTHEST_M)), 3)))
    return out


def collect(est, scenes: list, ranges_m: list[float], progress: bool = True) -> dict[str, np.ndarray]:
    """Every probe frame of every scene at every range, read by the head in a window cut on the
    true pose: the nominal range (m), the group (scene x range), and x, y (deg, crop frame) of the
    head's reading, the truth's and the window's bearing. Frames the head gives no reading of are
    left out."""
    from oibar.nav.keypoints import attitude_in_crop_deg, bearing_in_crop_deg, project, window_around
    from oibar.progress import Progress
    from oibar_hil.rig.camera import RigCamera, scene_spec
    from oibar_hil.rig.probe import offsets

    rd = est.reader
    rng, group, head, true, bearing = [], [], [], [], []
    total = len(scenes) * sum(len(offsets(r)) for r in ranges_m)
    bar_cm = (
        Progress("head crop gain", total=total, unit="frame") if progress else contextlib.nullcontext(None)
    )
    with bar_cm as bar:
        for i, s in enumerate(scenes):
            with RigCamera(scene=scene_spec(s)) as cam:
                for j, range_m in enumerate(ranges_m):
                    for _kind, r_D, att in offsets(range_m):
                        if bar is not None:
                            bar.update(1)
                        f = cam.render(r_D, att)
                        T, R = f.T_cam_target_m, f.R_cam_target
                        win = window_around(project(rd.K_frame, rd.points_m, R, T), rd.out_px, rd.margin)
                        R_head = rd.read_crop(f.image, win, refining=True).R_cam_target_head
                        if R_head is None or not np.all(np.isfinite(R_head)):
                            continue
                        rng.append(range_m)
                        group.append(i * len(ranges_m) + j)
                        head.append(attitude_in_crop_deg(win, rd.K_frame, R_head, rd.R_att_ref)[:2])
                        true.append(attitude_in_crop_deg(win, rd.K_frame, R, rd.R_att_ref)[:2])
                        bearing.append(bearing_in_crop_deg(win, rd.K_frame)[:2])
    return {
        "range_m": np.array(rng, float),
        "group": np.array(group, int),
        "head_deg": np.array(head, float).reshape(-1, 2),
        "true_deg": np.array(true, float).reshape(-1, 2),
        "bearing_deg": np.array(bearing, float).reshape(-1, 2),
    }


def _centred(a: np.ndarray, group: np.ndarray) -> np.ndarray:
    out = a.copy()
    for gid in np.unique(group):
        m = group == gid
        out[m] -= a[m].mean(0)
    return out


def fit_bin(group: np.ndarray, head: np.ndarray, true: np.ndarray, bearing: np.ndarray) -> dict:
    """Least squares of head on (truth, bearing), both axes pooled, each (group, axis) centred on
    its own mean (a scene's constant lean is not a gain): gain, leak, their standard errors and
    the residual's RMS (deg). HeadCropGainError when the truth and the bearing do not vary apart."""
    y = _centred(head, group).ravel()
    A = np.stack([_centred(true, group).ravel(), _centred(bearing, group).ravel()], 1)
    AtA = A.T @ A
    if not np.all(np.isfinite(AtA)) or np.linalg.cond(AtA) > 1e8:
        raise HeadCropGainError(
            "the truth's rotation and the bearing do not vary apart (sideways steps and turns both needed)"
        )
    coef = np.linalg.solve(AtA, A.T @ y)
    res = y - A @ coef
    dof = max(len(y) - 2 * len(np.unique(group)) - 2, 1)
    se = np.sqrt(np.diag(np.linalg.inv(AtA)) * float(res @ res) / dof)
    return {
        "gain": float(coef[0]),
        "gain_se": float(se[0]),
        "bearing_leak": float(coef[1]),
        "bearing_leak_se": float(se[1]),
        "resid_rms_deg": float(np.sqrt(np.mean(res**2))),
    }


def gain_table(
    rows: dict[str, np.ndarray], edges_m=ERROR_RANGE_EDGES_M, min_frames: int = MIN_FRAMES_PER_BIN
) -> dict:
    """The crop-gain table (HeadCropGainModel's input) and each bin's statistics, the frames
    binned by their nominal range. HeadCropGainError when a bin has fewer than `min_frames`
    frames or a value outside the flight code's limits."""
    from oibar.nav.error_models import HEAD_CROP_GAIN_LIMITS, HEAD_CROP_LEAK_LIMITS, HeadCropGainModel

    edges = np.asarray(edges_m, float)
    gains, leaks, bins = [], [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = (rows["range_m"] >= lo) & (rows["range_m"] < hi)
        n = int(m.sum())
        if n < min_frames:
            raise HeadCropGainError(f"{lo:g}-{hi:g} m: {n} frames, at least {min_frames} needed")
        try:
            b = fit_bin(rows["group"][m], rows["head_deg"][m], rows["true_deg"][m], rows["bearing_deg"][m])
        except HeadCropGainError as exc:
            raise HeadCropGainError(f"{lo:g}-{hi:g} m: {exc}") from exc
        for what, v, (vlo, vhi) in (
            ("gain", b["gain"], HEAD_CROP_GAIN_LIMITS),
            ("bearing leak", b["bearing_leak"], HEAD_CROP_LEAK_LIMITS),
        ):
            if not vlo <= v <= vhi:
                raise HeadCropGainError(
                    f"{lo:g}-{hi:g} m: {what} {v:.3f} outside {vlo}-{vhi} (a reading gone wrong?)"
                )
        gains.append(round(b["gain"], 4))
        leaks.append(round(b["bearing_leak"], 4))
        bins.append(
            {
                "range_m": [float(lo), float(hi)],
                "probed_at_m": sorted(set(rows["range_m"][m].tolist())),
                "frames": n,
                **b,
            }
        )
    table = {"range_edges_m": [float(e) for e in edges], "gain": gains, "bearing_leak": leaks}
    HeadCropGainModel(table)  # the flight code's own check
    return {"head_crop_gain": table, "bins": bins}


def plot(path: Path, rows: dict[str, np.ndarray], result: dict, title: str) -> None:
    """Per bin: the head's reading with its bearing leak taken out against the truth (each group
    centred), the fitted gain and 1:1."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bins = result["bins"]
    fig, axes = plt.subplots(1, len(bins), figsize=(2.6 * len(bins), 3.0), sharex=True, sharey=True)
    for ax, b in zip(np.atleast_1d(axes), bins, strict=True):
        lo, hi = b["range_m"]
        m = (rows["range_m"] >= lo) & (rows["range_m"] < hi)
        g = rows["group"][m]
        t = _centred(rows["true_deg"][m], g)
        h = _centred(rows["head_deg"][m], g) - b["bearing_leak"] * _centred(rows["bearing_deg"][m], g)
        ax.plot(t.ravel(), h.ravel(), ".", ms=2, alpha=0.4)
        lim = np.array([-1.2, 1.2]) * max(1.0, float(np.abs(t).max()) if t.size else 1.0)
        ax.plot(lim, lim, "k:", lw=0.8, label="1:1")
        ax.plot(lim, b["gain"] * lim, "r-", lw=1, label=f"gain {b['gain']:.3f}")
        ax.set_title(f"{lo:g}-{hi:g} m, leak {b['bearing_leak']:+.3f}", fontsize=8)
        ax.set_xlabel("true rotation in crop (deg)")
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[0].set_ylabel("head, leak removed (deg)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from oibar_hil.dataset import DatasetError, load_spec_file

    from .kp_head_gain import add_bin_options, head_model, range_edges_arg

    ap = argparse.ArgumentParser(
        prog="python -m oibar_models.kp_head_crop_gain", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--model", type=Path, default=REPO_ROOT / "models/oibarnet.onnx")
    ap.add_argument("--spec", type=Path, required=True, help="a scene set (models/scenes/*.json)")
    ap.add_argument(
        "--scenes",
        default=None,
        help="comma-separated scene names of the set (default: all); scenes the network did not train on",
    )
    add_bin_options(ap, MIN_FRAMES_PER_BIN)
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "runs/kp_head_crop_gain.json")
    ap.add_argument("--plot", type=Path, default=None, help="a PNG of each bin's fit")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    if a.min_frames < 2:
        print("error: --min-frames must be >= 2", file=sys.stderr)
        return 2
    edges = range_edges_arg(a.range_edges)
    if edges is None:
        return 2
    try:
        specs = {s.name: s for s in load_spec_file(a.spec)}
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    names = list(specs) if a.scenes is None else [n.strip() for n in a.scenes.split(",") if n.strip()]
    unknown = [n for n in names if n not in specs]
    if not names or unknown:
        print(f"error: --scenes: {unknown or 'none'} not in {a.spec}", file=sys.stderr)
        return 2
    est = head_model(a.model)
    if est is None:
        return 2
    ranges = sorted({r for pair in bin_ranges_m(edges) for r in pair})
    rows = collect(est, [specs[n] for n in names], ranges, progress=not a.no_progress)
    try:
        result = gain_table(rows, edges, a.min_frames)
    except HeadCropGainError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    doc = {
        "model": str(a.model),
        "measured_on": f"probe frames of {a.spec} ({len(names)} scenes), windows cut on the true pose",
        "scenes": names,
        "ranges_m": ranges,
        "min_frames_per_bin": a.min_frames,
        "frames": len(rows["range_m"]),
        **result,
    }
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(doc, indent=1) + "\n")
    if a.plot:
        plot(a.plot, rows, result, f"{a.model.name}: the head's rotation in its crop against the truth's")
    print(
        " ".join(
            f"{b['range_m'][0]:g}-{b['range_m'][1]:g} m {b['gain']:.3f}/{b['bearing_leak']:+.3f}"
            for b in result["bins"]
        )
    )
    print(f"-> {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
