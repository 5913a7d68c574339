"""The mission report: one HTML page with PNG plots beside it, plus summary.json.

Read it top down: verdict and speed, pass/fail per requirement, the plots (state timeline with
commands and faults; relative position and velocity; contact force, latch and plane; valves and
pressures), then the full timeline of states, commands, MCU events and notes.
"""

from __future__ import annotations

import csv
import html
import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from oibar import pb  # noqa: E402

STATE_ORDER = [n for n in pb.State.keys() if n != "STATE_UNSPECIFIED"]  # noqa: SIM118  (a protobuf enum, not a dict)


def _arr(samples: dict[str, list], key: str) -> np.ndarray:
    return np.asarray(samples[key], dtype=float)


def _mark_faults(ax: Any, result: Any) -> None:
    for t, text in result.notes:
        if text.startswith("inject"):
            ax.axvline(t, color="red", lw=1.0, ls="--", alpha=0.7)


def _plot_timeline(result: Any, path: Path) -> None:
    s = result.samples
    t = _arr(s, "t_s")
    idx = [STATE_ORDER.index(x) if x in STATE_ORDER else -1 for x in s["state"]]
    fig, ax = plt.subplots(figsize=(11, 4.2))
    ax.step(t, idx, where="post", color="tab:blue", lw=1.6)
    ax.set_yticks(range(len(STATE_ORDER)))
    ax.set_yticklabels([n.replace("STATE_", "") for n in STATE_ORDER], fontsize=7)
    for tc, label, verdict in result.requests:
        ok = verdict.startswith("accepted")
        ax.axvline(tc, color="tab:green" if ok else "tab:orange", lw=0.8, alpha=0.6)
        ax.text(
            tc,
            len(STATE_ORDER) - 0.5,
            label.replace("CMD_", ""),
            rotation=90,
            fontsize=6,
            va="top",
            ha="right",
            color="tab:green" if ok else "tab:orange",
        )
    _mark_faults(ax, result)
    ax.set_xlabel("simulated time [s]")
    ax.set_title(
        "MCU state (ground truth), commands (green accepted / orange refused), fault injections (red)"
    )
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _plot_approach(result: Any, path: Path) -> None:
    s = result.samples
    t = _arr(s, "t_s")
    fig, axs = plt.subplots(3, 1, figsize=(11, 7), sharex=True)
    axs[0].plot(t, _arr(s, "range_m"), label="range along docking axis [m]")
    axs[0].plot(t, _arr(s, "lateral_m") * 10, label="lateral offset x10 [m]")
    axs[0].axhline(0.0, color="k", lw=0.6)
    axs[0].set_ylabel("m")
    axs[0].legend(fontsize=8)
    axs[1].plot(t, _arr(s, "closing_mps") * 1000, label="closing speed [mm/s]")
    axs[1].plot(t, _arr(s, "v_sp_closing_mps") * 1000, label="guidance setpoint [mm/s]", alpha=0.7)
    axs[1].plot(t, _arr(s, "lat_speed_mps") * 1000, label="lateral speed [mm/s]", alpha=0.7)
    axs[1].axhline(50, color="red", ls=":", label="capture limit 50 mm/s")
    axs[1].set_ylabel("mm/s")
    axs[1].legend(fontsize=8)
    axs[2].plot(t, _arr(s, "misalign_deg"), label="yaw/pitch misalignment [deg]")
    axs[2].axhline(10, color="red", ls=":", label="capture limit 10 deg")
    axs[2].set_ylabel("deg")
    axs[2].set_xlabel("simulated time [s]")
    axs[2].legend(fontsize=8)
    for ax in axs:
        ax.grid(alpha=0.3)
        _mark_faults(ax, result)
    axs[0].set_title("Relative position and velocity (ground truth, docking frame D)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _plot_mechanism(result: Any, path: Path) -> None:
    s = result.samples
    t = _arr(s, "t_s")
    fig, axs = plt.subplots(3, 1, figsize=(11, 7), sharex=True)
    axs[0].plot(t, _arr(s, "force_n"), label="contact force estimate [N]")
    axs[0].axhline(30, color="orange", ls=":", label="soft-dock limit 30 N")
    axs[0].axhline(60, color="red", ls=":", label="hard-dock limit 60 N")
    axs[0].set_ylabel("N")
    axs[0].legend(fontsize=8)
    axs[1].plot(t, _arr(s, "latch_steps"), label="latch cam [steps]")
    axs[1].plot(t, _arr(s, "latch_engaged") * 600, label="latches engaged (x600)", alpha=0.7)
    axs[1].set_ylabel("steps")
    axs[1].legend(fontsize=8)
    axs[2].plot(t, _arr(s, "plane_mm"), label="fluidic plane [mm]")
    axs[2].set_ylabel("mm")
    axs[2].set_xlabel("simulated time [s]")
    axs[2].legend(fontsize=8)
    for ax in axs:
        ax.grid(alpha=0.3)
        _mark_faults(ax, result)
    axs[0].set_title("Contact force, latch and fluidic plane")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _plot_fluid(result: Any, path: Path) -> None:
    s = result.samples
    t = _arr(s, "t_s")
    fig, axs = plt.subplots(2, 1, figsize=(11, 6), sharex=True, gridspec_kw={"height_ratios": [1, 2]})
    for i, (name, cmd, sensed) in enumerate(
        (("SV valve", "sv_cmd", "sv_open"), ("TV valve", "tv_cmd", "tv_open"))
    ):
        off = 2.5 * i
        axs[0].step(t, _arr(s, cmd) + off, where="post", label=f"{name} commanded", lw=1.2)
        axs[0].step(t, _arr(s, sensed) * 0.9 + off, where="post", label=f"{name} sensed open", ls="--")
    axs[0].set_yticks([0, 1, 2.5, 3.5])
    axs[0].set_yticklabels(["SV closed", "SV open", "TV closed", "TV open"], fontsize=7)
    axs[0].legend(fontsize=7, ncol=4)
    axs[1].plot(t, _arr(s, "sv_kpa"), label="SV (supply) tank [kPa]")
    axs[1].plot(t, _arr(s, "tv_kpa"), label="TV (receiving) tank [kPa]")
    axs[1].plot(t, _arr(s, "line_kpa"), label="transfer line [kPa]")
    axs[1].plot(t, _arr(s, "tv_sensed_kpa"), label="TV tank, host telemetry [kPa]", ls=":", alpha=0.8)
    axs[1].axhline(result.scenario.mission.target_kpa, color="green", ls=":", label="target")
    axs[1].axhline(2600, color="red", ls=":", label="over-pressure trip 2600 kPa")
    axs[1].set_ylabel("kPa")
    axs[1].set_xlabel("simulated time [s]")
    axs[1].legend(fontsize=7, ncol=3)
    for ax in axs:
        ax.grid(alpha=0.3)
        _mark_faults(ax, result)
    axs[0].set_title("Valves and pressures (gas model: isothermal nitrogen simulant)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _plot_navigation(result: Any, path: Path) -> None:
    """The navigator's estimate beside the truth (CNN in the loop)."""
    log = result.nav_log
    t = np.array([r["t_s"] for r in log])

    def col(k):
        return np.array([r.get(k, np.nan) for r in log], dtype=float)

    hold = np.array([bool(r["hold_reason"]) for r in log])
    fig, axs = plt.subplots(4, 1, figsize=(11, 9), sharex=True)
    axs[0].plot(t, col("range_true_m"), color="k", lw=1.2, label="true")
    axs[0].plot(t, col("range_est_m"), color="tab:blue", lw=0.9, label="navigator")
    axs[0].set_ylabel("probe range [m]")
    axs[0].legend(fontsize=8)
    axs[1].semilogy(t, np.maximum(col("lateral_err_m") * 100, 1e-2), color="tab:red", lw=0.9)
    axs[1].axhline(2.0, color="gray", ls=":", label="gate 2 cm")
    axs[1].set_ylabel("lateral error [cm]")
    axs[1].legend(fontsize=8)
    axs[2].plot(t, col("misalign_true_deg"), color="k", lw=1.2, label="true")
    axs[2].plot(t, col("misalign_est_deg"), color="tab:blue", lw=0.9, label="navigator")
    axs[2].set_ylabel("misalignment [deg]")
    axs[2].legend(fontsize=8)
    axs[3].plot(t, col("nav_ms"), color="tab:purple", lw=0.8, label="navigator (estimate + filter)")
    axs[3].plot(t, col("render_ms"), color="tab:gray", lw=0.6, alpha=0.7, label="render (rig only)")
    axs[3].set_ylabel("time per cycle [ms]")
    axs[3].legend(fontsize=8)
    for ax in axs:
        for th in t[hold]:
            ax.axvline(th, color="orange", alpha=0.15, lw=0.8)
        ax.grid(alpha=0.3)
    axs[-1].set_xlabel("simulated time [s]")
    axs[0].set_title("navigation: estimate vs truth (orange: cycles that held)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_nav_cycles(log: list[dict], path: Path) -> None:
    """One row per guidance cycle: the navigator's solution, the frame's pose (answer and the
    filter's measurement) and their signed errors against the truth; a cell is empty where a cycle
    had no such value (no frame, no solution)."""
    cols = list(dict.fromkeys(k for r in log for k in r))  # every key, in first-seen order
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, restval="")
        w.writeheader()
        w.writerows(log)


def summary_dict(result: Any) -> dict[str, Any]:
    return {
        "scenario": result.scenario.name,
        "outcome": result.outcome,
        "passed": result.passed,
        "sim_time_s": round(result.sim_time_s, 3),
        "wall_time_s": round(result.wall_time_s, 3),
        "speed_factor": round(result.speed_factor, 1),
        "checks": [{"id": c.id, "text": c.text, "ok": c.ok, "measured": c.measured} for c in result.checks],
        "metrics": {k: v for k, v in result.metrics.items()},
        "capture": result.capture,
    }


def write_report(result: Any, out_dir: Path) -> Path:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    plots = [
        ("timeline.png", _plot_timeline),
        ("approach.png", _plot_approach),
        ("mechanism.png", _plot_mechanism),
        ("fluid.png", _plot_fluid),
    ]
    if getattr(result, "nav_log", None) and result.metrics.get("nav") == "cnn":
        plots.insert(2, ("navigation.png", _plot_navigation))
    for name, fn in plots:
        fn(result, out_dir / name)
    (out_dir / "summary.json").write_text(json.dumps(summary_dict(result), indent=2, default=str))
    if getattr(result, "nav_log", None):
        write_nav_cycles(result.nav_log, out_dir / "nav_cycles.csv")
    e = html.escape
    sc = result.scenario
    verdict = "PASS" if result.passed else "FAIL"
    rows = "".join(
        f"<tr class='{'na' if c.ok is None else ('ok' if c.ok else 'bad')}'><td>{e(c.id)}</td>"
        f"<td>{e(c.text)}</td><td>{e(c.measured)}</td>"
        f"<td>{'n/a' if c.ok is None else ('pass' if c.ok else 'FAIL')}</td></tr>"
        for c in result.checks
    )
    timeline = sorted(
        [(t, "state", s) for t, s in result.states]
        + [(t, "command", f"{label}: {v}") for t, label, v in result.requests]
        + [(t, "MCU event", text) for t, text in result.events]
        + [(t, "note", text) for t, text in result.notes]
    )
    tl_rows = "".join(f"<tr><td>{t:9.3f}</td><td>{e(k)}</td><td>{e(v)}</td></tr>" for t, k, v in timeline)
    m = result.metrics
    key_metrics = {
        "final MCU state": m["final_state"],
        "faults raised (MCU, ground truth)": ", ".join(m["faults_seen"]) or "none",
        "fuel lost [kg]": f"{m['fuel_lost_kg']:.4f}",
        "TV tank at end [kPa]": f"{m['tv_final_kpa']:.0f}",
        "SV tank at end [kPa]": f"{m['sv_final_kpa']:.0f}",
        "MCU resets": m["mcu_resets"],
        "lockstep exchanges (of which 1 ms)": f"{m['exchanges']} ({m['exchanges_1ms']})",
        "host retransmissions / link losses": f"{m['host_retransmissions']} / {m['host_link_losses']}",
        "CRC errors host / MCU": f"{m['host_rx_crc_errors']} / {m['mcu_rx_crc_errors']}",
        "wire": ", ".join(f"{k} {v}" for k, v in m["wire"].items()),
    }
    if m.get("nav") == "cnn":
        key_metrics["navigation (CNN) cycles / held"] = f"{m.get('nav_cycles')} / {m.get('nav_hold_cycles')}"
        key_metrics["frames fused on the vehicle's attitude (integrity check)"] = str(
            m.get("nav_attitude_replaced", 0)
        )
        key_metrics["navigation errors (median)"] = (
            f"range {m.get('nav_range_err_m_median', float('nan')) * 100:.1f} cm, lateral "
            f"{m.get('nav_lateral_err_m_median', float('nan')) * 100:.1f} cm, misalignment "
            f"{m.get('nav_misalign_err_deg_median', float('nan')):.2f} deg"
        )
        if "nav_lateral_err_m_p95_below_5m" in m:
            key_metrics["navigation below 5 m: lateral p95 / max, misalignment p95"] = (
                f"{m['nav_lateral_err_m_p95_below_5m'] * 100:.1f} / "
                f"{m['nav_lateral_err_m_max_below_5m'] * 100:.1f} cm, "
                f"{m['nav_misalign_err_deg_p95_below_5m']:.2f} deg"
            )
        key_metrics["navigator time per cycle median / p99 [ms]"] = (
            f"{m.get('nav_ms_median', float('nan')):.1f} / {m.get('nav_ms_p99', float('nan')):.1f}"
        )
    km = "".join(f"<tr><td>{e(k)}</td><td>{e(str(v))}</td></tr>" for k, v in key_metrics.items())
    imgs = "".join(f"<p><img src='{name}' alt='{name}'></p>" for name, _ in plots)
    page = f"""<!doctype html><html><head><meta charset="utf-8">
<title>OIBAR mission report: {e(sc.name)}</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:auto}} table{{border-collapse:collapse;margin:8px 0}}
td,th{{border:1px solid #ccc;padding:3px 8px;font-size:13px;text-align:left}} tr.ok td:last-child{{background:#cfc}}
tr.bad td:last-child{{background:#fbb}} tr.na td:last-child{{background:#eee}} img{{max-width:100%}}
.verdict{{font-size:22px;font-weight:bold;color:{"#070" if result.passed else "#b00"}}}</style></head><body>
<h1>OIBAR mission report: {e(sc.name)}</h1>
<p>{e(sc.description)}</p>
<p class="verdict">{verdict}: outcome <i>{e(result.outcome)}</i></p>
<p>Simulated {result.sim_time_s:.1f} s in {result.wall_time_s:.2f} s wall time:
<b>{result.speed_factor:.0f}x real time</b> (the real firmware on the simulated MCU, lockstep plant,
{"the CNN in the loop on the rendered camera" if m.get("nav") == "cnn" else "ground-truth navigation"},
the host's guidance). Seed {sc.seed}.</p>
<h2>Requirements and expected outcome</h2>
<table><tr><th>id</th><th>requirement</th><th>measured</th><th>verdict</th></tr>{rows}</table>
<h2>Key numbers</h2><table>{km}</table>
<h2>Plots</h2>{imgs}
<h2>Timeline</h2><table><tr><th>t [s]</th><th>kind</th><th>what</th></tr>{tl_rows}</table>
</body></html>"""
    path = out_dir / "report.html"
    path.write_text(page, encoding="utf-8")
    return path
