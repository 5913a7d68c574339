"""`make flash` (issue 59, item 4): OpenOCD through an ST-LINK, the .elf (so the parameter
sectors survive), a clear message when the tool or the board is missing, never part of
`make test`. No board here: OpenOCD is replaced by a missing name and by a stub that fails."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _make(*args: str) -> subprocess.CompletedProcess[str]:
    if shutil.which("make") is None:
        pytest.skip("make not installed")
    return subprocess.run(
        ["make", "--no-print-directory", *args], cwd=ROOT, capture_output=True, text=True, timeout=600
    )


def test_missing_openocd_fails_first_with_the_install_command() -> None:
    r = _make("flash", "OPENOCD=oibar-no-such-openocd")
    assert r.returncode != 0
    assert "'oibar-no-such-openocd' not found" in r.stderr and "apt-get install openocd" in r.stderr
    assert "Nothing was built" in r.stderr


def test_missing_board_fails_with_what_to_check(tmp_path: Path) -> None:
    if not (ROOT / "build" / "fw-arm" / "oibar_stm32f4.elf").is_file():
        pytest.skip("build/fw-arm not built (make firmware-arm)")
    stub = tmp_path / "openocd"
    log = tmp_path / "args"
    stub.write_text(f'#!/bin/sh\necho "$@" > {log}\necho "Error: open failed" >&2\nexit 1\n')
    stub.chmod(0o755)
    r = _make("flash", f"OPENOCD={stub}", "JOBS=1")
    assert r.returncode != 0
    assert "could not program the board" in r.stderr and "ST-LINK" in r.stderr
    args = log.read_text()
    # The ST-LINK and the STM32F4 target; the .elf, verified, so sectors 1-2 are not erased.
    assert "interface/stlink.cfg" in args and "target/stm32f4x.cfg" in args
    assert "program" in args and "oibar_stm32f4.elf verify reset exit" in args


def test_flash_is_not_part_of_make_test() -> None:
    r = _make("-pq", "help")
    deps = next(line for line in r.stdout.splitlines() if line.startswith("test:"))
    assert "flash" not in deps.split()[1:]
