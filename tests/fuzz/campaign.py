#!/usr/bin/env python3
"""A resumable libFuzzer campaign: N parallel processes sharing one corpus, counted to a total.

    python tests/fuzz/campaign.py --build build/fuzz --target fuzz_dispatch --runs 10000000 --jobs 16

Each leg starts `--jobs` processes of the target on the shared corpus folder (libFuzzer reloads
what the others add), with the executions still missing split evenly between them, distinct
random seeds and logs in `<build>/logs/`. A live line shows executions, rate and ETA. When the
leg ends, its figures are appended to the ledger `<build>/campaign-<target>.json`; the next call
runs only what the ledger says is missing, so a campaign can be spread over sessions or
machines (carry the build folder). `--max-time-s` ends a leg early and cleanly.

Exit status: 0 when every process ended cleanly without a finding, 1 on a finding (crash, leak,
timeout, sanitizer report; the reproducer is saved under `<build>/artifacts/`), 2 on misuse.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import platform
import re
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

SEED_FOLDERS = {"fuzz_frame": "frame", "fuzz_dispatch": "dispatch"}
PROGRESS = re.compile(r"^#(\d+)\s+(?:pulse|NEW|REDUCE|INITED|DONE)\s.*?cov: (\d+)", re.M)
STAT = re.compile(r"^stat::(\w+):\s+(\d+)", re.M)
FINDING = re.compile(r"==\d+==ERROR|^SUMMARY: |deadly signal|Test unit written to", re.M)


@dataclass
class Leg:
    started_utc: str
    host: str
    cpus: int
    jobs: int
    executions: int
    wall_s: float
    rate_per_s: float
    coverage_edges: int
    corpus_units: int
    new_units: int
    peak_rss_mb: int
    findings: list[str]


def ledger_path(build: Path, target: str) -> Path:
    return build / f"campaign-{target}.json"


def load_ledger(path: Path, target: str) -> dict:
    if not path.exists():
        return {"target": target, "legs": []}
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        sys.exit(f"campaign: the ledger {path} is unreadable ({exc}); move it away or pass --fresh")
    if data.get("target") != target or not isinstance(data.get("legs"), list):
        sys.exit(f"campaign: {path} is not a ledger for {target}; move it away or pass --fresh")
    return data


def executed(ledger: dict) -> int:
    return sum(int(leg["executions"]) for leg in ledger["legs"])


def last_progress(log: Path) -> tuple[int, int]:
    """(executions, coverage) from the last progress line of a libFuzzer log, (0, 0) if none."""
    try:
        with log.open("rb") as f:
            f.seek(max(0, log.stat().st_size - 8192))
            tail = f.read().decode("utf-8", "replace")
    except OSError:
        return 0, 0
    hits = PROGRESS.findall(tail)
    return (int(hits[-1][0]), int(hits[-1][1])) if hits else (0, 0)


def fmt_s(s: float) -> str:
    s = int(max(0, s))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def run_leg(args: argparse.Namespace, runs_left: int) -> Leg:
    exe = args.build / args.target
    seeds = args.build / "seeds" / SEED_FOLDERS[args.target]
    corpus = args.build / "corpus" / args.target
    logs = args.build / "logs"
    artifacts = args.build / "artifacts"
    for d in (corpus, logs, artifacts):
        d.mkdir(parents=True, exist_ok=True)
    if not exe.exists() or not seeds.is_dir():
        sys.exit(f"campaign: {exe} or {seeds} is missing: run `make fuzz-build` first")

    jobs = max(1, min(args.jobs, runs_left))
    per_job = math.ceil(runs_left / jobs)
    units_before = len(list(corpus.iterdir()))
    base_seed = int(time.time()) % 100_000 * 100
    procs, log_paths = [], []
    started = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    print(
        f"== {args.target}: {runs_left:,} executions on {jobs} processes ({per_job:,} each), "
        f"corpus {corpus} ({units_before:,} units)",
        flush=True,
    )
    t0 = time.monotonic()
    for j in range(jobs):
        log = logs / f"{args.target}.{j:02d}.log"
        cmd = [
            str(exe),
            f"-runs={per_job}",
            f"-seed={base_seed + j + 1}",
            "-print_final_stats=1",
            "-reload=1",
            f"-artifact_prefix={artifacts}/{args.target}-",
            str(corpus),
            str(seeds),
        ]
        if args.max_time_s:
            cmd.insert(1, f"-max_total_time={int(args.max_time_s)}")
        log_paths.append(log)
        with log.open("w") as f:
            procs.append(subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, start_new_session=True))

    stopped = []

    def stop(*_: object) -> None:  # Ctrl-C: let each libFuzzer print its stats and exit
        stopped.append(True)
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)

    tty = sys.stdout.isatty()
    last_print = 0.0
    while any(p.poll() is None for p in procs):
        time.sleep(1.0)
        now = time.monotonic()
        if now - last_print >= (2.0 if tty else args.progress_s):
            last_print = now
            prog = [last_progress(p) for p in log_paths]
            done = sum(e for e, _ in prog)
            rate = done / max(now - t0, 1e-6)
            eta = (jobs * per_job - done) / rate if rate > 0 else float("inf")
            line = (
                f"[{args.target}] {done:,}/{jobs * per_job:,} exec "
                f"({100.0 * done / (jobs * per_job):5.1f} %)  {rate:,.0f}/s  "
                f"cov {max((c for _, c in prog), default=0)}  elapsed {fmt_s(now - t0)}  "
                f"eta {fmt_s(eta) if math.isfinite(eta) else '?'}  "
                f"running {sum(p.poll() is None for p in procs)}/{jobs}"
            )
            print(("\r" + line) if tty else line, end="" if tty else "\n", flush=True)
    if tty:
        print()
    wall = time.monotonic() - t0

    total, cov, rss, findings = 0, 0, 0, []
    for p, log in zip(procs, log_paths, strict=True):
        text = log.read_text(errors="replace")
        stats = {k: int(v) for k, v in STAT.findall(text)}
        total += stats.get("number_of_executed_units", 0)
        rss = max(rss, stats.get("peak_rss_mb", 0))
        cov = max(cov, last_progress(log)[1])
        interrupted = bool(stopped) and "run interrupted" in text
        if FINDING.search(text) or (p.returncode != 0 and not interrupted):
            findings.append(f"{log.name}: exit {p.returncode}")
    findings += [str(a) for a in sorted(artifacts.glob(f"{args.target}-*"))]
    return Leg(
        started_utc=started,
        host=platform.node(),
        cpus=os.cpu_count() or 0,
        jobs=jobs,
        executions=total,
        wall_s=round(wall, 1),
        rate_per_s=round(total / max(wall, 1e-6), 1),
        coverage_edges=cov,
        corpus_units=len(list(corpus.iterdir())),
        new_units=len(list(corpus.iterdir())) - units_before,
        peak_rss_mb=rss,
        findings=findings,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--build", type=Path, default=Path("build/fuzz"), help="the fuzz build folder")
    ap.add_argument("--target", required=True, choices=sorted(SEED_FOLDERS))
    ap.add_argument("--runs", type=int, default=10_000_000, help="executions the whole campaign must reach")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="parallel libFuzzer processes")
    ap.add_argument("--max-time-s", type=float, default=0.0, help="end this leg after so many seconds")
    ap.add_argument(
        "--progress-s", type=float, default=30.0, help="progress line period when not on a terminal"
    )
    ap.add_argument("--fresh", action="store_true", help="start a new ledger (the corpus is kept)")
    args = ap.parse_args(argv)
    if args.runs <= 0 or args.jobs <= 0:
        ap.error("--runs and --jobs must be positive")

    path = ledger_path(args.build, args.target)
    ledger = {"target": args.target, "legs": []} if args.fresh else load_ledger(path, args.target)
    left = args.runs - executed(ledger)
    if left <= 0:
        print(
            f"== {args.target}: the ledger already holds {executed(ledger):,} executions "
            f"(>= {args.runs:,}); nothing to run ({path})"
        )
        return 1 if any(leg["findings"] for leg in ledger["legs"]) else 0
    leg = run_leg(args, left)
    ledger["legs"].append(asdict(leg))
    ledger["executions"] = executed(ledger)
    ledger["findings"] = sum(len(x["findings"]) for x in ledger["legs"])
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(ledger, indent=2) + "\n")
    tmp.replace(path)
    print(
        f"== {args.target}: this leg {leg.executions:,} executions in {fmt_s(leg.wall_s)} "
        f"({leg.rate_per_s:,.0f}/s on {leg.jobs} processes), coverage {leg.coverage_edges} edges, "
        f"corpus {leg.corpus_units:,} units (+{leg.new_units:,}), peak RSS {leg.peak_rss_mb} MB; "
        f"campaign {ledger['executions']:,}/{args.runs:,}; findings: {len(leg.findings) or 'none'}"
    )
    for f in leg.findings:
        print(f"   finding: {f}")
    return 1 if leg.findings else 0


if __name__ == "__main__":
    sys.exit(main())
