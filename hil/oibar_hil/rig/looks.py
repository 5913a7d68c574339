"""Closed loop over many looks: the demo's mission on validation scenes' looks, several runs per
look, one or more models side by side, with error bars.

    python -m oibar_hil.rig.looks --model models/oibarnet.onnx --model runs/cand/oibarnet.onnx \\
        [--looks va000,va002,...] [--starts 10,9] [--seeds 1,2] [--turns 2:-1.5,-2:1.5] \\
        [--jobs 2] [--out build/looks] [--json FILE] [--plot FILE.png]

Why: one loop per look varies more from look to look, and from one start to the next on the
same look, than two candidate models differ (validation, 2026-11-24: va011's look gave 3.7 cm
from 10 m and 5.3 cm from 9 m for the same model). A choice between models needs several runs
per look and the difference measured *paired* (the same look, start, seed and turn for both).

Each run is ``python -m oibar_hil.rig.cli --nav cnn --scene SPEC:LOOK demo`` with the start range,
seed and start turn (pitch:yaw, degrees) given; its metrics JSON under
``--out/code-<hash of the host's, rig's and firmware's sources>/<model>-<hash>/`` is the cache: a run already
there is not run again, so an interrupted study resumes where it stopped and a new
model is compared against the old ones' runs for free. ``--model truth`` flies ground-truth
navigation (the floor: what the rig adds without the camera).

Per model: the lateral error p95 below 5 m (the demo's navigation figure; target 5 cm) and the
capture's distance off the axis, mean +- standard error over all runs, the worst run, the share
of runs within 5 cm; against the first model, the mean paired difference +- its standard error
and how many runs each won. Exit status 1 when a run failed to complete its mission.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import subprocess
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from oibar.nav.pose import ModelFileError, read_metadata
from oibar.progress import Progress
from oibar_hil.dataset import DatasetError, load_spec_file
from oibar_hil.rig.runner import REPO_ROOT

DEFAULT_SPEC = "models/scenes/val.json"
# The ten validation looks the 2026-11-24 choices were judged on (the first four chose that
# day's estimator; the other six were fresh then).
DEFAULT_LOOKS = ("va003", "va005", "va008", "va014", "va000", "va002", "va004", "va007", "va010", "va011")
# The other twelve: no flight-code choice was made on them up to 2026-11-25. The filter's settings
# were tuned with 0.8.1 on the ten above and hold an edge there (2.9 cm against 5.4 here), so a
# choice is confirmed on these (`--looks held-out`).
HELD_OUT_LOOKS = (
    "va001", "va006", "va009", "va012", "va013", "va015", "va016", "va017", "va018", "va019", "va020", "va021",
)  # fmt: skip
LOOK_SETS = {"default": DEFAULT_LOOKS, "held-out": HELD_OUT_LOOKS}
LATERAL_TARGET_M = 0.05
TRUTH = "truth"


@dataclass(frozen=True)
class RunKey:
    model: str  # the model's tag (model_tag)
    look: str
    start_range_m: float
    seed: int
    turn_deg: tuple[float, float]  # the chaser's start misalignment, pitch / yaw

    def name(self) -> str:
        p, y = self.turn_deg
        return f"{self.look}_r{self.start_range_m:g}_s{self.seed}_t{p:g}_{y:g}"


@dataclass
class LoopResult:
    key: RunKey
    completed: bool
    lateral_p95_below_5m_m: float  # NaN when the run never came below 5 m
    misalign_p95_below_5m_deg: float
    capture_lateral_m: float  # NaN without a capture
    outcome: str


def model_tag(path: str) -> str:
    """A model's folder name under --out: its file stem and the start of its content hash (two
    exports called oibarnet.onnx never share a cache); the hash covers the far network beside it
    too, when the file names one (``oibar.far_network``), since that network flies with it."""
    if path == TRUTH:
        return TRUTH
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"model {path}: no such file")
    digest = hashlib.sha256(p.read_bytes())
    try:
        far = read_metadata(p).get("far_network")
    except ModelFileError:  # not a model: its run reports that; the tag is its bytes'
        far = None
    if isinstance(far, dict) and (p.parent / str(far.get("file", ""))).is_file():
        digest.update((p.parent / str(far["file"])).read_bytes())
    return f"{p.stem}-{digest.hexdigest()[:10]}"


def code_tag(root: Path = REPO_ROOT) -> str:
    """The flight code's version for the cache: a hash of the host's and the rig's Python
    sources (this study's own module and the probe excluded), the firmware's sources (the
    simulated MCU every run flies is built from them) and the link's protocol. A run is
    deterministic for a model file *and* this code: a change to the filter's defaults, or to
    the latch's timeouts, flies every run again."""
    h = hashlib.sha256()
    files: list[Path] = []
    for base in (root / "host" / "oibar", root / "hil" / "oibar_hil"):
        files += [
            f
            for f in sorted(base.rglob("*.py"))
            if not (f.parent.name == "rig" and f.name in ("looks.py", "probe.py"))
        ]
    for pattern in ("*.c", "*.h", "CMakeLists.txt", "*.cmake"):
        files += sorted((root / "firmware").rglob(pattern))
    files += sorted((root / "proto").glob("*"))
    for f in files:
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:10]


def parse_turns(text: str) -> list[tuple[float, float]]:
    """'2:-1.5,-2:1.5' -> [(2.0, -1.5), (-2.0, 1.5)]."""
    out = []
    for part in text.split(","):
        try:
            p, y = part.split(":")
            out.append((float(p), float(y)))
        except ValueError as exc:
            raise ValueError(f"bad turn {part!r}: give PITCH:YAW in degrees, e.g. 2:-1.5") from exc
    return out


def parse_floats(text: str, what: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",")]
    except ValueError as exc:
        raise ValueError(f"bad {what} {text!r}: give comma-separated numbers") from exc


def result_from_json(key: RunKey, doc: Any) -> LoopResult:
    """A run's result from the rig's --json file (a list with one scenario)."""
    r = doc[0]
    m = r["metrics"]
    cap = r.get("capture") or {}
    return LoopResult(
        key=key,
        completed=r.get("outcome") == "completed",
        lateral_p95_below_5m_m=float(m.get("nav_lateral_err_m_p95_below_5m", math.nan)),
        misalign_p95_below_5m_deg=float(m.get("nav_misalign_err_deg_p95_below_5m", math.nan)),
        capture_lateral_m=float(cap.get("lateral_m", math.nan)),
        outcome=str(r.get("outcome")),
    )


def rig_command(key: RunKey, model_path: str, spec: str, run_dir: Path, json_path: Path) -> list[str]:
    cmd = [sys.executable, "-m", "oibar_hil.rig.cli", "--no-progress", "--out", str(run_dir)]
    if model_path == TRUTH:
        cmd += ["--nav", "truth"]
    else:
        cmd += ["--nav", "cnn", "--model", model_path, "--scene", f"{spec}:{key.look}"]
    cmd += ["--start-range-m", f"{key.start_range_m:g}", "--seed", str(key.seed)]
    cmd += ["--misalignment-deg", f"{key.turn_deg[0]:g}", f"{key.turn_deg[1]:g}"]
    return cmd + ["--json", str(json_path), "demo"]


def run_one(key: RunKey, model_path: str, spec: str, out: Path) -> LoopResult:
    """Run (or read back) one loop. The JSON is written by the rig only when the run finishes, so
    an interrupted run leaves nothing behind that looks done."""
    run_dir = out / key.model / key.name()
    json_path = run_dir / "result.json"
    if not json_path.is_file():
        run_dir.mkdir(parents=True, exist_ok=True)
        tmp = run_dir / "result.json.part"
        cmd = rig_command(key, model_path, spec, run_dir, tmp)
        with open(run_dir / "rig.log", "w") as log:
            rc = subprocess.run(cmd, cwd=REPO_ROOT, stdout=log, stderr=subprocess.STDOUT).returncode
        if not tmp.is_file():
            raise RuntimeError(
                f"{key.model} {key.name()}: the rig exited {rc} without results, see {run_dir / 'rig.log'}"
            )
        os.replace(tmp, json_path)
    return result_from_json(key, json.loads(json_path.read_text()))


def mean_se(xs: Sequence[float]) -> tuple[float, float]:
    """Mean and standard error of the finite values (NaN, NaN without any; SE NaN for one)."""
    v = [x for x in xs if math.isfinite(x)]
    if not v:
        return math.nan, math.nan
    m = sum(v) / len(v)
    if len(v) < 2:
        return m, math.nan
    var = sum((x - m) ** 2 for x in v) / (len(v) - 1)
    return m, math.sqrt(var / len(v))


def _cond(key: RunKey) -> tuple[str, float, int, tuple[float, float]]:
    return (key.look, key.start_range_m, key.seed, key.turn_deg)


def summarise(results: Sequence[LoopResult], models: Sequence[str]) -> dict[str, Any]:
    """Per model: runs, mean +- SE, worst and share within target of the lateral p95 below 5 m,
    capture off the axis; against the first model: paired differences over the conditions both
    ran (a negative difference: the model is better)."""
    by_model: dict[str, dict[tuple, LoopResult]] = {m: {} for m in models}
    for r in results:
        by_model[r.key.model][_cond(r.key)] = r
    out: dict[str, Any] = {"models": {}}
    ref = models[0]
    for m in models:
        rs = list(by_model[m].values())
        lat = [r.lateral_p95_below_5m_m for r in rs]
        cap = [r.capture_lateral_m for r in rs]
        lat_ok = [x for x in lat if math.isfinite(x)]
        mu, se = mean_se(lat)
        cmu, cse = mean_se(cap)
        row: dict[str, Any] = {
            "runs": len(rs),
            "completed": sum(r.completed for r in rs),
            "lateral_p95_below_5m_cm_mean": mu * 100,
            "lateral_p95_below_5m_cm_se": se * 100,
            "lateral_p95_below_5m_cm_worst": max(lat_ok) * 100 if lat_ok else math.nan,
            "within_5cm_share": sum(x <= LATERAL_TARGET_M for x in lat_ok) / len(lat_ok)
            if lat_ok
            else math.nan,
            "capture_lateral_mm_mean": cmu * 1000,
            "capture_lateral_mm_se": cse * 1000,
            "capture_lateral_mm_worst": max((x for x in cap if math.isfinite(x)), default=math.nan) * 1000,
        }
        if m != ref:
            common = sorted(set(by_model[m]) & set(by_model[ref]), key=str)
            d = [
                by_model[m][c].lateral_p95_below_5m_m - by_model[ref][c].lateral_p95_below_5m_m
                for c in common
            ]
            d = [x for x in d if math.isfinite(x)]
            dmu, dse = mean_se(d)
            row["paired_vs_first"] = {
                "runs": len(d),
                "lateral_p95_diff_cm_mean": dmu * 100,
                "lateral_p95_diff_cm_se": dse * 100,
                "better": sum(x < 0 for x in d),
                "worse": sum(x > 0 for x in d),
            }
        out["models"][m] = row
    return out


def _fmt_pm(mu: float, se: float) -> str:
    return f"{mu:.2f}" + (f" +- {se:.2f}" if math.isfinite(se) else "")


def print_table(summary: dict[str, Any], labels: dict[str, str]) -> None:
    head = (
        f"{'model':<34} {'runs':>4} {'lateral p95 <5 m (cm)':>22} {'worst':>6} {'<=5cm':>6} "
        f"{'capture (mm)':>14}  paired vs first (cm)"
    )
    print(head)
    print("-" * len(head))
    for m, row in summary["models"].items():
        pv = row.get("paired_vs_first")
        paired = (
            f"{_fmt_pm(pv['lateral_p95_diff_cm_mean'], pv['lateral_p95_diff_cm_se'])} "
            f"({pv['better']} better, {pv['worse']} worse of {pv['runs']})"
            if pv
            else "-"
        )
        print(
            f"{labels.get(m, m):<34} {row['runs']:>4} "
            f"{_fmt_pm(row['lateral_p95_below_5m_cm_mean'], row['lateral_p95_below_5m_cm_se']):>22} "
            f"{row['lateral_p95_below_5m_cm_worst']:6.2f} {row['within_5cm_share'] * 100:5.0f}% "
            f"{_fmt_pm(row['capture_lateral_mm_mean'], row['capture_lateral_mm_se']):>14}  {paired}"
        )


def plot(results: Sequence[LoopResult], models: Sequence[str], labels: dict[str, str], path: Path) -> None:
    """Per look, every run of every model as a dot, each model's mean over the look as a bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    looks = list(dict.fromkeys(r.key.look for r in results))
    fig, ax = plt.subplots(figsize=(max(6.0, 1.1 * len(looks) + 2), 4.8))
    w = 0.8 / max(1, len(models))
    for i, m in enumerate(models):
        off = (i - (len(models) - 1) / 2) * w
        means = []
        for j, lk in enumerate(looks):
            v = [
                r.lateral_p95_below_5m_m * 100
                for r in results
                if r.key.model == m and r.key.look == lk and math.isfinite(r.lateral_p95_below_5m_m)
            ]
            means.append(sum(v) / len(v) if v else math.nan)
            ax.plot([j + off] * len(v), v, "o", ms=3.5, color=f"C{i}", alpha=0.8)
        ax.bar(
            [j + off for j in range(len(looks))], means, w, color=f"C{i}", alpha=0.35, label=labels.get(m, m)
        )
    ax.axhline(LATERAL_TARGET_M * 100, color="k", ls=":", lw=1, label="target 5 cm")
    ax.set_xticks(range(len(looks)))
    ax.set_xticklabels(looks)
    ax.set_ylabel("lateral error p95 below 5 m (cm)")
    ax.set_title("closed loop on validation looks: runs (dots) and their mean (bars)")
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=min(4, len(models) + 1))
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_study(
    keys: Sequence[RunKey],
    paths: dict[str, str],
    spec: str,
    out: Path,
    jobs: int,
    runner: Callable[[RunKey, str, str, Path], LoopResult] = run_one,
    progress: bool = True,
) -> list[LoopResult]:
    """Every key, `jobs` at a time (each run is its own process: the rig, the simulated MCU and
    the navigator), in order of the keys; a run that errors is reported and the rest go on."""
    results: dict[RunKey, LoopResult] = {}
    errors: list[str] = []
    bar = Progress("closed loops", total=len(keys), unit="run") if progress else None
    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        futs = {pool.submit(runner, k, paths[k.model], spec, out): k for k in keys}
        for f in as_completed(futs):
            k = futs[f]
            try:
                results[k] = f.result()
            except Exception as exc:  # one broken run does not lose the others
                errors.append(f"{k.model} {k.name()}: {exc}")
            if bar:
                bar.update(1)
    if bar:
        bar.close()
    for e in errors:
        print(f"error: {e}", file=sys.stderr)
    return [results[k] for k in keys if k in results]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_hil.rig.looks", description=__doc__.splitlines()[0])
    ap.add_argument(
        "--model",
        action="append",
        required=True,
        help="an ONNX model, or 'truth' (repeatable; the first is the reference)",
    )
    ap.add_argument(
        "--label", action="append", default=None, help="a name per --model for the table and plot"
    )
    ap.add_argument("--spec", default=DEFAULT_SPEC, help="scene-set file whose scenes' looks are flown")
    ap.add_argument(
        "--looks",
        default="default",
        help="comma-separated scene names, or 'default' (the ten the flight code was chosen on) or "
        "'held-out' (the twelve it was not)",
    )
    ap.add_argument("--starts", default="10", help="start ranges, metres, comma-separated")
    ap.add_argument("--seeds", default="1", help="scenario seeds, comma-separated")
    ap.add_argument("--turns", default="2:-1.5", help="start turns PITCH:YAW (deg), comma-separated")
    ap.add_argument("--jobs", type=int, default=1, help="runs at once (each takes about one core)")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "build" / "looks", help="run cache folder")
    ap.add_argument("--json", type=Path, default=None, help="write every run and the summary here")
    ap.add_argument("--plot", type=Path, default=None, help="draw the runs per look (PNG)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    try:
        starts = parse_floats(args.starts, "start ranges")
        seeds = [int(s) for s in parse_floats(args.seeds, "seeds")]
        turns = parse_turns(args.turns)
        looks = [lk for x in args.looks.split(",") if x for lk in LOOK_SETS.get(x, (x,))]
        known = {s.name for s in load_spec_file(REPO_ROOT / args.spec)}
        unknown = [lk for lk in looks if lk not in known]
        if unknown:
            raise ValueError(f"looks {unknown} are not scenes of {args.spec}")
        tags = [model_tag(m) for m in args.model]
    except (ValueError, FileNotFoundError, DatasetError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.label and len(args.label) != len(args.model):
        print("error: give one --label per --model", file=sys.stderr)
        return 2
    labels = dict(zip(tags, args.label or args.model, strict=True))
    paths = dict(zip(tags, args.model, strict=True))
    # one condition over every look before the next: a study stopped early is still balanced
    keys = [
        RunKey(t, lk, r, s, tn) for s in seeds for tn in turns for r in starts for lk in looks for t in tags
    ]
    # runs are cached per flight-code version: another filter default flies everything again
    flight_code = code_tag()
    out = args.out / f"code-{flight_code}"
    results = run_study(keys, paths, args.spec, out, args.jobs, progress=not args.no_progress)
    summary = summarise(results, tags)
    print_table(summary, labels)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        doc = {
            "code_tag": flight_code,  # what the runs were flown under (a rebase checks it)
            "looks": looks,
            "starts_m": starts,
            "seeds": seeds,
            "turns_deg": turns,
            "labels": labels,
            "summary": summary,
            "runs": [asdict(r) for r in results],
        }
        args.json.write_text(json.dumps(doc, indent=1) + "\n")
    if args.plot:
        plot(results, tags, labels, args.plot)
    return 0 if len(results) == len(keys) and all(r.completed for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
