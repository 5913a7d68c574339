"""Two flights of one mission side by side: where the chaser truly was, and what navigation thought.

Reads the rig report's ``nav_cycles.csv`` (oibar_hil.rig.report, one row per guidance cycle) of
each flight, e.g. a campaign mission replayed by two versions of the code, and draws against the
true range: the chaser's true distance from the docking axis, the navigation's lateral error, and
the camera's attitude error (with the vehicle's attitude check's verdict where the flight had one).
It prints, per range band, the largest true off-axis distance and the p95 lateral error.

    python -m oibar_hil.rig.compare BEFORE/nav_cycles.csv AFTER/nav_cycles.csv \\
        --labels "c37897c" "attitude check" --title "cnn_300 mission 71" --out compare.png
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

BANDS_M = ((8.0, 11.0), (6.0, 8.0), (4.0, 6.0), (2.0, 4.0), (0.5, 2.0))


def load(path: Path) -> dict[str, np.ndarray]:
    """The columns of a nav_cycles.csv as float arrays (an empty cell is NaN, a bool is 0/1)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        raise ValueError(f"{path}: no cycles")

    def num(v: str | None) -> float:
        if v in (None, ""):
            return float("nan")
        if v in ("True", "False"):
            return float(v == "True")
        try:
            return float(v)
        except ValueError:
            return float("nan")

    cols = {k: np.array([num(r.get(k)) for r in rows]) for k in rows[0]}
    for need in ("range_true_m", "true_x_m", "true_y_m", "lateral_err_m"):
        if need not in cols:
            raise ValueError(f"{path}: no column {need!r} (not a rig report's nav_cycles.csv)")
    cols["off_axis_true_m"] = np.hypot(cols["true_x_m"], cols["true_y_m"])
    if "ans_err_att_x_deg" in cols:
        cols["att_err_deg"] = np.hypot(cols["ans_err_att_x_deg"], cols["ans_err_att_y_deg"])
    return cols


def band_table(cols: dict[str, np.ndarray]) -> list[dict[str, float]]:
    """Per range band: cycles, the largest true off-axis distance, the p95 lateral error."""
    out = []
    for lo, hi in BANDS_M:
        m = (cols["range_true_m"] >= lo) & (cols["range_true_m"] < hi)
        lat = cols["lateral_err_m"][m]
        lat = lat[np.isfinite(lat)]
        out.append(
            {
                "from_m": lo,
                "to_m": hi,
                "cycles": int(m.sum()),
                "off_axis_true_m_max": float(np.nanmax(cols["off_axis_true_m"][m]))
                if m.any()
                else float("nan"),
                "lateral_err_m_p95": float(np.percentile(lat, 95)) if lat.size else float("nan"),
            }
        )
    return out


def plot(runs: list[tuple[str, dict[str, np.ndarray]]], title: str, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(3, 1, figsize=(9, 8.5), sharex=True)
    for (label, c), color in zip(runs, ("tab:red", "tab:blue", "tab:green"), strict=False):
        r = c["range_true_m"]
        axs[0].plot(r, c["off_axis_true_m"], color=color, lw=1.2, label=label)
        axs[1].plot(r, c["lateral_err_m"], color=color, lw=0.8, label=label)
        if "att_err_deg" in c:
            axs[2].plot(r, c["att_err_deg"], ".", color=color, ms=2, label=f"{label}: camera's answer")
        if "att_replaced" in c:
            rep = c["att_replaced"] == 1
            axs[2].plot(
                r[rep], np.zeros(rep.sum()), "|", color="k", ms=8, label="fused on the vehicle's attitude"
            )
    axs[0].set_ylabel("true distance from\nthe docking axis [m]")
    axs[1].set_ylabel("navigation's lateral\nerror [m]")
    axs[2].set_ylabel("camera's tilt\nerror [deg]")
    axs[2].set_xlabel("true range [m] (the approach runs right to left)")
    axs[2].invert_xaxis()
    for ax in axs:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axs[0].set_title(title)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_hil.rig.compare", description=__doc__.split("\n\n")[0])
    ap.add_argument("csv", nargs="+", type=Path, help="nav_cycles.csv of each flight (1-3)")
    ap.add_argument(
        "--labels", nargs="+", default=None, help="one label per flight (default: the folder names)"
    )
    ap.add_argument("--title", default="navigation, flight against flight")
    ap.add_argument("--out", type=Path, default=Path("compare.png"))
    args = ap.parse_args(argv)
    if not 1 <= len(args.csv) <= 3:
        ap.error("give 1 to 3 nav_cycles.csv files")
    labels = args.labels or [p.parent.name for p in args.csv]
    if len(labels) != len(args.csv):
        ap.error(f"{len(args.csv)} files but {len(labels)} labels")
    try:
        runs = [(lab, load(p)) for lab, p in zip(labels, args.csv, strict=True)]
    except (OSError, ValueError) as exc:
        print(f"compare: error: {exc}", file=sys.stderr)
        return 2
    for lab, c in runs:
        print(f"{lab}:")
        for b in band_table(c):
            print(
                f"  {b['from_m']:4.1f}-{b['to_m']:4.1f} m  {b['cycles']:4d} cycles  "
                f"off the axis (true) max {b['off_axis_true_m_max']:.2f} m  "
                f"lateral error p95 {b['lateral_err_m_p95']:.2f} m"
            )
    plot(runs, args.title, args.out)
    print(f"figure: {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
