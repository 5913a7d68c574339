"""Where the keypoint network puts each keypoint on a look, with the window placed by the truth:
per keypoint, how far its reading sits from the truth's projection, radially (outward from the
fixture's centre in the image, in crop pixels) and as a share of its distance from that centre.

Why: on the Mitsuba lab look (grey unpainted print, one spot lamp, black background) the range is
read 4-5.5 % short at every range beyond 3 m (issue 58). A network that reads every keypoint
outward by the same share reads the fixture larger, hence nearer; one whose search or PnP is at
fault does not. With the window on the truth the search is out of the question, so this says
what the network itself does on the look, keypoint by keypoint: what domain randomisation must
cover (docs/model_history.md, "The studies on other looks").

    python -m oibar_models.kp_offsets --sets val val_lab --stride 8 1
    python -m oibar_models.kp_offsets --by-look data/train_dr --stride 2   (randomised looks)

With --by-look, each sequence of a folder of randomised looks (make dataset-train-dr) is one row:
its lighting, backdrop and the rim's and plate's materials (oibar_hil.randomize) beside the rim's
and the inner keypoints' median shares, grouped by what the lab look combines (a lamp, a rim that
is not dark paint).

Exit status: 0 done; 2 bad arguments, a set not rendered or a model file that is not a keypoint
model.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from .config import REPO_ROOT
from .data import DatasetError, load_sequence
from .kp_evaluate import SETS
from .scenes import load_set

# A keypoint nearer the centre than this share of the farthest one has no radial direction to
# speak of (the drogue's centre and throat sit on the axis): its share is not reported.
MIN_RADIUS_FRAC = 0.2


def radial_offsets(uv_read_px: np.ndarray, uv_true_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K,) radial offset of each reading from the truth's projection (px, + outward from the
    truth's centroid) and (K,) the reading's distance from that centroid over the truth's, minus 1
    (NaN within MIN_RADIUS_FRAC of the farthest keypoint's distance, or where the reading is NaN)."""
    c = uv_true_px.mean(axis=0)
    out = uv_true_px - c
    r_true = np.linalg.norm(out, axis=1)
    unit = out / np.where(r_true > 0, r_true, 1.0)[:, None]
    radial = np.einsum("ij,ij->i", uv_read_px - uv_true_px, unit)
    rel = np.linalg.norm(uv_read_px - c, axis=1) / np.where(r_true > 0, r_true, np.nan) - 1.0
    rel[r_true < MIN_RADIUS_FRAC * r_true.max()] = np.nan
    return radial, rel


def read_offsets(reader, image: np.ndarray, R: np.ndarray, T: np.ndarray) -> dict[str, np.ndarray] | None:
    """One frame read in the window the truth (R, T) places (reader.window_for): radial offsets in
    crop px, the relative shares, presence; None where the truth places no window."""
    from oibar.nav.keypoints import project

    win = reader.window_for(R, T)
    if win is None:
        return None
    reading = reader.read_crop(image, win)
    radial, rel = radial_offsets(reading.uv_px, project(reader.K_frame, reader.points_m, R, T))
    return {"radial_crop_px": radial * win.scale, "rel": rel, "present": reading.present}


def frames(set_name: str, stride: int, range_m: tuple[float, float]) -> Iterable[tuple[Any, int]]:
    """(sequence, frame index) of every stride-th frame of the set whose camera range is inside
    range_m; raises DatasetError when the set is not rendered."""
    spec, root = SETS[set_name]
    for s in load_set(REPO_ROOT / spec):
        seq = load_sequence(REPO_ROOT / root / s.name)
        for k in range(0, len(seq), stride):
            if range_m[0] <= float(np.linalg.norm(seq.T_cam_target[k])) <= range_m[1]:
                yield seq, k


def study(reader, items: list[tuple[Any, int]], progress: bool, what: str) -> dict[str, np.ndarray]:
    """Each frame's offsets, stacked (frames, K); 'range_m' (frames,)."""
    from oibar.geometry.rotations import quat_to_matrix

    it: Iterable[tuple[Any, int]] = items
    if progress:
        from oibar.progress import progress_iter

        it = progress_iter(items, what, total=len(items), unit="frame", leave=False)
    rows: dict[str, list] = {"radial_crop_px": [], "rel": [], "present": [], "range_m": []}
    for seq, k in it:
        img = np.asarray(Image.open(seq.dir / seq.files[k]).convert("RGB"))
        T = np.asarray(seq.T_cam_target[k], float)
        got = read_offsets(reader, img, quat_to_matrix(seq.q_cam_target[k]), T)
        if got is None:
            continue
        for key, v in got.items():
            rows[key].append(v)
        rows["range_m"].append(float(np.linalg.norm(T)))
    return {k: np.asarray(v, float) for k, v in rows.items()}


def _median(x: np.ndarray) -> float:
    """The median of the finite values; NaN when there are none (a keypoint never read)."""
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else float("nan")


def summary(r: dict[str, np.ndarray], names: list[str]) -> list[dict[str, Any]]:
    """Per keypoint: medians over the frames of the radial offset, the share and the presence."""
    return [
        {
            "keypoint": name,
            "radial_crop_px_median": _median(r["radial_crop_px"][:, i]),
            "rel_pct_median": 100 * _median(r["rel"][:, i]),
            "present_median": _median(r["present"][:, i]),
        }
        for i, name in enumerate(names)
    ]


def markdown(per_set: dict[str, list[dict[str, Any]]], counts: dict[str, int]) -> str:
    sets = list(per_set)
    head = (
        "| keypoint | "
        + " | ".join(f"{s} ({counts[s]} frames): radial (crop px) / share" for s in sets)
        + " |"
    )
    lines = [head, "| --- |" + " ---: |" * len(sets)]
    for i, row in enumerate(per_set[sets[0]]):
        cells = []
        for s in sets:
            x = per_set[s][i]
            share = "-" if not np.isfinite(x["rel_pct_median"]) else f"{x['rel_pct_median']:+.1f} %"
            cells.append(f"{x['radial_crop_px_median']:+.2f} / {share}")
        lines.append(f"| {row['keypoint']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(path: Path, per_set: dict[str, list[dict[str, Any]]], counts: dict[str, int], title: str) -> None:
    """Bars per keypoint, one per set: the reading's share of its distance from the centre."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = list(per_set)
    names = [x["keypoint"] for x in per_set[sets[0]]]
    keep = [i for i in range(len(names)) if any(np.isfinite(per_set[s][i]["rel_pct_median"]) for s in sets)]
    y = np.arange(len(keep))
    h = 0.8 / len(sets)
    fig, ax = plt.subplots(figsize=(8, 0.32 * len(keep) + 1.8))
    for j, s in enumerate(sets):
        ax.barh(y + (j - (len(sets) - 1) / 2) * h, [per_set[s][i]["rel_pct_median"] for i in keep], h,
                label=f"{s} ({counts[s]} frames)")  # fmt: skip
    ax.axvline(0.0, c="k", lw=0.8)
    ax.set_yticks(y, [names[i] for i in keep], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("reading's distance from the fixture's centre against the truth's, median (%; + outward)")
    ax.grid(alpha=0.3, axis="x")
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# Groups of randomised looks, by what the lab look combines: lit by lamps (vs the Sun and the
# Earth), and a rim about as light as the plate (the lab's grey print: one grey for both) against
# one clearly darker (as built: albedo 0.11 against the plate's 0.73). Darker: by DARK_RIM_ALBEDO.
DARK_RIM_ALBEDO = 0.3
RIM = slice(0, 4)  # rim_* keypoints (the export's order, oibar.keypoint_names)
INNER = slice(4, 12)  # pin guides, couplings, connector corners


def look_rows(reader, root: Path, stride: int, range_m: tuple[float, float], progress: bool) -> list[dict]:
    """One row per randomised sequence under `root`: its look's factors and the medians of its
    rim's and inner keypoints' shares (%). Raises DatasetError for a folder without such."""
    rows = []
    dirs = sorted(d for d in root.iterdir() if (d / "manifest.json").is_file()) if root.is_dir() else []
    for d in dirs:
        manifest = json.loads((d / "manifest.json").read_text())
        look = manifest.get("config", {}).get("look")
        if not look:
            continue
        seq = load_sequence(d)
        items = [
            (seq, k)
            for k in range(0, len(seq), stride)
            if range_m[0] <= float(np.linalg.norm(seq.T_cam_target[k])) <= range_m[1]
        ]
        r = study(reader, items, progress, d.name)
        if not len(r["range_m"]):
            continue
        kinds = {name: m["kind"] for name, m in look["materials"]}
        contrast = _albedo("plate", dict(look["materials"])) - _albedo("rim", dict(look["materials"]))
        rows.append(
            {
                "sequence": d.name,
                "frames": len(r["range_m"]),
                "lighting": look["lighting"],
                "backdrop": look["backdrop"],
                "rim_kind": kinds.get("rim"),
                "plate_kind": kinds.get("plate"),
                "lamps": look["lighting"].startswith("lamp"),
                "rim_contrast": contrast,
                "dark_rim": contrast >= DARK_RIM_ALBEDO,
                "rim_pct": 100 * _median(r["rel"][:, RIM].ravel()),
                "inner_pct": 100 * _median(r["rel"][:, INNER].ravel()),
            }
        )
    if not rows:
        raise DatasetError(f"{root}: no rendered sequence with a randomised look (make dataset-train-dr)")
    return rows


@functools.lru_cache(maxsize=1)
def _as_built_albedo() -> dict[str, float]:
    from oibar_hil.meshes import berthing_fixture

    return {p.name: float(np.mean(p.rgb)) for p in berthing_fixture() if p.name}


def _albedo(part: str, materials: dict[str, dict]) -> float:
    """A part's mean diffuse albedo in a look (its own colour when drawn as built, meshes.py)."""
    m = materials.get(part)
    if m is None or m["kind"] == "as_built":
        return _as_built_albedo()[part]
    return float(np.mean(m["rgb"]))


def look_groups(rows: list[dict]) -> list[dict]:
    """(lamps, dark rim) groups: sequences, and the median and range of their inner keypoints'
    shares (the rim's share is where the rim's own edge is read; the inner keypoints say how the
    whole pattern is scaled)."""
    out = []
    for lamps in (False, True):
        for dark in (True, False):
            v = [r["inner_pct"] for r in rows if r["lamps"] == lamps and r["dark_rim"] == dark]
            w = [r["rim_pct"] for r in rows if r["lamps"] == lamps and r["dark_rim"] == dark]
            out.append(
                {
                    "light": "lamps" if lamps else "Sun / Earth",
                    "rim": "darker than the plate" if dark else "about as light as the plate",
                    "sequences": len(v),
                    "inner_pct_median": _median(np.asarray(v, float)),
                    "inner_pct_min": float(min(v)) if v else float("nan"),
                    "inner_pct_max": float(max(v)) if v else float("nan"),
                    "rim_pct_median": _median(np.asarray(w, float)),
                }
            )
    return out


def look_markdown(groups: list[dict]) -> str:
    lines = [
        "| light | rim | sequences | inner keypoints: share, median (range) | rim keypoints: share, median |",
        "| --- | --- | ---: | ---: | ---: |",
    ]
    for g in groups:
        lines.append(
            f"| {g['light']} | {g['rim']} | {g['sequences']} | {g['inner_pct_median']:+.1f} % "
            f"({g['inner_pct_min']:+.1f} to {g['inner_pct_max']:+.1f}) | {g['rim_pct_median']:+.1f} % |"
        )
    return "\n".join(lines) + "\n"


def look_plot(path: Path, rows: list[dict], title: str, marks: dict[str, float] | None = None) -> None:
    """Each sequence a dot at its inner keypoints' share, in its (lamps, dark rim) group; `marks`:
    other sets' shares drawn as lines (the lab look's, our renderer's)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = [(False, True), (False, False), (True, True), (True, False)]
    labels = [f"{light},\nrim {rim}" for light in ("Sun / Earth", "lamps") for rim in ("darker", "as light")]
    fig, ax = plt.subplots(figsize=(7, 3.6))
    rng = np.random.default_rng(0)
    for i, (lamps, dark) in enumerate(groups):
        v = np.array([r["inner_pct"] for r in rows if r["lamps"] == lamps and r["dark_rim"] == dark])
        ax.scatter(i + rng.uniform(-0.12, 0.12, len(v)), v, s=18, alpha=0.7)
        if len(v):
            ax.hlines(np.median(v), i - 0.3, i + 0.3, colors="k", lw=1.5)
    for k, (name, y) in enumerate((marks or {}).items()):
        ax.axhline(y, ls="--", lw=0.9, c=f"C{k + 4}", label=name)
    ax.axhline(0.0, c="k", lw=0.6)
    # a sequence far off (one whose rim is not read at all) would squash the rest: clip, and say so
    v_all = np.array([r["inner_pct"] for r in rows] + list((marks or {}).values()), float)
    v_all = v_all[np.isfinite(v_all)]
    lo = min(-3.0, float(np.percentile(v_all, 2)) - 1) if v_all.size else -3.0
    hi = max(6.0, float(v_all.max()) + 1) if v_all.size else 6.0
    ax.set_ylim(lo, hi)
    n_out = int(np.sum(v_all < lo))
    if n_out:
        ax.annotate(f"{n_out} below, not shown", (0.01, 0.02), xycoords="axes fraction", fontsize=7)
    ax.set_xticks(range(4), labels, fontsize=8)
    ax.set_ylabel("inner keypoints' distance from centre\nagainst the truth's, median (%)", fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    if marks:
        ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from oibar.nav.pose import ModelFileError

    ap = argparse.ArgumentParser(
        prog="python -m oibar_models.kp_offsets", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--model", type=Path, default=REPO_ROOT / "models" / "oibarnet.onnx")
    ap.add_argument("--sets", nargs="+", default=["val", "val_lab"], choices=sorted(SETS))
    ap.add_argument(
        "--stride", type=int, nargs="+", default=[1], help="every n-th frame, one per set or one for all"
    )
    ap.add_argument("--min-range-m", type=float, default=3.0)
    ap.add_argument("--max-range-m", type=float, default=10.5)
    ap.add_argument("--by-look", type=Path, metavar="DIR", help="a folder of randomised looks (one row each)")
    ap.add_argument("--marks", nargs="*", default=[], choices=sorted(SETS),
                    help="with --by-look: sets whose inner keypoints' share is drawn as a line")  # fmt: skip
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "runs" / "kp_offsets")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    if len(a.stride) not in (1, len(a.sets)) or min(a.stride) < 1:
        ap.error("--stride: one value >= 1, or one per set")
    if not a.min_range_m < a.max_range_m:
        ap.error("--min-range-m must be below --max-range-m")
    strides = a.stride * len(a.sets) if len(a.stride) == 1 else a.stride
    range_m = (a.min_range_m, a.max_range_m)
    if a.by_look is not None:
        return main_by_look(a, range_m)
    try:
        reader = _reader(a.model)
        names = list(reader.meta.get("keypoint_names") or [f"kp{i}" for i in range(len(reader.points_m))])
        items = {
            s: list(frames(s, n, (a.min_range_m, a.max_range_m)))
            for s, n in zip(a.sets, strides, strict=True)
        }
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ModelFileError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    empty = [s for s, v in items.items() if not v]
    if empty:
        print(
            f"error: no frames between {a.min_range_m:g} and {a.max_range_m:g} m in {empty}", file=sys.stderr
        )
        return 2
    per_set, counts = {}, {}
    for s, v in items.items():
        r = study(reader, v, not a.no_progress, s)
        per_set[s], counts[s] = summary(r, names), len(r["range_m"])
    a.out.mkdir(parents=True, exist_ok=True)
    title = (
        f"{a.model.name}: keypoints read in the window the truth places, "
        f"{a.min_range_m:g}-{a.max_range_m:g} m"
    )
    table = markdown(per_set, counts)
    (a.out / "offsets.md").write_text(f"{title}\n\n{table}")
    (a.out / "offsets.json").write_text(json.dumps({"counts": counts, "per_set": per_set}, indent=1) + "\n")
    plot(a.out / "offsets.png", per_set, counts, title)
    for s, rows in per_set.items():
        _track(a, f"offsets {s}", {f"rel_pct_{x['keypoint']}": x["rel_pct_median"] for x in rows},
               {"set": s, "frames": counts[s]})  # fmt: skip
    print(
        f"{title}\n\n{table}written: {a.out / 'offsets.md'}, {a.out / 'offsets.json'}, {a.out / 'offsets.png'}"
    )
    return 0


def main_by_look(a: argparse.Namespace, range_m: tuple[float, float]) -> int:
    from oibar.nav.pose import ModelFileError

    try:
        reader = _reader(a.model)
        rows = look_rows(reader, a.by_look, a.stride[0], range_m, not a.no_progress)
        marks = {}
        for m in a.marks:
            r = study(reader, list(frames(m, a.stride[0], range_m)), not a.no_progress, m)
            marks[m] = 100 * _median(r["rel"][:, INNER].ravel()) if len(r["range_m"]) else float("nan")
    except (DatasetError, ModelFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    groups = look_groups(rows)
    a.out.mkdir(parents=True, exist_ok=True)
    title = (
        f"{a.model.name} on the randomised looks of {a.by_look.name} ({len(rows)} sequences, "
        f"{range_m[0]:g}-{range_m[1]:g} m, window on the truth)"
    )
    table = look_markdown(groups) + "".join(
        f"\n{m}: inner keypoints' share {v:+.1f} %\n" for m, v in marks.items()
    )
    (a.out / "by_look.md").write_text(f"{title}\n\n{table}")
    (a.out / "by_look.json").write_text(
        json.dumps({"groups": groups, "sequences": rows, "marks": marks}, indent=1) + "\n"
    )
    look_plot(a.out / "by_look.png", rows, title, marks)
    flat = {}
    for g in groups:
        light = "lamps" if g["light"] == "lamps" else "sun"
        rim = "dark" if g["rim"].startswith("darker") else "light"
        flat[f"inner_pct_{light}_{rim}_rim"] = g["inner_pct_median"]
    _track(a, f"by_look {a.by_look.name}", {**flat, **{f"inner_pct_{m}": v for m, v in marks.items()}},
           {"by_look": str(a.by_look), "stride": a.stride[0], "sequences": len(rows)})  # fmt: skip
    print(
        f"{title}\n\n{table}written: {a.out / 'by_look.md'}, {a.out / 'by_look.json'}, {a.out / 'by_look.png'}"
    )
    return 0


def _track(a: argparse.Namespace, label: str, metrics: dict[str, float], opts: dict[str, Any]) -> None:
    """One run in the experiment tracker (experiment "kp_offsets"); a store that cannot be
    written costs a line, not the study."""
    from types import SimpleNamespace

    from . import tracking

    try:
        tracking.log_evaluation(
            SimpleNamespace(name="kp_offsets", path=a.out, seed=0), label, a.model, a.out, metrics,
            {"min_range_m": a.min_range_m, "max_range_m": a.max_range_m, **opts}, kind="study",
        )  # fmt: skip
    except tracking.TrackingError as exc:
        print(f"kp_offsets: not tracked ({exc})", file=sys.stderr)


def _reader(model: Path):
    from oibar.nav.pose import ModelFileError, PoseEstimator

    reader = getattr(PoseEstimator(model), "reader", None)
    if reader is None:
        raise ModelFileError(f"{model}: not a keypoint model")
    return reader


if __name__ == "__main__":
    sys.exit(main())
