"""A short, bounded libFuzzer campaign on the firmware, as part of `make test`.

The long campaign (10 million executions) is `make fuzz`; docs/reliability.md has its figures.
Targets are built by `make fuzz-build` (a prerequisite of `make test`).
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FUZZ = ROOT / "build" / "fuzz"

# (target, seed folder, executions): 10-20 s each on a 2-core machine.
CAMPAIGNS = [("fuzz_frame", "frame", 200_000), ("fuzz_dispatch", "dispatch", 10_000)]


@pytest.mark.parametrize("target,seeds,runs", CAMPAIGNS, ids=[c[0] for c in CAMPAIGNS])
def test_short_fuzz_campaign_finds_nothing(target, seeds, runs, tmp_path):
    exe, seed_dir = FUZZ / target, FUZZ / "seeds" / seeds
    if not exe.exists() or not seed_dir.is_dir():
        pytest.fail(f"{exe} or its seeds are missing: run `make fuzz-build`")
    proc = subprocess.run(
        [
            str(exe),
            f"-runs={runs}",
            "-seed=1",
            "-print_final_stats=1",
            f"-artifact_prefix={tmp_path}/",
            str(tmp_path),
            str(seed_dir),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]
    assert not list(tmp_path.glob("crash-*")) and not list(tmp_path.glob("leak-*"))
    done = re.search(r"stat::number_of_executed_units: (\d+)", log)
    assert done and int(done.group(1)) >= runs


def _inited_cov(exe: Path, *dirs: Path) -> int:
    """Edges covered after libFuzzer has run every unit of ``dirs`` once (no fuzzing)."""
    proc = subprocess.run([str(exe), "-runs=0", *map(str, dirs)], capture_output=True, text=True, timeout=300)
    found = re.search(r"INITED cov: (\d+)", proc.stderr)
    assert proc.returncode == 0 and found, proc.stderr[-2000:]
    return int(found.group(1))


@pytest.mark.parametrize("target,seeds,runs", CAMPAIGNS, ids=[c[0] for c in CAMPAIGNS])
def test_committed_corpus_starts_deeper_than_the_golden_seeds(target, seeds, runs, tmp_path):
    """tests/fuzz/corpus.tar.gz (the long campaigns, minimised) is unpacked into the seeds and
    reaches code the golden vectors alone do not (dispatcher: 588 -> 846 edges when packed)."""
    exe, seed_dir = FUZZ / target, FUZZ / "seeds" / seeds
    if not exe.exists() or not seed_dir.is_dir():
        pytest.fail(f"{exe} or its seeds are missing: run `make fuzz-build`")
    committed = [f for f in seed_dir.iterdir() if f.name.startswith("corpus-")]
    assert len(committed) > 100, "the committed corpus was not unpacked into the seeds"
    golden = tmp_path / "golden"
    golden.mkdir()
    for f in seed_dir.iterdir():
        if not f.name.startswith("corpus-"):
            (golden / f.name).write_bytes(f.read_bytes())
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    cov_golden = _inited_cov(exe, tmp_path / "a", golden)
    cov_all = _inited_cov(exe, tmp_path / "b", seed_dir)
    assert cov_all > cov_golden, (cov_all, cov_golden)


def test_corpus_archive_round_trip_and_bad_archives(tmp_path):
    sys.path.insert(0, str(ROOT / "tests" / "fuzz"))
    import corpus

    counts = corpus.unpack(tmp_path / "out")
    assert counts["dispatch"] > 100 and counts["frame"] > 100
    assert len(list((tmp_path / "out" / "dispatch").iterdir())) <= counts["dispatch"]

    cut = tmp_path / "cut.tar.gz"
    cut.write_bytes(corpus.ARCHIVE.read_bytes()[:5000])  # truncated download
    with pytest.raises(corpus.CorpusError):
        corpus.unpack(tmp_path / "o2", cut)
    import io
    import tarfile

    evil = tmp_path / "evil.tar.gz"
    with tarfile.open(evil, "w:gz") as tar:
        info = tarfile.TarInfo("dispatch/../../escape")
        info.size = 1
        tar.addfile(info, io.BytesIO(b"x"))
    with pytest.raises(corpus.CorpusError, match="unexpected member"):
        corpus.unpack(tmp_path / "o3", evil)
    assert not (tmp_path / "escape").exists()


# --- the resumable campaign runner (tests/fuzz/campaign.py) ---------------------------------


def _campaign(build: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [
            sys.executable,
            str(ROOT / "tests" / "fuzz" / "campaign.py"),
            "--build",
            str(build),
            "--target",
            "fuzz_frame",
            "--progress-s",
            "1",
            *args,
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )


def _ledger(build: Path) -> dict:
    return json.loads((build / "campaign-fuzz_frame.json").read_text())


@pytest.fixture
def campaign_build(tmp_path: Path) -> Path:
    exe, seeds = FUZZ / "fuzz_frame", FUZZ / "seeds" / "frame"
    if not exe.exists() or not seeds.is_dir():
        pytest.fail(f"{exe} or its seeds are missing: run `make fuzz-build`")
    (tmp_path / "seeds").mkdir()
    (tmp_path / "fuzz_frame").symlink_to(exe)
    (tmp_path / "seeds" / "frame").symlink_to(seeds)
    return tmp_path


def test_campaign_counts_parallel_executions_and_resumes_from_its_ledger(campaign_build):
    first = _campaign(campaign_build, "--runs", "3000", "--jobs", "2")
    assert first.returncode == 0, first.stdout + first.stderr
    led = _ledger(campaign_build)
    assert len(led["legs"]) == 1 and led["legs"][0]["jobs"] == 2
    assert led["executions"] >= 3000 and led["findings"] == 0
    assert (campaign_build / "logs" / "fuzz_frame.01.log").exists()
    assert any((campaign_build / "corpus" / "fuzz_frame").iterdir())

    # A larger goal runs only what is missing, on the corpus the first leg left.
    second = _campaign(campaign_build, "--runs", "5000", "--jobs", "2")
    assert second.returncode == 0, second.stdout + second.stderr
    led = _ledger(campaign_build)
    assert len(led["legs"]) == 2
    assert 5000 - 3002 <= led["legs"][1]["executions"] <= 5000 - 3000 + 2
    assert led["executions"] >= 5000

    # Reached already: nothing runs, the ledger stays as it is.
    again = _campaign(campaign_build, "--runs", "4000")
    assert again.returncode == 0 and "nothing to run" in again.stdout
    assert len(_ledger(campaign_build)["legs"]) == 2


def test_campaign_reports_a_finding_and_fails(campaign_build):
    # A stand-in target that behaves like libFuzzer after a sanitizer report.
    fake = campaign_build / "fuzz_frame"
    fake.unlink()
    fake.write_text(
        "#!/bin/sh\necho '#1\tINITED cov: 3 ft: 3 corp: 1/1b exec/s: 0 rss: 1Mb'\n"
        "echo '==42==ERROR: AddressSanitizer: heap-buffer-overflow'\n"
        "echo 'stat::number_of_executed_units: 7'\nexit 1\n"
    )
    fake.chmod(0o755)
    r = _campaign(campaign_build, "--runs", "100", "--jobs", "2")
    assert r.returncode == 1
    assert "finding: fuzz_frame.00.log: exit 1" in r.stdout
    led = _ledger(campaign_build)
    assert led["findings"] == 2 and led["executions"] == 14


def test_campaign_refuses_a_corrupt_ledger(campaign_build):
    (campaign_build / "campaign-fuzz_frame.json").write_text("{not json")
    r = _campaign(campaign_build, "--runs", "100")
    assert r.returncode != 0 and "unreadable" in r.stderr
    assert (campaign_build / "campaign-fuzz_frame.json").read_text() == "{not json"
