"""A short, bounded libFuzzer campaign on the firmware, as part of `make test`.

The long campaign (10 million executions) is `make fuzz`; docs/reliability.md has its figures.
Targets are built by `make fuzz-build` (a prerequisite of `make test`).
"""
from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FUZZ = ROOT / "build" / "fuzz"

# (target, seed folder, executions): about 20 s each on a 2-core machine.
CAMPAIGNS = [("fuzz_frame", "frame", 200_000), ("fuzz_dispatch", "dispatch", 400)]


@pytest.mark.parametrize("target,seeds,runs", CAMPAIGNS, ids=[c[0] for c in CAMPAIGNS])
def test_short_fuzz_campaign_finds_nothing(target, seeds, runs, tmp_path):
    exe, seed_dir = FUZZ / target, FUZZ / "seeds" / seeds
    if not exe.exists() or not seed_dir.is_dir():
        pytest.fail(f"{exe} or its seeds are missing: run `make fuzz-build`")
    proc = subprocess.run(
        [str(exe), f"-runs={runs}", "-seed=1", "-print_final_stats=1",
         f"-artifact_prefix={tmp_path}/", str(tmp_path), str(seed_dir)],
        capture_output=True, text=True, timeout=300)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]
    assert not list(tmp_path.glob("crash-*")) and not list(tmp_path.glob("leak-*"))
    done = re.search(r"stat::number_of_executed_units: (\d+)", log)
    assert done and int(done.group(1)) >= runs
