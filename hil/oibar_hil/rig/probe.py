"""Does the network follow what guidance needs? A response probe on rendered frames.

The paper's metrics on the nominal sequences cannot tell: there the vehicle stays on the axis
and aligned, so a network that always answers "centred, aligned" scores well. Here the rig's
camera renders the scene with the probe tip moved sideways (and, separately, the vehicle
turned) at several ranges, and the probe fits the estimate against the truth: a slope of 1 is
a network that follows; 0 is one that ignores it.

Each range gets 9 lateral frames (offsets of -1, -1/2, 0, 1/2, 1 times 6 % of the range on each
axis) and 9 turned ones (the same steps of 3 deg in pitch and yaw), per scene. With several
scenes the slope is fitted with each scene's own mean removed, and its standard error comes
with it. Two readings are probed: the pose the estimator answers and the measurement the
navigation filter is fed (PoseEstimate.measurement(): for a keypoint model the fit without the
attitude prior).

Why a slope falls short, in two numbers: where the camera sees the fixture (its bearing,
T_cam_target's direction) and from where it sees it (the view: the camera's direction from the
fixture, in the fixture's frame). A lateral offset changes both; a turn mostly the bearing.
Guidance's lateral offset at 3 m is mostly the view (3 m x 1 deg = 5 cm), so a network that
places the fixture exactly but reads its perspective timidly has a bearing slope of 1 and a
lateral slope well under it.

    python -m oibar_hil.rig.probe --model models/oibarnet.onnx          # the 22 validation scenes
    python -m oibar_hil.rig.probe --model M --scenes va000,va003 --json P.json --plot P.png --md P.md
    python -m oibar_hil.rig.probe --model M --scenes seq01              # a test scene: report only
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from oibar.geometry.docking import docking_from_camera_pose

RANGES_M = (3.0, 1.0, 0.5)
LATERAL_FRACTION = 0.06  # offsets of +-6 % of the range on each axis (the approach corridor)
ATT_DEG = 3.0  # pitch / yaw offsets
STEPS = (-1.0, -0.5, 0.5, 1.0)  # fractions of the offset, on each axis in turn, plus the centre
VAL_SPEC = "models/scenes/val.json"


def offsets(range_m: float) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(kind, probe tip r_D_m, attitude error att_rad) of one range's frames: 'lateral' and
    'attitude', the centre first, then STEPS on x, then on y."""
    d = LATERAL_FRACTION * range_m
    out: list[tuple[str, np.ndarray, np.ndarray]] = []
    for kind in ("lateral", "attitude"):
        for step, axis in [(0.0, 0)] + [(s, a) for a in (0, 1) for s in STEPS]:
            off = np.zeros(2)
            off[axis] = step
            if kind == "lateral":
                out.append((kind, np.array([off[0] * d, off[1] * d, range_m]), np.zeros(3)))
            else:
                att = np.radians([off[0] * ATT_DEG, off[1] * ATT_DEG, 0.0])
                out.append((kind, np.array([0.0, 0.0, range_m]), att))
    return out


def view_xy(T_cam_target_m: np.ndarray, R_cam_target: np.ndarray) -> np.ndarray:
    """The camera's direction seen from the fixture (unit vector in the fixture frame), x and y:
    what the fixture's perspective tells."""
    p = -np.asarray(R_cam_target, float).T @ np.asarray(T_cam_target_m, float)
    return (p / np.linalg.norm(p))[:2]


def bearing_xy(T_cam_target_m: np.ndarray) -> np.ndarray:
    """The fixture's direction seen from the camera (unit vector, camera frame), x and y: where
    it is in the image."""
    T = np.asarray(T_cam_target_m, float)
    return (T / np.linalg.norm(T))[:2]


def slope_fit(truth: np.ndarray, est: np.ndarray, groups: Iterable[Any]) -> tuple[float, float]:
    """Least-squares slope of `est` on `truth` (N, 2): both axes pooled, each (group, axis)
    centred on its own mean (a scene's constant bias is not a response), with its standard
    error. NaN when the truth does not vary."""
    x, y = np.asarray(truth, float), np.asarray(est, float)
    g = np.asarray(list(groups))
    xc, yc = x.copy(), y.copy()
    for name in np.unique(g):
        m = g == name
        xc[m] -= x[m].mean(0)
        yc[m] -= y[m].mean(0)
    xc, yc = xc.ravel(), yc.ravel()
    sxx = float(xc @ xc)
    if sxx <= 0:
        return float("nan"), float("nan")
    b = float(xc @ yc) / sxx
    n_groups = 2 * len(np.unique(g))  # one mean removed per (group, axis)
    dof = max(len(xc) - n_groups - 1, 1)
    se = float(np.sqrt(float(np.sum((yc - b * xc) ** 2)) / dof / sxx))
    return b, se


def probe_frames(
    est: Any, cameras: Iterable[tuple[str, Any]], ranges_m: Iterable[float] = RANGES_M
) -> list[dict]:
    """Every probe frame of every (scene name, camera) through `est.estimate`, each on its own
    (no prediction, nothing carried from the frame before): truth, the answer and the filter's
    measurement, in guidance's terms (probe tip and attitude error) and as view and bearing."""
    rows = []
    for scene, cam in cameras:
        for rng in ranges_m:
            for kind, r_D, att in offsets(float(rng)):
                f = cam.render(r_D, att)
                est.forget()
                e = est.estimate(f.image, 0.0)
                row: dict[str, Any] = {
                    "scene": scene,
                    "range_m": float(rng),
                    "kind": kind,
                    "lateral_true_m": r_D[:2].tolist(),
                    "attitude_true_rad": att[:2].tolist(),
                    "view_true": view_xy(f.T_cam_target_m, f.R_cam_target).tolist(),
                    "bearing_true": bearing_xy(f.T_cam_target_m).tolist(),
                    "confidence": float(e.confidence),
                    "flags": list(e.flags),
                    "answered": bool(e.finite),
                }
                if e.finite:
                    for name, (T, R) in (
                        ("est", (e.T_cam_target_m, e.R_cam_target)),
                        ("meas", e.measurement()),
                    ):
                        s = docking_from_camera_pose(T, R)
                        row[f"lateral_{name}_m"] = s.r_D_m[:2].tolist()
                        row[f"attitude_{name}_rad"] = s.att_rad[:2].tolist()
                        row[f"view_{name}"] = view_xy(T, R).tolist()
                    row["bearing_est"] = bearing_xy(e.T_cam_target_m).tolist()
                rows.append(row)
    return rows


def summarise(frames: list[dict]) -> list[dict]:
    """One row per range: slopes (+- standard error) and RMS errors of the answer; the same
    slopes for the filter's measurement (`meas_*`); the view and bearing slopes."""
    out = []
    for rng in sorted({f["range_m"] for f in frames}, reverse=True):
        at = [f for f in frames if f["range_m"] == rng]
        ok = [f for f in at if f["answered"]]

        def arr(rows: list[dict], key: str) -> np.ndarray:
            return np.array([r[key] for r in rows], float).reshape(-1, 2)

        lat = [f for f in ok if f["kind"] == "lateral"]
        att = [f for f in ok if f["kind"] == "attitude"]
        row: dict[str, Any] = {
            "range_m": rng,
            "lateral_offset_m": LATERAL_FRACTION * rng,
            "frames": len(at),
            "answered": len(ok),
            "scenes": len({f["scene"] for f in at}),
        }
        for name, prefix in (("est", ""), ("meas", "meas_")):
            for kind, rows, unit, scale in (
                ("lateral", lat, "m", 1.0),
                ("attitude", att, "rad", float(np.degrees(1.0))),
            ):
                truth, est = arr(rows, f"{kind}_true_{unit}"), arr(rows, f"{kind}_{name}_{unit}")
                b, se = slope_fit(truth, est, [f["scene"] for f in rows])
                row[f"{prefix}{kind}_slope"], row[f"{prefix}{kind}_slope_se"] = b, se
                rms = float(np.sqrt(np.mean(np.sum((est - truth) ** 2, 1)))) * scale if rows else float("nan")
                row[f"{prefix}{kind}_err_rms_{'m' if kind == 'lateral' else 'deg'}"] = rms
            b, se = slope_fit(arr(ok, "view_true"), arr(ok, f"view_{name}"), [f["scene"] for f in ok])
            row[f"{prefix}view_slope"], row[f"{prefix}view_slope_se"] = b, se
        row["bearing_slope"], row["bearing_slope_se"] = slope_fit(
            arr(ok, "bearing_true"), arr(ok, "bearing_est"), [f["scene"] for f in ok]
        )
        out.append(row)
    return out


def scene_list(text: str, repo_root: Path) -> list[tuple[str, Any]]:
    """'val' (every scene of the validation set), or comma-separated names: the paper's seqNN,
    the validation set's vaNNN, or FILE:NAME -> [(name, spec or scene string)]."""
    from oibar_hil.dataset import load_spec_file

    if text == "val":
        return [(s.name, s) for s in load_spec_file(repo_root / VAL_SPEC)]
    out: list[tuple[str, Any]] = []
    for name in (n.strip() for n in text.split(",") if n.strip()):
        if name.startswith("va") and ":" not in name:
            out.append((name, f"{repo_root / VAL_SPEC}:{name}"))
        else:
            out.append((name.rsplit(":", 1)[-1], name))
    if not out:
        raise ValueError(f"--scenes {text!r}: no scene named")
    return out


def probe(
    model_path: str | Path, scene: str | list[str] = "seq01", ranges_m: Iterable[float] = RANGES_M
) -> list[dict]:
    """The summary rows (summarise) of `model_path` on one scene or several (rig camera scenes:
    seqNN, FILE:NAME or SequenceSpec)."""
    return summarise(probe_scenes(model_path, [scene] if isinstance(scene, str) else scene, ranges_m))


def probe_scenes(
    model_path: str | Path, scenes: list[Any], ranges_m: Iterable[float] = RANGES_M, progress: bool = False
) -> list[dict]:
    """Per-frame rows (probe_frames) over `scenes`, one rig camera at a time."""
    from oibar.nav.pose import PoseEstimator
    from oibar_hil.rig.camera import RigCamera, scene_spec

    specs = [scene_spec(s) for s in scenes]  # an unknown scene fails before the model loads
    est = PoseEstimator(model_path)
    frames: list[dict] = []
    for i, spec in enumerate(specs):
        with RigCamera(scene=spec) as cam:
            frames += probe_frames(est, [(spec.name, cam)], ranges_m)
        if progress:
            print(f"probe: {i + 1}/{len(specs)} scenes ({spec.name})", file=sys.stderr, flush=True)
    return frames


def markdown(rows: list[dict], model: str, scene: str) -> str:
    n = rows[0]["scenes"] if rows else 0
    out = [
        f"Response probe of `{model}` on {scene} ({n} scene(s), rendered by the rig camera; single "
        "frames): slope of the estimate against the truth (1 = follows, 0 = ignores) +- its standard "
        "error, and the RMS error. In brackets: the navigation filter's measurement.",
        "",
        "| range (m) | lateral offsets (m) | lateral slope | lateral RMS error (cm) | attitude offsets (deg) "
        "| attitude slope | attitude RMS error (deg) | bearing slope | view slope |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        out.append(
            f"| {r['range_m']:.1f} | ±{r['lateral_offset_m']:.3f} | "
            f"{r['lateral_slope']:.2f} ± {r['lateral_slope_se']:.2f} ({r['meas_lateral_slope']:.2f}) | "
            f"{r['lateral_err_rms_m'] * 100:.1f} ({r['meas_lateral_err_rms_m'] * 100:.1f}) | ±{ATT_DEG:.0f} | "
            f"{r['attitude_slope']:.2f} ± {r['attitude_slope_se']:.2f} ({r['meas_attitude_slope']:.2f}) | "
            f"{r['attitude_err_rms_deg']:.2f} ({r['meas_attitude_err_rms_deg']:.2f}) | "
            f"{r['bearing_slope']:.2f} | {r['view_slope']:.2f} ({r['meas_view_slope']:.2f}) |"
        )
    unanswered = sum(r["frames"] - r["answered"] for r in rows)
    if unanswered:
        out += ["", f"{unanswered} frame(s) had no answer and are left out of the fits."]
    return "\n".join(out) + "\n"


def plot(path: Path, frames: list[dict], rows: list[dict], title: str) -> None:
    """Estimate against truth, per range: lateral (cm) and attitude (deg), both axes, each
    scene's mean removed, with the fitted slope and the identity."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ranges = [r["range_m"] for r in rows]
    fig, axes = plt.subplots(2, len(ranges), figsize=(4.2 * len(ranges), 8), squeeze=False)
    for j, (rng, row) in enumerate(zip(ranges, rows, strict=True)):
        for i, (kind, k, unit) in enumerate(
            (("lateral", 100.0, "cm"), ("attitude", float(np.degrees(1.0)), "deg"))
        ):
            ax = axes[i][j]
            sel = [f for f in frames if f["range_m"] == rng and f["kind"] == kind and f["answered"]]
            suffix = "_m" if kind == "lateral" else "_rad"
            for name, color in (("est", "C0"), ("meas", "C1")):
                t = np.array([f[f"{kind}_true{suffix}"] for f in sel], float)
                e = np.array([f[f"{kind}_{name}{suffix}"] for f in sel], float)
                sc = np.array([f["scene"] for f in sel])
                for s in np.unique(sc):
                    m = sc == s
                    e[m] -= e[m].mean(0) - t[m].mean(0)
                lab = "answer" if name == "est" else "filter measurement"
                slope = row[f"{'meas_' if name == 'meas' else ''}{kind}_slope"]
                ax.scatter(
                    t.ravel() * k,
                    e.ravel() * k,
                    s=8,
                    alpha=0.4,
                    color=color,
                    label=f"{lab} (slope {slope:.2f})",
                )
            lim = (LATERAL_FRACTION * rng * 100 if kind == "lateral" else ATT_DEG) * 1.3
            ax.plot([-lim, lim], [-lim, lim], "k--", lw=1, label="follows (slope 1)")
            ax.set_xlim(-lim, lim)
            ax.set_ylim(-lim, lim)
            ax.set_title(f"{rng:g} m: {kind}")
            ax.set_xlabel(f"truth ({unit})")
            ax.set_ylabel(f"estimate, scene mean removed ({unit})")
            ax.legend(fontsize=7, loc="upper left")
            ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from oibar_hil.rig.runner import REPO_ROOT

    ap = argparse.ArgumentParser(prog="python -m oibar_hil.rig.probe", description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument(
        "--scenes",
        "--scene",
        default="val",
        help="'val' (the 22 validation scenes, the default: choices are made there), or names: "
        "seq01 (a test scene: report, do not tune), va003, FILE:NAME, comma-separated",
    )
    ap.add_argument("--md", type=Path, default=None, help="also write the table here")
    ap.add_argument("--json", type=Path, default=None, help="the summary rows and every frame")
    ap.add_argument("--plot", type=Path, default=None, help="estimate against truth per range (PNG)")
    a = ap.parse_args(argv)
    try:
        scenes = scene_list(a.scenes, REPO_ROOT)
        frames = probe_scenes(a.model, [s for _, s in scenes], progress=len(scenes) > 1)
    except Exception as exc:
        from oibar.nav.pose import ModelFileError
        from oibar_hil.dataset import DatasetError

        if (
            isinstance(exc, ModelFileError | DatasetError | ValueError)
            or type(exc).__name__ == "RigCameraError"
        ):
            print(f"error: {exc}", file=sys.stderr)
            return 2
        raise
    rows = summarise(frames)
    label = "the validation scenes" if a.scenes == "val" else a.scenes
    text = markdown(rows, str(a.model), label)
    print(text)
    if a.md:
        a.md.parent.mkdir(parents=True, exist_ok=True)
        a.md.write_text(text)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(
            json.dumps({"model": str(a.model), "scenes": label, "rows": rows, "frames": frames}) + "\n"
        )
    if a.plot:
        plot(a.plot, frames, rows, f"{a.model.name} on {label}: does the estimate follow?")
    return 0


if __name__ == "__main__":
    sys.exit(main())
