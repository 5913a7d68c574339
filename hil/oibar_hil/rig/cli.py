"""Command line of the rig.

    python -m oibar_hil.rig demo                  the nominal mission, summary table, report path
    python -m oibar_hil.rig run SCENARIO.yaml...  run scenarios, one report each
    python -m oibar_hil.rig all [--dir DIR]       every scenario in hil/scenarios, summary table

Reports go to build/hil/<scenario>/report.html (``--out`` to change). Exit status 1 when a
scenario fails one of its checks.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from oibar_hil.rig.checks import evaluate
from oibar_hil.rig.report import write_report
from oibar_hil.rig.runner import REPO_ROOT, Rig, RunResult, default_mcu_path
from oibar_hil.rig.scenario import Scenario, load_scenario

SCENARIO_DIR = REPO_ROOT / "hil" / "scenarios"
DEFAULT_OUT = REPO_ROOT / "build" / "hil"


def run_scenario(scenario: Scenario | str | Path, *, out_root: Path | None = DEFAULT_OUT,
                 progress: bool = False, mcu_path: Path | None = None,
                 report: bool = True) -> RunResult:
    """Run one scenario, check it, and (by default) write its report."""
    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    out_dir = (Path(out_root) / sc.name) if out_root else None
    result = Rig(sc, mcu_path=mcu_path, out_dir=out_dir, progress=progress).run()
    result.checks = evaluate(result)
    if report and out_dir is not None:
        result.report_path = write_report(result, out_dir)
    return result


def print_summary(results: list[RunResult]) -> None:
    head = f"{'scenario':<26} {'outcome':<10} {'verdict':<7} {'sim s':>7} {'wall s':>7} {'speed':>6}  failed checks"
    print(head)
    print("-" * len(head))
    for r in results:
        bad = [c.id for c in r.checks if c.ok is False]
        print(f"{r.scenario.name:<26} {r.outcome:<10} {'PASS' if r.passed else 'FAIL':<7} "
              f"{r.sim_time_s:7.1f} {r.wall_time_s:7.2f} {r.speed_factor:5.0f}x  {', '.join(bad) or '-'}")


def _print_checks(r: RunResult) -> None:
    for c in r.checks:
        verdict = "n/a " if c.ok is None else ("pass" if c.ok else "FAIL")
        print(f"  [{verdict}] {c.id:<32} {c.text}  ({c.measured})")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_hil.rig", description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="report folder root")
    ap.add_argument("--mcu", type=Path, default=None, help=f"simulated MCU (default {default_mcu_path()})")
    ap.add_argument("--no-progress", action="store_true")
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("demo", help="the nominal mission from 10 m")
    p_run = sub.add_parser("run", help="run the given scenario files")
    p_run.add_argument("scenarios", nargs="+", type=Path)
    p_all = sub.add_parser("all", help="run every scenario of a folder")
    p_all.add_argument("--dir", type=Path, default=SCENARIO_DIR)
    args = ap.parse_args(argv)

    if args.cmd == "demo":
        paths = [SCENARIO_DIR / "nominal.yaml"]
    elif args.cmd == "run":
        paths = args.scenarios
    else:
        paths = sorted(args.dir.glob("*.yaml"))
    results = []
    t0 = time.perf_counter()
    for path in paths:
        r = run_scenario(path, out_root=args.out, progress=not args.no_progress, mcu_path=args.mcu)
        results.append(r)
        print(f"{r.scenario.name}: {r.outcome}, {'PASS' if r.passed else 'FAIL'} "
              f"({r.sim_time_s:.1f} s simulated in {r.wall_time_s:.2f} s, {r.speed_factor:.0f}x real time)")
        if args.cmd != "all" or not r.passed:
            _print_checks(r)
        print(f"  report: {r.report_path}")
    print()
    print_summary(results)
    if len(results) > 1:
        print(f"{sum(r.passed for r in results)}/{len(results)} scenarios passed "
              f"in {time.perf_counter() - t0:.1f} s")
    return 0 if all(r.passed for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
