"""Reading a sequence folder written by oibar_hil.dataset (docs/synthetic.md): its manifest, the
files' hashes and the pose table. The one reader of that layout: the generator (resume, verify),
the training library (oibar_models.data) and the studies use it. numpy and the standard library
only, so reading a data set imports neither the renderer nor torch.

Sequence folder: manifest.json (written last: its presence marks the sequence complete; it lists
the SHA-256 of every file), poses.csv (one row per frame: frame, file, time_s, phase, tx_m..tz_m,
qw..qz, range_m, ...), frames/NNNNNN.jpg|png.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from oibar.dataset_format import read_pose_rows
from oibar.hashing import sha256_file

MANIFEST = "manifest.json"
POSES = "poses.csv"

_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"
_JPG_END = b"\xff\xd9"


class DatasetError(RuntimeError):
    """A data set on disk is missing, incomplete, inconsistent or corrupt; the message names the
    file at fault."""


def check_image_trailer(path: Path) -> str | None:
    """None if the file looks complete, else a reason. Cheap: reads the last bytes only."""
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        return "missing"
    if size < 16:
        return f"truncated ({size} bytes)"
    with open(path, "rb") as fh:
        head = fh.read(8)
        fh.seek(-12, os.SEEK_END)
        tail = fh.read(12)
    if path.suffix == ".png":
        if not head.startswith(b"\x89PNG"):
            return "not a PNG file"
        if tail != _PNG_END:
            return "truncated (no PNG IEND chunk)"
    elif path.suffix == ".jpg":
        if not head.startswith(b"\xff\xd8"):
            return "not a JPEG file"
        if not tail.endswith(_JPG_END):
            return "truncated (no JPEG end-of-image marker)"
    return None


def read_manifest(
    seq_dir: str | Path, required: Callable[[dict[str, Any]], object] | None = None
) -> dict[str, Any]:
    """The sequence's manifest. ``required`` (optional) reads the fields the caller needs; a
    KeyError/TypeError/ValueError there is reported as a corrupt manifest too."""
    seq_dir = Path(seq_dir)
    if not seq_dir.is_dir():
        raise DatasetError(f"{seq_dir}: sequence folder not found (render it with `make dataset`)")
    mpath = seq_dir / MANIFEST
    if not mpath.is_file():
        raise DatasetError(
            f"{mpath}: missing, so the sequence is incomplete "
            "(re-run `python -m oibar_hil.dataset` with the same arguments to resume)"
        )
    try:
        manifest: dict[str, Any] = json.loads(mpath.read_text())
        if required is not None:
            required(manifest)
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{mpath}: corrupt manifest ({type(exc).__name__}: {exc})") from exc
    return manifest


def verify_files(seq_dir: str | Path, manifest: dict[str, Any], check_trailers: bool = True) -> None:
    """Check every file the manifest lists: present, complete (image trailers) and the same
    SHA-256. Raises DatasetError naming the bad files (the first 10)."""
    seq_dir = Path(seq_dir)
    problems = []
    for name, digest in manifest.get("files", {}).items():
        path = seq_dir / name
        if not path.is_file():
            problems.append(f"{path}: missing")
            continue
        reason = check_image_trailer(path) if check_trailers and path.suffix in (".png", ".jpg") else None
        if reason is not None:
            problems.append(f"{path}: {reason}")
        elif sha256_file(path) != digest:
            problems.append(f"{path}: corrupt (SHA-256 differs from the manifest)")
    if problems:
        more = f" (and {len(problems) - 10} more)" if len(problems) > 10 else ""
        raise DatasetError(
            f"{len(problems)} bad file(s) in {seq_dir}:\n  " + "\n  ".join(problems[:10]) + more
        )


def read_pose_table(
    path: str | Path, numeric: Sequence[str], required: Sequence[str] = (), frames_limit: int | None = None
) -> tuple[list[dict[str, str]], np.ndarray]:
    """poses.csv -> (rows as dicts of strings, the ``numeric`` columns as a float array (N, C)).
    Checks that the ``required`` and ``numeric`` columns exist and parse; keeps the first
    ``frames_limit`` rows when given."""
    rows = read_pose_rows(
        path,
        (*required, *numeric),
        DatasetError,
        "a missing pose table: render the sequence with `make dataset`",
    )
    rows = rows[:frames_limit] if frames_limit else rows
    try:
        num = np.array([[float(r[c]) for c in numeric] for r in rows])
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{path}: non-numeric value ({exc})") from exc
    return rows, num
