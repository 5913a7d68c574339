#!/usr/bin/env python3
"""Run every OIBAR test suite and print each one's counts, then one closing line.

C: every Unity executable `test_*` in the firmware host build, plus cppcheck on the firmware.
Python: pytest over tests/ (two runs at once over two groups of folders, counted per folder from
their JUnit XML reports).
The closing line reads `total: N passed, M failed` so CI and people see one verdict.
"""

from __future__ import annotations

import argparse
import collections
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
UNITY_SUMMARY = re.compile(r"^(\d+) Tests (\d+) Failures (\d+) Ignored", re.M)
UNITY_TIMEOUT_S = 300


def run_unity(build: Path) -> tuple[int, int]:
    suites = sorted(p for p in (build / "tests").glob("test_*") if p.is_file() and os.access(p, os.X_OK))
    if not suites:
        print(f"C: no Unity suites found in {build / 'tests'}", file=sys.stderr)
        return 0, 1
    print(f"== firmware (Unity, ASan+UBSan): {len(suites)} suites")
    passed = failed = 0
    for exe in suites:
        t0 = time.monotonic()
        try:
            proc = subprocess.run(
                [str(exe)], cwd=ROOT, capture_output=True, text=True, timeout=UNITY_TIMEOUT_S
            )
            out, rc = proc.stdout + proc.stderr, proc.returncode
        except subprocess.TimeoutExpired as exc:
            out, rc = f"{exc.stdout or ''}\nTIMEOUT after {UNITY_TIMEOUT_S} s", -1
        m = UNITY_SUMMARY.findall(out)
        if m and rc == 0:
            tests, fails, ignored = (int(x) for x in m[-1])
        else:
            tests, fails, ignored = (int(m[-1][0]) if m else 1), max(1, int(m[-1][1]) if m else 1), 0
        passed += tests - fails - ignored
        failed += fails
        verdict = "ok" if fails == 0 and rc == 0 else "FAILED"
        print(
            f"   {exe.name:<34} {tests:4d} tests {fails:3d} failures {ignored:2d} ignored"
            f"  {time.monotonic() - t0:6.2f} s  {verdict}"
        )
        if verdict != "ok":
            print("\n".join("      " + ln for ln in out.strip().splitlines()[-40:]))
    return passed, failed


def run_cppcheck() -> tuple[int, int]:
    """Static analysis of our firmware sources (not the third-party runtimes)."""
    if shutil.which("cppcheck") is None:
        print("== cppcheck: not installed (run `make setup`)", file=sys.stderr)
        return 0, 1
    parts = [
        p for p in ("link", "app", "hal", "port/sim", "port/stm32f4") if (ROOT / "firmware" / p).is_dir()
    ]
    includes = [f"-I{p}" for p in (ROOT / "firmware").glob("*/include")]
    includes += [f"-I{p}" for p in (ROOT / "firmware" / "port").glob("*/include")]
    cmd = [
        "cppcheck",
        "--quiet",
        "--enable=warning,style,performance,portability",
        "--error-exitcode=1",
        "--inline-suppr",
        "--std=c11",
        "--suppress=missingIncludeSystem",
        *includes,
        # the board image gets these from its build; any value will do for the analysis
        '-DOIBAR_FW_VERSION="0"',
        '-DOIBAR_BUILD_ID="0"',
        *[str(ROOT / "firmware" / p) for p in parts],
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    findings = proc.stderr.strip()
    ok = proc.returncode == 0 and not findings
    print(f"== cppcheck on firmware/{{{','.join(parts)}}}: {'no findings' if ok else 'FINDINGS'}")
    if not ok:
        print(findings)
    return (1, 0) if ok else (0, 1)


# pytest runs as two processes at once, one per group of test folders, so that both cores work
# (one pytest process keeps one core busy: 18 minutes of suites on 2 cores, 2026-12-02). The
# groups hold about the same time (fresh clone: hil_rig, fuzz and board about 9 minutes, the rest
# about 9); every folder under tests/ not named here goes to the second.
PYTEST_GROUPS = (("tests/hil_rig", "tests/fuzz", "tests/board"),)


def _pytest_groups() -> list[list[str]]:
    first = [f for f in PYTEST_GROUPS[0] if (ROOT / f).is_dir()]
    rest = sorted(
        str(p.relative_to(ROOT))
        for p in (ROOT / "tests").iterdir()
        if p.is_dir() and not p.name.startswith((".", "_")) and str(p.relative_to(ROOT)) not in first
    )
    return [g for g in (first, rest) if g]


def run_pytest(extra: list[str]) -> tuple[int, int]:
    with tempfile.TemporaryDirectory() as tmp:
        procs = []
        for i, folders in enumerate(_pytest_groups()):
            report, log = Path(tmp) / f"pytest{i}.xml", Path(tmp) / f"pytest{i}.log"
            cmd = [
                sys.executable,
                "-m",
                "pytest",
                *folders,
                "-q",
                "-p",
                "no:cacheprovider",
                f"--junitxml={report}",
                "-o",
                "junit_family=xunit1",
                *extra,
            ]
            print("== pytest: " + " ".join(cmd[3:]), flush=True)
            with open(log, "w") as out:
                procs.append(
                    (subprocess.Popen(cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT), report, log)
                )
        per_folder: dict[str, list[int]] = collections.defaultdict(lambda: [0, 0, 0])
        failed_runs = 0
        for proc, report, log in procs:
            rc = proc.wait()
            print(log.read_text(), end="", flush=True)  # each group's output whole, in order
            if not report.exists():
                print(f"pytest produced no report (exit {rc})", file=sys.stderr)
                failed_runs += 1
                continue
            before = sum(v[1] for v in per_folder.values())
            for case in ET.parse(report).iter("testcase"):
                # xunit1 reports carry the file; count per test folder (tests/host, tests/hil, ...).
                folder = str(Path(case.get("file", "?")).parent)
                outcome = 0
                if case.find("failure") is not None or case.find("error") is not None:
                    outcome = 1
                elif case.find("skipped") is not None:
                    outcome = 2
                per_folder[folder][outcome] += 1
            if rc not in (0, 1) and sum(v[1] for v in per_folder.values()) == before:
                failed_runs += 1  # interrupted, usage error, nothing collected...
    print("== pytest per folder")
    for folder, (ok, bad, skipped) in sorted(per_folder.items()):
        print(f"   {folder:<34} {ok:4d} passed {bad:3d} failed {skipped:3d} skipped")
    passed = sum(v[0] for v in per_folder.values())
    failed = sum(v[1] for v in per_folder.values()) + failed_runs
    return passed, failed


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fw-build", type=Path, required=True, help="firmware host build folder")
    ap.add_argument("--only", choices=("c", "py"), help="run only one language's suites")
    ap.add_argument("pytest_args", nargs="*", help="extra pytest arguments")
    args = ap.parse_args()

    t0 = time.monotonic()
    total_ok = total_bad = 0
    if args.only in (None, "c"):
        for ok, bad in (run_unity(args.fw_build), run_cppcheck()):
            total_ok, total_bad = total_ok + ok, total_bad + bad
    if args.only in (None, "py"):
        # Interop tests run the firmware's host-built tools (e.g. the link peer) from here.
        os.environ["OIBAR_FW_BUILD"] = str(args.fw_build.resolve())
        ok, bad = run_pytest(args.pytest_args)
        total_ok, total_bad = total_ok + ok, total_bad + bad
    print(f"== all suites in {time.monotonic() - t0:.0f} s")
    print(f"total: {total_ok} passed, {total_bad} failed")
    return 0 if total_bad == 0 and total_ok > 0 else 1


if __name__ == "__main__":
    sys.exit(main())
