"""What the figures were measured on: machine, OS, tool and library versions, git commit."""

from __future__ import annotations

import datetime as dt
import os
import platform
import re
import shutil
import subprocess
import sys
from importlib import metadata
from pathlib import Path

from oibar.machine import cpu_model

from .core import ROOT


def _first_line(cmd: list[str]) -> str:
    if shutil.which(cmd[0]) is None:
        return "not installed"
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"unknown ({exc})"
    text = (out.stdout or out.stderr).strip()
    return text.splitlines()[0] if text else "unknown"


def _ram_gib() -> float | None:
    try:
        m = re.search(r"^MemTotal:\s+(\d+) kB", Path("/proc/meminfo").read_text(), re.M)
        return int(m.group(1)) / 2**20 if m else None
    except OSError:
        return None


def _os_name() -> str:
    try:
        m = re.search(r'^PRETTY_NAME="?([^"\n]+)"?', Path("/etc/os-release").read_text(), re.M)
        if m:
            return f"{m.group(1)}, Linux {platform.release()}"
    except OSError:
        pass
    return platform.platform()


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "not installed"


def git_commit() -> str:
    try:
        sha = subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short=12", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=20,
        ).stdout.strip()
    except (OSError, subprocess.TimeoutExpired):
        return "unknown (no git)"
    if not sha:
        return "unknown (not a git checkout)"
    return sha + (" (with uncommitted changes)" if dirty else "")


def describe() -> dict:
    """Machine and versions, as (label -> text) pairs in page order."""
    ram = _ram_gib()
    return {
        "machine": {
            "CPU": cpu_model(),
            "cores (logical)": str(os.cpu_count()),
            "RAM": f"{ram:.1f} GiB" if ram else "unknown",
            "OS": _os_name(),
        },
        "versions": {
            "python": sys.version.split()[0],
            "onnxruntime": _version("onnxruntime"),
            "torch": _version("torch"),
            "numpy": _version("numpy"),
            "gcc": _first_line(["gcc", "--version"]),
            "arm-none-eabi-gcc": _first_line(["arm-none-eabi-gcc", "--version"]),
            "qemu-system-arm": _first_line(["qemu-system-arm", "--version"]),
            "valgrind": _first_line(["valgrind", "--version"]),
        },
        "run": {
            "date (UTC)": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M"),
            "git commit": git_commit(),
        },
    }
