"""python -m oibar_bench: run the registered measurements, write docs/benchmarks.md (+ JSON).

    python -m oibar_bench                        everything (~15 min on 2 cores)
    python -m oibar_bench --quick                short time boxes, a subset (~1 min)
    python -m oibar_bench --only pose,link       some sections (the page keeps the other tables)

A measurement that fails does not stop the others: its table says why, and the exit status
is 1 at the end.
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path

from . import firmware, hil, link, machine, nav, pose, pose_cold, render  # noqa: F401  (register the measurements)
from .core import REGISTRY, ROOT, SECTIONS, Context, Result, load_average
from .report import previous_blocks, write_json, write_markdown


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_bench", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short time boxes and a subset (smoke run, ~1 min)")
    ap.add_argument("--only", help=f"comma-separated sections or measurement keys ({', '.join(SECTIONS)})")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks.md", help="the Markdown page")
    ap.add_argument(
        "--json",
        type=Path,
        default=ROOT / "build" / "bench" / "benchmarks.json",
        help="every row with its raw numbers",
    )
    ap.add_argument("--threads", type=int, default=2, help="inference threads (the target machine's cores)")
    ap.add_argument("--banner", help="a line shown at the top of the page (e.g. why the run is special)")
    ap.add_argument("--list", action="store_true", help="list the measurements and exit")
    a = ap.parse_args(argv)

    if a.list:
        for m in sorted(REGISTRY, key=lambda m: (list(SECTIONS).index(m.section), m.order)):
            print(f"{m.key:<22} {m.title}")
        return 0
    # Page order: by section, then as registered.
    chosen = sorted(REGISTRY, key=lambda m: (list(SECTIONS).index(m.section), m.order))
    if a.only:
        wanted = [w.strip() for w in a.only.split(",") if w.strip()]
        unknown = [w for w in wanted if w not in SECTIONS and all(m.key != w for m in REGISTRY)]
        if unknown:
            ap.error(
                f"--only: unknown {unknown}; sections {list(SECTIONS)}, keys {[m.key for m in REGISTRY]}"
            )
        chosen = [m for m in chosen if m.section in wanted or m.key in wanted]

    command = "python -m oibar_bench " + " ".join(
        shlex.quote(x) for x in (argv if argv is not None else sys.argv[1:])
    )
    load_start = load_average()
    t0 = time.monotonic()
    tmp = Path(tempfile.mkdtemp(prefix="oibar-bench-"))
    ctx = Context(quick=a.quick, tmp=tmp, threads=a.threads)
    ctx.progress(f"{len(chosen)} measurements{' (quick mode)' if a.quick else ''}; load average {load_start}")
    info = machine.describe()
    results = []
    failed = []
    try:
        for i, m in enumerate(chosen, 1):
            ctx.progress(f"== {i}/{len(chosen)} {m.key}: {m.title}")
            load = load_average()
            t = time.monotonic()
            try:
                res = m.fn(ctx)
            except Exception as exc:  # one broken figure must not cost the others
                traceback.print_exc()
                failed.append(m.key)
                res = Result([], [f"**failed**: {type(exc).__name__}: {exc}"])
            results.append((m, res, {"seconds": time.monotonic() - t, "load": load}))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    duration = time.monotonic() - t0
    # An --only run keeps the page's other tables (they say so) instead of dropping them.
    keep = previous_blocks(a.out.read_text()) if a.only and a.out.is_file() else None
    write_markdown(
        a.out,
        info=info,
        results=results,
        keep_from=keep,
        registry=sorted(REGISTRY, key=lambda m: (list(SECTIONS).index(m.section), m.order)),
        quick=a.quick,
        banner=a.banner,
        command=command,
        duration_s=duration,
        load_start=load_start,
        load_end=load_average(),
    )
    write_json(a.json, info=info, results=results, quick=a.quick, duration_s=duration)
    ctx.progress(
        f"wrote {a.out} and {a.json} in {duration / 60:.1f} min"
        + (f"; FAILED: {', '.join(failed)}" if failed else "")
    )
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
