"""What flies: a fingerprint of the code that decides a mission's outcome (docs/campaign.md).

A campaign flies one version of the code. Its folder records, when it is made, a SHA-256 over
each group of sources below (relative paths hashed with the contents, in sorted order), one
over the groups, and the git commit for the record; a resume recomputes it and refuses a
checkout whose sources differ (``store.open_campaign``), unless ``--allow-code-change REASON``.

    host      host/oibar/**/*.py (not _generated/, not __pycache__/)
    firmware  firmware/**/*.c, firmware/**/*.h
    proto     proto/oibar.proto
    hil       hil/oibar_hil/**/*.py (the rig and this campaign runner)
    models    models/*.onnx (not the unshipped *.int8.onnx) and the ``--model`` file, cnn only
    sim_mcu   the simulated MCU binary the rig runs (its sha256, or "absent")

The git commit and whether the tree is dirty are recorded, not compared: a commit that leaves
these sources alone (documentation, tests) does not change what flies.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from oibar.hashing import sha256_file as _file_sha256
from oibar_hil.rig.runner import REPO_ROOT

# The root the groups' paths are taken from (tests point it at a tree of their own).
SOURCE_ROOT = REPO_ROOT
GROUP_LABELS = {
    "host": "host",
    "firmware": "firmware",
    "proto": "proto",
    "hil": "hil",
    "models": "models",
    "sim_mcu": "sim MCU binary",
}
EXCLUDED_DIRS = {"__pycache__", "_generated"}
SHORT_LEN = 12


def _files(root: Path, base: str, patterns: Iterable[str]) -> list[Path]:
    top = root / base
    if not top.is_dir():
        return []
    out: set[Path] = set()
    for pattern in patterns:
        for p in top.glob(pattern):
            rel = p.relative_to(root)
            if p.is_file() and not EXCLUDED_DIRS.intersection(rel.parts):
                out.add(p)
    return sorted(out, key=lambda p: p.relative_to(root).as_posix())


def _hash_files(root: Path, paths: Iterable[Path]) -> dict[str, Any]:
    h = hashlib.sha256()
    n = 0
    for p in paths:
        try:
            rel = p.relative_to(root).as_posix()
        except ValueError:  # a --model file outside the tree: its absolute path
            rel = str(p)
        data = p.read_bytes()
        h.update(f"{rel}\0{len(data)}\0".encode())
        h.update(data)
        n += 1
    return {"sha256": h.hexdigest(), "files": n}


def _git(root: Path) -> dict[str, Any] | None:
    """HEAD and whether tracked files differ from it; None without git or outside a checkout.
    Read-only: GIT_OPTIONAL_LOCKS=0 keeps `git status` from refreshing the index."""
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0"}
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, env=env, capture_output=True, text=True, timeout=20
        )
        if head.returncode != 0:
            return None
        status = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    dirty = bool(status.stdout.strip()) if status.returncode == 0 else None
    return {"commit": head.stdout.strip(), "dirty": dirty}


def _model_files(root: Path, model_path: str | Path | None) -> list[Path]:
    models = [p for p in _files(root, "models", ["*.onnx"]) if not p.name.endswith(".int8.onnx")]
    if model_path is not None:
        extra = Path(model_path).resolve()
        if extra.is_file() and extra not in {p.resolve() for p in models}:
            models.append(extra)
    return models


def _mcu_file(mcu_path: str | Path | None) -> Path:
    from oibar_hil.rig.fw_params import default_mcu_path

    return Path(mcu_path) if mcu_path else default_mcu_path()


def loaded_files_stamp(
    nav: str, mcu_path: str | Path | None = None, model_path: str | Path | None = None
) -> tuple[tuple[str, int, int], ...]:
    """(path, size, mtime_ns) of the files a mission loads afresh (the simulated MCU binary it
    starts, the models it opens), where the Python a worker imported is fixed for its life: a
    worker's cached fingerprint is good while this stays the same. Costs a few stat calls."""
    root = Path(SOURCE_ROOT)
    paths = [_mcu_file(mcu_path)] + (_model_files(root, model_path) if nav == "cnn" else [])
    out = []
    for p in paths:
        try:
            st = p.stat()
            out.append((str(p), st.st_size, st.st_mtime_ns))
        except OSError:
            out.append((str(p), -1, -1))
    return tuple(out)


def code_fingerprint(
    nav: str, mcu_path: str | Path | None = None, model_path: str | Path | None = None
) -> dict[str, Any]:
    """The fingerprint of what flies a campaign of navigation ``nav`` with this simulated MCU
    (default: the rig's) and model (cnn; default: the shipped ones)."""
    root = Path(SOURCE_ROOT)
    groups: dict[str, dict[str, Any]] = {
        "host": _hash_files(root, _files(root, "host/oibar", ["**/*.py"])),
        "firmware": _hash_files(root, _files(root, "firmware", ["**/*.c", "**/*.h"])),
        "proto": _hash_files(root, [p for p in [root / "proto" / "oibar.proto"] if p.is_file()]),
        "hil": _hash_files(root, _files(root, "hil/oibar_hil", ["**/*.py"])),
    }
    if nav == "cnn":
        groups["models"] = _hash_files(root, _model_files(root, model_path))
    mcu = _mcu_file(mcu_path)
    groups["sim_mcu"] = {"sha256": _file_sha256(mcu) if mcu.is_file() else "absent", "path": str(mcu)}
    overall = hashlib.sha256(
        json.dumps({k: g["sha256"] for k, g in groups.items()}, sort_keys=True).encode()
    ).hexdigest()
    return {"sha256": overall, "short": overall[:SHORT_LEN], "groups": groups, "git": _git(root)}


def changed_groups(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """The groups whose hash differs between two fingerprints, by their labels."""
    og, ng = old.get("groups", {}), new.get("groups", {})
    keys = list(GROUP_LABELS) + sorted((og.keys() | ng.keys()) - GROUP_LABELS.keys())
    return [
        GROUP_LABELS.get(k) or k for k in keys if og.get(k, {}).get("sha256") != ng.get(k, {}).get("sha256")
    ]


def describe(fp: dict[str, Any] | None) -> str:
    """`short` (git commit[:10], dirty) in a line."""
    if not fp:
        return "unknown"
    git = fp.get("git")
    if git:
        where = f"git {str(git.get('commit', ''))[:10]}" + (", dirty tree" if git.get("dirty") else "")
    else:
        where = "no git"
    return f"{fp.get('short', '?')} ({where})"
