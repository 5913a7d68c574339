#!/usr/bin/env python3
"""The committed fuzzing corpus: what the long campaigns found, minimised, as seeds for every run.

`tests/fuzz/corpus.tar.gz` holds one folder per seed kind (`frame/`, `dispatch/`). The golden
vectors alone start the dispatcher target at a fraction of the coverage the 10-million campaign
reached; these inputs start it where the campaign ended, so the short run in `make test` spends
its executions in the deep states (transfer, separation, faults) instead of rediscovering them.

    python tests/fuzz/corpus.py unpack --out build/fuzz/seeds     (make_seeds.py does this)
    python tests/fuzz/corpus.py pack --build build/fuzz           (make fuzz-corpus)

`pack` merges what a campaign left in `<build>/corpus/<target>` with the current seeds, through
libFuzzer's `-merge=1` (the smallest set of inputs keeping every feature), and rewrites the
archive byte for byte reproducibly (sorted names, zero times and owners).
"""

from __future__ import annotations

import argparse
import gzip
import hashlib
import io
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ARCHIVE = Path(__file__).resolve().parent / "corpus.tar.gz"
# seed kind -> libFuzzer target
KINDS = {"frame": "fuzz_frame", "dispatch": "fuzz_dispatch"}
MAX_UNIT_BYTES = 64 * 1024  # far above any input libFuzzer keeps here (-max_len 4096)


class CorpusError(RuntimeError):
    """The archive is missing, unreadable or holds something other than seed files."""


def unpack(out: Path, archive: Path = ARCHIVE) -> dict[str, int]:
    """Write every unit into out/<kind>/corpus-<sha1>; return the count per kind."""
    try:
        tar = tarfile.open(archive, "r:gz")  # noqa: SIM115  (a with block below; this try only words the error)
    except (OSError, tarfile.TarError, EOFError) as exc:
        raise CorpusError(f"{archive}: not a readable .tar.gz ({exc})") from exc
    counts = {k: 0 for k in KINDS}
    with tar:
        try:
            members = tar.getmembers()
        except (OSError, tarfile.TarError, EOFError) as exc:
            raise CorpusError(f"{archive}: corrupt ({exc})") from exc
        for m in members:
            if m.isdir():
                continue
            kind, _, name = m.name.partition("/")
            # Only plain files one level down in a known kind: never a path outside `out`.
            if kind not in KINDS or not name or "/" in name or not m.isfile() or m.size > MAX_UNIT_BYTES:
                raise CorpusError(f"{archive}: unexpected member {m.name!r}")
            try:
                data = tar.extractfile(m).read()
            except (OSError, tarfile.TarError, EOFError) as exc:
                raise CorpusError(f"{archive}: corrupt at {m.name!r} ({exc})") from exc
            d = out / kind
            d.mkdir(parents=True, exist_ok=True)
            (d / f"corpus-{hashlib.sha1(data).hexdigest()}").write_bytes(data)
            counts[kind] += 1
    return counts


def _write_archive(folders: dict[str, Path], archive: Path) -> None:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for kind in sorted(folders):
            for f in sorted(folders[kind].iterdir()):
                data = f.read_bytes()
                info = tarfile.TarInfo(f"{kind}/{hashlib.sha1(data).hexdigest()}")
                info.size, info.mtime, info.mode = len(data), 0, 0o644
                tar.addfile(info, io.BytesIO(data))
    with (
        open(archive, "wb") as raw,
        gzip.GzipFile(fileobj=raw, mode="wb", compresslevel=9, mtime=0, filename="") as gz,
    ):
        gz.write(buf.getvalue())


def pack(build: Path, archive: Path = ARCHIVE) -> dict[str, int]:
    """Merge <build>/corpus/<target> and <build>/seeds/<kind> into a minimal set; write the archive."""
    counts = {}
    with tempfile.TemporaryDirectory() as tmp:
        merged = {}
        for kind, target in KINDS.items():
            exe = build / target
            sources = [d for d in (build / "corpus" / target, build / "seeds" / kind) if d.is_dir()]
            if not exe.exists() or not sources:
                raise CorpusError(f"{exe} or its corpus is missing: run `make fuzz-build` (and `make fuzz`)")
            out = Path(tmp) / kind
            out.mkdir()
            proc = subprocess.run(
                [str(exe), "-merge=1", str(out), *map(str, sources)], capture_output=True, text=True
            )
            if proc.returncode != 0:
                raise CorpusError(f"{target} -merge=1 failed:\n{proc.stderr[-2000:]}")
            merged[kind] = out
            counts[kind] = sum(1 for _ in out.iterdir())
            line = next(
                (ln for ln in proc.stderr.splitlines() if "MERGE-OUTER:" in ln and "new files" in ln), ""
            )
            print(f"corpus: {kind}: {counts[kind]} units ({line.split('MERGE-OUTER: ')[-1]})")
        _write_archive(merged, archive)
    print(f"corpus: wrote {archive} ({archive.stat().st_size:,} bytes)")
    return counts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    u = sub.add_parser("unpack", help="write the units into OUT/<kind>/")
    u.add_argument("--out", type=Path, required=True)
    p = sub.add_parser("pack", help="merge a campaign's corpus into the archive")
    p.add_argument("--build", type=Path, required=True)
    for s in (u, p):
        s.add_argument("--archive", type=Path, default=ARCHIVE)
    args = ap.parse_args()
    try:
        if args.cmd == "unpack":
            print("corpus:", ", ".join(f"{k} {n} units" for k, n in unpack(args.out, args.archive).items()))
        else:
            pack(args.build, args.archive)
    except CorpusError as exc:
        sys.exit(f"corpus: error: {exc}")


if __name__ == "__main__":
    main()
