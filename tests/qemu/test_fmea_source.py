"""FMEA rows (firmware/fmea.toml) whose property the host and QEMU cannot show by behaviour:
read from the board port's sources and linker script, as test_flight_image.py reads the image.
Each test fails when the protection it names is removed."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PORT = ROOT / "firmware" / "port" / "stm32f4"


def _code(path: Path) -> str:
    """The source without its comments (a protection must be code, not a sentence)."""
    text = path.read_text(encoding="utf-8")
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    return re.sub(r"//[^\n]*", "", text)


def test_linker_reserves_a_minimum_stack() -> None:
    # FMEA RAM-STACK: no run-time guard, so the link-time reserve is the only bound.
    ld = _code(PORT / "stm32f405.ld")
    m = re.search(r"_min_stack_bytes\s*=\s*(\d+)K\s*;", ld)
    assert m and int(m.group(1)) >= 8, "the linker script no longer reserves 8 KiB of stack"
    assert re.search(r"ASSERT\s*\(\s*_estack\s*-\s*_end_static\s*>=\s*_min_stack_bytes", ld)


def test_watchdog_runs_on_its_own_lsi_clock() -> None:
    # FMEA CLOCK-HSE: with CSS off, a clock that dies in flight is caught by the IWDG, which
    # runs from its own LSI oscillator: started (0xCCCC) and never stopped.
    core = _code(PORT / "src" / "hal_core.c")
    assert re.search(r"IWDG->KR\s*=\s*IWDG_KEY_START", core)
    regs = _code(PORT / "include" / "stm32f4_regs.h")
    assert re.search(r"#define\s+IWDG_KEY_START\s+0xCCCCu?", regs)


def test_clock_waits_are_bounded_with_an_hsi_fallback() -> None:
    # FMEA CLOCK-HSE at start: no crystal never hangs the boot (every wait counted), the core
    # falls back to the HSI.
    clock = _code(PORT / "src" / "clock.c")
    assert "while" not in re.sub(r"for\s*\([^)]*\)", "", clock), "an unbounded wait in clock.c"
    assert "CLOCK_SRC_HSI_PLL" in clock and "info_hsi(out, CLOCK_SRC_HSI)" in clock
