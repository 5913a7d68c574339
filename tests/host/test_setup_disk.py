"""scripts/setup.sh on a disk too full for the Python packages: a clear error before pip fetches
anything, and nothing installed (a CI run once failed inside pip's resolve with only "No space
left on device", which says nothing of what the set-up needs)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_a_fresh_venv_on_a_full_disk_stops_before_pip_with_what_it_needs(tmp_path):
    root = tmp_path / "clone"
    for d in ("scripts", "requirements"):
        shutil.copytree(REPO / d, root / d)
    for d in ("host", "hil", "models"):
        (root / d).mkdir()
        shutil.copy(REPO / d / "pyproject.toml", root / d / "pyproject.toml")
    env = {**os.environ, "PIP_NEED_MB": str(10**12)}  # more than any disk has free
    r = subprocess.run(
        ["bash", "scripts/setup.sh"], cwd=root, env=env, capture_output=True, text=True, timeout=300
    )
    assert r.returncode != 0
    assert "GB free on the disk of" in r.stderr and "nothing was installed" in r.stderr
    assert "resolving the pinned Python packages" not in r.stdout  # pip never ran
    site = list((root / ".venv").glob("lib/python*/site-packages"))
    assert site and not (site[0] / "torch").exists()
