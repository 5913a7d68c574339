"""Figure 3: the HIL rig's speed factor (simulated time / wall time) over whole missions.

The rig runs through its own command line (``python -m oibar_hil.rig``), one process per
mission, as `make mission-demo` runs it; the figures are its RunResult's (written with
``--json``, or read from its result line when that option is missing). Ground-truth
navigation (``--nav truth``) and the CNN in the loop (``--nav cnn``: the rig renders the
camera and runs the host's navigator) are both reported; the latter is "not available yet"
while the rig's CLI has no ``--nav``.
"""

from __future__ import annotations

import json
import os
import re
import statistics
import subprocess
import sys
from pathlib import Path

from .core import NOT_AVAILABLE, ROOT, Context, Result, Target, measurement
from .pose import SHIPPED, nav_model

# Ours: the rig must not be slower than the flight it simulates (a real-time HIL bench would be
# paced to 1x; anything above is what campaigns such as the fault matrix live on).
SPEED_TARGET = Target(">=", 1.0, "x", "ours: at least real time")
COLUMNS = [
    ("scenario", "scenario"),
    ("nav", "navigation"),
    ("runs", "runs"),
    ("outcome", "outcome"),
    ("sim_s", "simulated (s)"),
    ("wall_s", "wall median (s)"),
    ("speed", "speed median (x)"),
    ("speed_range", "speed min-max (x)"),
    ("target", "target"),
    ("gap", "gap"),
]
# Older CLIs print only this line: "<name>: <outcome>, PASS (63.9 s simulated in 1.19 s, 54x real time...)"
RESULT_LINE = re.compile(
    r"^(\S+): (\S+), (PASS|FAIL) \(([\d.]+) s simulated in ([\d.]+) s, ([\d.]+)x real time", re.M
)
RUN_TIMEOUT_S = 600
SCENARIOS = ROOT / "hil" / "scenarios"


def _rig(ctx: Context, *args: str, timeout_s: float = RUN_TIMEOUT_S) -> subprocess.CompletedProcess:
    env = dict(
        os.environ,
        PYTHONPATH=os.pathsep.join(
            p for p in (str(ROOT / "hil"), str(ROOT / "host"), os.environ.get("PYTHONPATH", "")) if p
        ),
    )
    cmd = [sys.executable, "-m", "oibar_hil.rig", *args]
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout_s)


def rig_options(ctx: Context) -> tuple[set[str], str]:
    """The rig CLI's top-level options (e.g. {"--nav", "--json"}), or why it does not start."""
    if "rig_options" not in ctx.shared:
        try:
            h = _rig(ctx, "--help", timeout_s=60)
        except subprocess.TimeoutExpired:
            ctx.shared["rig_options"] = (set(), "`python -m oibar_hil.rig --help` did not answer in 60 s")
        else:
            if h.returncode != 0:
                last = ((h.stderr or h.stdout).strip().splitlines() or ["no output"])[-1]
                ctx.shared["rig_options"] = (set(), f"the rig's CLI does not start ({last})")
            else:
                ctx.shared["rig_options"] = (set(re.findall(r"(--[a-z][a-z-]*)", h.stdout)), "")
    return ctx.shared["rig_options"]


def _one_run(ctx: Context, opts: list[str], scenario: Path, tag: str) -> dict:
    known, _ = rig_options(ctx)
    out_json = ctx.tmp / f"rig-{tag}.json"
    args = ["--no-progress", "--out", str(ctx.tmp / "hil"), *opts]
    if "--json" in known:
        args += ["--json", str(out_json)]
    p = _rig(ctx, *args, "run", str(scenario))
    if "--json" in known and out_json.is_file():
        r = json.loads(out_json.read_text())[0]
        out_json.unlink()
        return {
            "outcome": r["outcome"],
            "passed": bool(r["passed"]),
            "sim_s": float(r["sim_time_s"]),
            "wall_s": float(r["wall_time_s"]),
            "metrics": r.get("metrics") or {},
        }
    m = RESULT_LINE.search(p.stdout)
    if m is None:
        tail = "\n".join((p.stdout + p.stderr).strip().splitlines()[-8:])
        raise RuntimeError(
            f"rig {' '.join(args)} run {scenario.name} (exit {p.returncode}) gave no result:\n{tail}"
        )
    return {
        "outcome": m.group(2),
        "passed": m.group(3) == "PASS",
        "sim_s": float(m.group(4)),
        "wall_s": float(m.group(5)),
        "metrics": {},
    }


def _runs(ctx: Context, opts: list[str], scenario: Path, n: int, label: str) -> tuple[dict, list[dict]]:
    runs = []
    for i in range(n):
        r = _one_run(ctx, opts, scenario, f"{label}-{i}")
        r["speed"] = r["sim_s"] / r["wall_s"]
        runs.append(r)
        ctx.progress(
            f"hil {label} run {i + 1}/{n}: {r['outcome']}, {'PASS' if r['passed'] else 'FAIL'}, "
            f"{r['sim_s']:.1f} s simulated in {r['wall_s']:.2f} s = {r['speed']:.1f}x"
        )
    speeds = [r["speed"] for r in runs]
    outcomes = sorted({f"{r['outcome']} ({'PASS' if r['passed'] else 'FAIL'})" for r in runs})
    med = statistics.median(speeds)
    return (
        {
            "runs": n,
            "outcome": ", ".join(outcomes),
            "sim_s": statistics.median(r["sim_s"] for r in runs),
            "wall_s": statistics.median(r["wall_s"] for r in runs),
            "speed": med,
            "speed_range": f"{min(speeds):.1f}-{max(speeds):.1f}",
            "target": SPEED_TARGET,
            "measured": med,
        },
        runs,
    )


@measurement("hil.ground_truth", "Ground-truth navigation (the host guidance on the true pose)", COLUMNS)
def ground_truth(ctx: Context) -> Result:
    known, why = rig_options(ctx)
    if why:
        raise RuntimeError(why)
    scenario = "nominal_short" if ctx.quick else "nominal"
    n = 1 if ctx.quick else 3
    opts = ["--nav", "truth"] if "--nav" in known else []
    row, _ = _runs(ctx, opts, SCENARIOS / f"{scenario}.yaml", n, scenario)
    notes = [
        "The simulated MCU is the `make firmware-host` build (Debug, ASan+UBSan); the Python plant "
        "dominates (docs/hil.md). nominal = the whole mission from 10 m; nominal_short = from 1.2 m."
    ]
    if ctx.quick:
        notes.append("Quick mode: nominal_short once; `make bench` runs the nominal mission 3 times.")
    return Result([{"scenario": scenario, "nav": "ground truth", **row}], notes)


@measurement("hil.cnn", "The CNN in the loop (`python -m oibar_hil.rig --nav cnn`)", COLUMNS)
def cnn_in_loop(ctx: Context) -> Result:
    known, why = rig_options(ctx)
    if why or "--nav" not in known:
        why = why or "the rig's CLI has no `--nav` option yet"
        ctx.progress(f"hil cnn: {NOT_AVAILABLE} ({why})")
        return Result(
            [
                {
                    "scenario": "nominal",
                    "nav": f"CNN: {NOT_AVAILABLE}",
                    "target": SPEED_TARGET,
                    "gap": NOT_AVAILABLE,
                    "available": False,
                }
            ],
            [f"{NOT_AVAILABLE}: {why}."],
        )
    if ctx.quick:
        ctx.progress("hil cnn: available; skipped in quick mode")
        return Result(
            [
                {
                    "scenario": "nominal",
                    "nav": "CNN: skipped in quick mode",
                    "target": SPEED_TARGET,
                    "gap": "-",
                    "available": True,
                }
            ],
            ["Quick mode: a mission with the CNN takes minutes on 2 cores; `make bench` runs it."],
        )
    model, model_text = nav_model(ctx)
    opts = ["--nav", "cnn"]
    if "--model" in known:
        opts += ["--model", str(model)]
    row, runs = _runs(ctx, opts, SCENARIOS / "nominal.yaml", 1, "nominal with the CNN")
    notes = [
        f"Model: {model_text}. The rig renders every camera frame (744x480) and runs the host's navigator "
        "on it at 10 Hz of simulated time; one run, as it takes minutes on 2 cores."
    ]
    if not (ROOT / SHIPPED).is_file():
        notes.append(
            "With untrained weights the navigation is wrong and the mission ends early (aborted or "
            "failed): the speed factor still holds for the simulated time it ran; the mission's own "
            "outcome needs the trained model."
        )
    m = runs[0]["metrics"]
    keys = [k for k in ("nav_cycles", "nav_ms_median", "nav_ms_p99", "render_ms_median") if k in m]
    if keys:
        notes.append(
            "The rig's own figures: "
            + ", ".join(f"{k} = {m[k]:.1f}" if isinstance(m[k], float) else f"{k} = {m[k]}" for k in keys)
            + "."
        )
    return Result([{"scenario": "nominal", "nav": "CNN", **row, "available": True}], notes)
