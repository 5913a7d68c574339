"""The campaign report (report.md and figures/ in the campaign folder).

0. the code that flew the campaign (its fingerprint, git commit), any change allowed on a
   resume and any workers' other code kept (``--allow-code-change``), with the missions each
   code version flew;
1. the success rate with its Clopper-Pearson interval and one-sided lower bound: all missions,
   fault-free ones (the docking success rate) and faulted ones (ended as the fault matrix
   expects), and the outcomes;
2. failure drivers: every dispersed input, failed against passed missions (Mann-Whitney U:
   does the input sit elsewhere in the missions that failed?), and the failure rate per fault
   type, phase and approach port; outcome drivers, which a campaign without failures still
   has: the inputs that move each contact outcome and the navigation error most (rank
   correlation);
3. figures: each dispersed input's histogram split by success; each contact and load outcome,
   and the navigation's lateral error, against each dispersed input; the outcome distributions
   against their limits;
4. the worst missions (failures first, then the smallest margin to a limit), each with the one
   command that flies it again;
5. the dispersion model itself and what the rig cannot apply yet.
"""

from __future__ import annotations

import json
import math
import shlex
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from oibar.nav.guidance import CORRIDOR_SLOPE
from oibar_hil.campaign.dispersion import INPUTS, NOT_APPLIED, CampaignConfig
from oibar_hil.campaign.stats import Rate, rate
from oibar_hil.rig.runner import NEAR_RANGE_M

# The limits each contact/load outcome is judged against (paper; the drogue's mouth radius).
LIMITS = {
    "contact_lateral_m": (0.10, "funnel mouth radius"),
    "contact_closing_speed_mps": (0.050, "capture speed limit"),
    "contact_misalignment_deg": (10.0, "capture misalignment limit"),
    "peak_force_n": (60.0, "hard-docking force limit"),
    "peak_force_soft_n": (30.0, "soft-docking force limit"),
}
# Navigation has no limit of its own: its error is drawn against the funnel mouth it must find.
# The chaser's true path inside 5 m is drawn against guidance's approach corridor there.
NAV_REFERENCE = {
    "nav_lateral_err_m_p95_below_5m": (0.10, "funnel mouth radius"),
    "approach_off_axis_m_max_below_5m": (CORRIDOR_SLOPE * NEAR_RANGE_M, "guidance's corridor at 5 m"),
}
OUTCOME_PLOTS = (
    "contact_lateral_m",
    "contact_closing_speed_mps",
    "peak_force_n",
    "nav_lateral_err_m_p95_below_5m",
    "approach_off_axis_m_max_below_5m",
)
WORST_SHOWN = 10


def margin_score(row: dict[str, Any]) -> float:
    """Largest fraction of a limit reached (1 = at the limit); a failed mission scores 10 + that."""
    fracs = [0.0]
    for col, (limit, _) in LIMITS.items():
        v = row.get(col)
        if v is not None and math.isfinite(v):
            fracs.append(abs(v) / limit)
    s = max(fracs)
    return s + 10.0 if not row["success"] else s


def replay_command(folder: Path, index: int) -> str:
    return f"python -m oibar_hil.campaign replay {shlex.quote(str(folder))} {index}"


def _rates(rows: list[dict[str, Any]]) -> dict[str, Rate]:
    clean = [r for r in rows if not r["fault"]]
    faulted = [r for r in rows if r["fault"]]
    return {
        "all missions": rate(sum(r["success"] for r in rows), len(rows)),
        "fault-free (docking success)": rate(sum(r["success"] for r in clean), len(clean)),
        "with a fault (safe outcome as the matrix expects)": rate(
            sum(r["success"] for r in faulted), len(faulted)
        ),
    }


def drivers(rows: list[dict[str, Any]], cfg: CampaignConfig) -> list[dict[str, Any]]:
    """Per dispersed input: medians in failed and passed missions, Mann-Whitney U p-value."""
    from scipy.stats import mannwhitneyu

    out = []
    fail = [r for r in rows if not r["success"]]
    ok = [r for r in rows if r["success"]]
    for name in dispersed_inputs(cfg):
        a, b = input_values(fail, name), input_values(ok, name)
        p = float("nan")
        if len(a) >= 1 and len(b) >= 1 and np.ptp(np.concatenate([a, b])) > 0:
            p = float(mannwhitneyu(a, b, alternative="two-sided").pvalue)
        out.append(
            {
                "input": name,
                "unit": input_unit(name),
                "median_failed": float(np.median(a)) if len(a) else float("nan"),
                "median_passed": float(np.median(b)) if len(b) else float("nan"),
                "p": p,
            }
        )
    return sorted(out, key=lambda d: (math.isnan(d["p"]), d["p"]))


def outcome_drivers(rows: list[dict[str, Any]], cfg: CampaignConfig, out_col: str) -> list[dict[str, Any]]:
    """What moves one measured outcome, failures or not: per dispersed input, Spearman's rank
    correlation (a choice input such as the port: Kruskal-Wallis across its values, with each
    value's median), over the missions where the outcome was measured; smallest p first."""
    from scipy.stats import kruskal, spearmanr

    y_all = np.array([np.nan if r[out_col] is None else r[out_col] for r in rows], dtype=float)
    keep = np.isfinite(y_all)
    y = y_all[keep]
    out: list[dict[str, Any]] = []
    if len(y) < 3 or np.ptp(y) == 0:
        return out
    for name in dispersed_inputs(cfg):
        x = input_values(rows, name)[keep]
        if np.ptp(x) == 0:
            continue
        spec = cfg.inputs.get(name)
        d: dict[str, Any] = {"input": name, "unit": input_unit(name), "rho": float("nan"), "medians": {}}
        if spec is not None and spec.kind == "choice":
            groups = {v: y[x == v] for v in np.unique(x)}
            d["medians"] = {v: float(np.median(g)) for v, g in groups.items()}
            sizes = [g for g in groups.values() if len(g)]
            d["p"] = float(kruskal(*sizes).pvalue) if len(sizes) >= 2 else float("nan")
        else:
            res = spearmanr(x, y)
            d["rho"], d["p"] = float(res.statistic), float(res.pvalue)
        out.append(d)
    return sorted(out, key=lambda d: (math.isnan(d["p"]), d["p"]))


def _driver_lines(rows: list[dict[str, Any]], cfg: CampaignConfig, top: int = 5) -> list[str]:
    names = dispersed_inputs(cfg)
    out = [
        "## What drives the outcomes",
        "",
        f"Each outcome against each of the {len(names)} dispersed inputs, the {top} with the smallest p "
        "(Spearman's rho; a choice input: Kruskal-Wallis across its values, medians per value). "
        f"With {len(names)} inputs tried, only p < {0.05 / max(1, len(names)):.2g} stands out (Bonferroni, 5 %).",
        "",
        "| outcome | input | rho or medians | p |",
        "| --- | --- | --- | --- |",
    ]
    for out_col in OUTCOME_PLOTS:
        for d in outcome_drivers(rows, cfg, out_col)[:top]:
            how = (
                ", ".join(f"{_fmt(float(v))}: {_fmt(m)}" for v, m in d["medians"].items())
                if d["medians"]
                else f"{d['rho']:+.2f}"
            )
            out.append(f"| {out_col} | {d['input']} [{d['unit']}] | {how} | {_fmt(d['p'], 2)} |")
    out.append("")
    return out


def dispersed_inputs(cfg: CampaignConfig) -> list[str]:
    """Inputs the model varies and that act in this campaign's navigation mode, then the derived
    ones whose parts are dispersed (the guidance gate reads the combined misalignment, not
    pitch and yaw apart)."""
    names = [n for n, d in cfg.inputs.items() if d.dispersed and INPUTS[n].nav in ("both", cfg.nav)]
    return names + [n for n, (_, parts, _) in DERIVED.items() if any(q in names for q in parts)]


# Inputs computed from drawn ones: name -> (unit, the inputs it is made of, how).
DERIVED: dict[str, tuple[str, tuple[str, ...], Any]] = {
    "start_misalignment_deg": ("deg", ("start_pitch_deg", "start_yaw_deg"), lambda p, y: math.hypot(p, y)),
    "start_lateral_m": ("m", ("start_lateral_x_m", "start_lateral_y_m"), lambda x, y: math.hypot(x, y)),
}


def input_values(rows: list[dict[str, Any]], name: str) -> np.ndarray:
    """One input's value in every row (drawn, or derived from drawn ones)."""
    if name in DERIVED:
        _, parts, fn = DERIVED[name]
        return np.array([fn(*(r[f"in_{q}"] for q in parts)) for r in rows], dtype=float)
    return np.array([r[f"in_{name}"] for r in rows], dtype=float)


def input_unit(name: str) -> str:
    return DERIVED[name][0] if name in DERIVED else INPUTS[name].unit


def _log_axis(cfg: CampaignConfig, name: str) -> bool:
    spec = cfg.inputs.get(name)
    return spec is not None and spec.kind == "loguniform"  # a rate over decades: log axes


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return "-" if math.isnan(v) else f"{v:.{digits}g}"
    return str(v)


def _unit(v: Any, unit: str) -> str:
    text = _fmt(v)
    return text if text == "-" else f"{text} {unit}"


def _category_rates(rows: list[dict[str, Any]], key: str) -> list[tuple[str, Rate]]:
    groups: dict[str, list[bool]] = defaultdict(list)
    for r in rows:
        groups[str(r[key]) or "(none)"].append(bool(r["success"]))
    return sorted(((k, rate(sum(v), len(v))) for k, v in groups.items()), key=lambda kv: (kv[1].rate, kv[0]))


def _figures(rows: list[dict[str, Any]], cfg: CampaignConfig, fig_dir: Path) -> list[tuple[str, str]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig_dir.mkdir(parents=True, exist_ok=True)
    made: list[tuple[str, str]] = []
    names = dispersed_inputs(cfg)
    ok = np.array([bool(r["success"]) for r in rows])
    if names:
        cols = 5
        nrows = math.ceil(len(names) / cols)
        fig, axes = plt.subplots(nrows, cols, figsize=(3.2 * cols, 2.4 * nrows), squeeze=False)
        for ax, name in zip(axes.flat, names, strict=False):
            x = input_values(rows, name)
            nbins = min(20, max(5, len(x) // 10))
            if _log_axis(cfg, name):
                bins = np.geomspace(x.min(), x.max() * 1.0001, nbins + 1)
                ax.set_xscale("log")
            else:
                bins = np.histogram_bin_edges(x, bins=nbins)
            ax.hist(
                [x[ok], x[~ok]],
                bins=bins,
                stacked=True,
                color=["tab:green", "tab:red"],
                label=["ok", "failed"],
            )
            ax.set_title(f"{name} [{input_unit(name)}]", fontsize=8)
            ax.tick_params(labelsize=7)
        for ax in list(axes.flat)[len(names) :]:
            ax.axis("off")
        axes.flat[0].legend(fontsize=7)
        fig.suptitle(f"{cfg.name}: dispersed inputs, missions that succeeded (green) and failed (red)")
        fig.tight_layout()
        fig.savefig(fig_dir / "inputs_success.png", dpi=80)
        plt.close(fig)
        made.append(("inputs_success.png", "each dispersed input, split by success"))
        for out_col in OUTCOME_PLOTS:
            y = np.array([np.nan if r[out_col] is None else r[out_col] for r in rows], dtype=float)
            if not np.isfinite(y).any():
                continue
            limit, what = {**LIMITS, **NAV_REFERENCE}[out_col]
            fig, axes = plt.subplots(nrows, cols, figsize=(3.2 * cols, 2.4 * nrows), squeeze=False)
            for ax, name in zip(axes.flat, names, strict=False):
                x = input_values(rows, name)
                ax.scatter(x[ok], y[ok], s=6, c="tab:green", alpha=0.6)
                ax.scatter(x[~ok], y[~ok], s=14, c="tab:red", marker="x")
                ax.axhline(limit, color="k", ls="--", lw=0.8)
                if _log_axis(cfg, name):
                    ax.set_xscale("log")
                ax.set_title(f"{name} [{input_unit(name)}]", fontsize=8)
                ax.tick_params(labelsize=7)
            for ax in list(axes.flat)[len(names) :]:
                ax.axis("off")
            fig.suptitle(f"{cfg.name}: {out_col} against each dispersed input (dashed: {what})")
            fig.tight_layout()
            fig.savefig(fig_dir / f"inputs_vs_{out_col}.png", dpi=80)
            plt.close(fig)
            made.append((f"inputs_vs_{out_col}.png", f"{out_col} against each dispersed input"))
    fig, axes = plt.subplots(1, len(LIMITS) + 1, figsize=(3.2 * (len(LIMITS) + 1), 2.6))
    for ax, (col, (limit, what)) in zip(axes, LIMITS.items(), strict=False):
        y = np.array([r[col] for r in rows if r[col] is not None], dtype=float)
        if len(y):
            ax.hist(np.abs(y), bins=20, color="tab:blue")
        ax.axvline(limit, color="r", ls="--", lw=1)
        ax.set_title(f"{col}\n(red: {what})", fontsize=8)
        ax.tick_params(labelsize=7)
    y = np.array(
        [r["fuel_transferred_kg"] for r in rows if r["fuel_transferred_kg"] is not None], dtype=float
    )
    if len(y):
        axes[-1].hist(y, bins=20, color="tab:purple")
    axes[-1].set_title("fuel_transferred_kg", fontsize=8)
    fig.tight_layout()
    fig.savefig(fig_dir / "outcomes.png", dpi=80)
    plt.close(fig)
    made.append(("outcomes.png", "contact errors, peak loads and fuel transferred against their limits"))
    return made


def _when(text: Any) -> str:
    return str(text or "?").replace("T", " ").replace("Z", " UTC")


def code_lines(folder: Path, rows: list[dict[str, Any]]) -> list[str]:
    """The report's code version: campaign.json's fingerprint, the changes allowed on a resume,
    other code kept from workers, and how many missions each code version flew (``code_sha``)."""
    from oibar_hil.campaign.fingerprint import describe

    # campaign.json read here, not through store: a driver started before fingerprints (its old
    # store already imported) still writes its final report with this module
    path = Path(folder) / "campaign.json"
    record = json.loads(path.read_text()) if path.exists() else {}
    code = record.get("code")
    out = ["## Code version", ""]
    if not code:
        out.append(
            "No code fingerprint recorded: the folder was made before campaigns recorded one, "
            "so nothing says that every mission was flown by the same code."
        )
    else:
        groups = ", ".join(sorted(code.get("groups", {})))
        out.append(
            f"Flown by code `{describe(code)}`, recorded {_when(code.get('time'))}: the SHA-256 "
            f"`{code.get('sha256', '?')}` over {groups} (docs/campaign.md). A resume from other "
            "code is refused unless a reason is given."
        )
    adopted = record.get("code_adopted")
    if adopted:
        out += [
            "",
            f"The fingerprint was recorded at a resume ({_when(adopted.get('time'))}), after "
            f"{adopted.get('missions_before', '?')} missions flown before campaigns recorded one: "
            "their rows have no `code_sha`.",
        ]
    changes = record.get("code_changes") or []
    if changes:
        out += [
            "",
            f"**The code changed during this campaign** ({len(changes)} change(s), each allowed with "
            "`--allow-code-change`): the missions do not all come from one version of the code.",
            "",
            "| time | reason | changed | from | to | missions flown before |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for c in changes:
            reason = str(c.get("reason", "")).replace("|", "\\|")
            out.append(
                f"| {_when(c.get('time'))} | {reason} | {', '.join(c.get('changed', [])) or '-'} | "
                f"`{describe(c.get('old'))}` | `{describe(c.get('new'))}` | {c.get('missions_before', '?')} |"
            )
    kept = record.get("worker_code") or []
    if kept:
        out += [
            "",
            f"**Ray workers flew missions with other code** ({len(kept)} fingerprint(s), each kept "
            "with `--allow-code-change`; their rows carry the worker's `code_sha`):",
            "",
        ]
        for k in kept:
            out.append(
                f"- `{describe(k.get('code'))}` on worker {k.get('worker') or '?'}, first mission "
                f"{k.get('first_mission', '?')}: differs in {', '.join(k.get('changed', [])) or '-'}; "
                f"reason: {k.get('reason', '')}"
            )
    by_code = Counter(r.get("code_sha") or "" for r in rows)
    if by_code:
        out += [
            "",
            "Missions by code (`code_sha`): "
            + ", ".join(f"`{k}` {v}" if k else f"none recorded {v}" for k, v in by_code.items())
            + ".",
        ]
    out.append("")
    return out


def write_report(folder: Path, rows: list[dict[str, Any]], cfg: CampaignConfig, figures: bool = True) -> Path:
    folder = Path(folder)
    lines: list[str] = []
    add = lines.append
    n = len(rows)
    add(f"# Campaign `{cfg.name}`: {n} of {cfg.missions} missions, {cfg.nav} navigation")
    add("")
    add(
        f"Seed {cfg.seed}, model identity `{cfg.identity()}` (from `{cfg.source or 'campaign.json'}`), "
        f"fault probability {cfg.fault_probability:g} per mission, at most {cfg.max_time_s:g} s simulated "
        f"per mission. Every row of `missions.parquet` replays with "
        f"`{replay_command(folder, 0).replace(' 0', ' INDEX')}`."
    )
    add("")
    lines += code_lines(folder, rows)
    if not rows:
        add("No mission has finished yet.")
        path = folder / "report.md"
        path.write_text("\n".join(lines) + "\n")
        return path
    add("## Success rate (Clopper-Pearson, exact)")
    add("")
    add("| missions | success | rate | 95 % interval | >= with 95 % confidence |")
    add("| --- | --- | --- | --- | --- |")
    for label, r in _rates(rows).items():
        if r.trials:
            add(
                f"| {label} | {r.successes}/{r.trials} | {100 * r.rate:.2f} % | "
                f"{100 * r.low:.2f}-{100 * r.high:.2f} % | {100 * r.lower_bound:.2f} % |"
            )
    add("")
    outcomes = Counter(r["outcome"] for r in rows)
    add("Outcomes: " + ", ".join(f"{k} {v}" for k, v in outcomes.most_common()) + ".")
    wall = np.array([r["wall_time_s"] for r in rows], dtype=float)
    cpu = np.array([r["cpu_time_s"] or np.nan for r in rows], dtype=float)
    sim = np.array([r["sim_time_s"] or 0.0 for r in rows], dtype=float)
    add(
        f"Per mission (one core each): wall median {np.median(wall):.1f} s (p95 {np.percentile(wall, 95):.1f} s), "
        f"CPU median {np.nanmedian(cpu):.1f} s (the rig and its simulated MCU), so about "
        f"{3600.0 / np.nanmean(cpu):.0f} missions per core-hour on a free core; simulated "
        f"{np.median(sim):.0f} s median."
    )
    vented = [r for r in rows if (r["fuel_lost_kg"] or 0.0) > 0.0]
    add(
        f"Vented: {len(vented)} missions; fuel transferred median "
        f"{_fmt(float(np.median([r['fuel_transferred_kg'] or 0.0 for r in rows])))} kg."
    )
    add("")
    failures = [r for r in rows if not r["success"]]
    add(f"## Failures ({len(failures)})")
    add("")
    if failures:
        add("| mission | fault | outcome | failed checks / error | abort reason | replay |")
        add("| --- | --- | --- | --- | --- | --- |")
        for row in failures[:50]:
            why = (row["failed_checks"] or row["error"]).replace("|", "/")[:160]
            fault = f"{row['fault']}@{row['fault_phase']}" if row["fault"] else "-"
            add(
                f"| {row['index']} | {fault} | {row['outcome']} | {why} | {row['abort_reason'] or '-'} | "
                f"`{replay_command(folder, row['index'])}` |"
            )
        if len(failures) > 50:
            add(f"| ... {len(failures) - 50} more in missions.parquet | | | | | |")
    else:
        add("None.")
    add("")
    add("## Failure drivers")
    add("")
    add(
        "Each dispersed input in the failed against the passed missions (Mann-Whitney U, two-sided; "
        "a small p says the failures sit elsewhere in that input; with few failures nothing is small)."
    )
    add("")
    add("| input | unit | median, failed | median, passed | p |")
    add("| --- | --- | --- | --- | --- |")
    for d in drivers(rows, cfg):
        add(
            f"| {d['input']} | {d['unit']} | {_fmt(d['median_failed'])} | {_fmt(d['median_passed'])} | "
            f"{_fmt(d['p'], 2)} |"
        )
    add("")
    cats = ["fault", "fault_phase"] + (["in_approach_port"] if cfg.nav == "cnn" else [])
    for key in cats:
        add(
            f"Success by {key}: "
            + "; ".join(f"{k} {r.successes}/{r.trials}" for k, r in _category_rates(rows, key))
            + "."
        )
        add("")
    lines += _driver_lines(rows, cfg)
    if figures:
        add("## Figures")
        add("")
        for name, what in _figures(rows, cfg, folder / "figures"):
            add(f"![{what}](figures/{name})")
            add("")
    add(f"## Worst missions (failures first, then the least margin to a limit; {WORST_SHOWN} shown)")
    add("")
    add(
        "| mission | success | margin | lateral at contact | closing | misalignment | peak force | fault | replay |"
    )
    add("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for row in sorted(rows, key=margin_score, reverse=True)[:WORST_SHOWN]:
        lat = row["contact_lateral_m"]
        clo = row["contact_closing_speed_mps"]
        add(
            f"| {row['index']} | {'yes' if row['success'] else 'NO'} | {margin_score(row) % 10:.2f} | "
            f"{'-' if lat is None else f'{1000 * lat:.1f} mm'} | {'-' if clo is None else f'{1000 * clo:.1f} mm/s'} | "
            f"{_unit(row['contact_misalignment_deg'], 'deg')} | {_unit(row['peak_force_n'], 'N')} | "
            f"{(row['fault'] + '@' + row['fault_phase']) if row['fault'] else '-'} | "
            f"`{replay_command(folder, row['index'])}` |"
        )
    add("")
    add("## The dispersion model")
    add("")
    add("| input | unit | distribution | bounds | acts in | applied at | note |")
    add("| --- | --- | --- | --- | --- | --- | --- |")
    for name, idef in INPUTS.items():
        spec = cfg.inputs.get(name)
        if spec is None:
            dist, bounds, note = f"nominal {idef.nominal:g}", "-", "not dispersed"
        else:
            dist = ", ".join(f"{k}={v}" for k, v in spec.to_dict().items() if k not in ("note",))
            lo, hi = spec.bounds
            bounds, note = f"[{lo:g}, {hi:g}]", spec.note
        add(f"| {name} | {idef.unit} | {dist} | {bounds} | {idef.nav} | {idef.applies} | {note} |")
    add("")
    add(
        "Not applied (the rig has no place for them yet): "
        + "; ".join(f"{k}: {v}" for k, v in NOT_APPLIED.items())
        + "."
    )
    path = folder / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
