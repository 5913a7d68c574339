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
    # FMEA RAM-STACK: the link-time reserve, with the run-time guard below.
    ld = _code(PORT / "stm32f405.ld")
    m = re.search(r"_min_stack_bytes\s*=\s*(\d+)K\s*;", ld)
    assert m and int(m.group(1)) >= 8, "the linker script no longer reserves 8 KiB of stack"
    assert re.search(r"ASSERT\s*\(\s*_estack\s*-\s*_end_static\s*>=\s*_min_stack_bytes", ld)


def test_watchdog_runs_on_its_own_lsi_clock() -> None:
    # FMEA CLOCK-HSE: behind the clock security system, a clock that dies in flight is caught by
    # the IWDG, which runs from its own LSI oscillator: started (0xCCCC) and never stopped.
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


def _body(code: str, signature: str) -> str:
    """The body of the function whose definition starts with ``signature`` (braces balanced)."""
    m = re.search(re.escape(signature) + r"\s*\{", code)
    assert m, f"{signature} not defined"
    i = m.end() - 1
    depth = 0
    for j in range(i, len(code)):
        depth += {"{": 1, "}": -1}.get(code[j], 0)
        if depth == 0:
            return code[i + 1 : j]
    raise AssertionError(f"{signature}: unbalanced braces")


def _vectors(startup: str) -> list[str]:
    """The entries of g_vectors, in order (``{ Name }`` or ``{ .stack_top = ... }``)."""
    table = startup[startup.index("g_vectors[") :]
    table = table[table.index("= {") + 3 : table.index("};")]
    return [e.strip() for e in re.findall(r"\{([^{}]*)\}", table)]


def test_clock_security_on_with_the_crystal() -> None:
    # FMEA CLOCK-HSE: CSS on once the core runs from the crystal (RCC_CR bit 19).
    regs = _code(PORT / "include" / "stm32f4_regs.h")
    assert re.search(r"#define\s+RCC_CR_CSSON\s+\(1u\s*<<\s*19\)", regs)
    assert re.search(r"#define\s+RCC_CIR_CSSF\s+\(1u\s*<<\s*7\)", regs)
    assert re.search(r"#define\s+RCC_CIR_CSSC\s+\(1u\s*<<\s*23\)", regs)
    init = _body(_code(PORT / "src" / "clock.c"), "void clock_init(clock_info_t *out)")
    assert re.search(r"RCC->CR\s*\|=\s*RCC_CR_CSSON", init), "clock_init never switches CSS on"


def test_nmi_vector_is_the_handler_that_safes_the_outputs() -> None:
    # FMEA CLOCK-HSE: the NMI (CSS) vector is NMI_Handler, which de-energises every output
    # (port_outputs_safe: valves, plane H-bridge, stepper enable) first, acknowledges CSSF and
    # resets (the next boot falls back to the HSI PLL and starts in FAULT).
    vectors = _vectors(_code(PORT / "src" / "startup.c"))
    assert vectors[2] == "NMI_Handler", vectors[:4]
    nmi = _body(_code(PORT / "src" / "clock.c"), "void NMI_Handler(void)")
    statements = [st.strip() for st in nmi.split(";") if st.strip()]
    assert statements[0] == "port_outputs_safe()", "NMI_Handler must safe the outputs first"
    assert re.search(r"RCC->CIR\s*=\s*RCC_CIR_CSSC", nmi)
    assert "port_fatal_reset(" in nmi
    gpio = _code(PORT / "src" / "hal_gpio.c")
    safe = _body(gpio, "void port_outputs_safe(void)")
    assert re.search(r"i\s*<\s*\(unsigned\)HAL_DO_COUNT", safe) and "drive(&k_do[i], false)" in safe
    hal_h = _code(ROOT / "firmware" / "hal" / "include" / "oibar" / "hal.h")
    do_enum = hal_h[hal_h.index("HAL_DO_LATCH_DIR") : hal_h.index("HAL_DO_COUNT")]
    assert "HAL_DO_SV_VALVE" in do_enum and "HAL_DO_TV_VALVE" in do_enum


def test_stack_guard_filled_at_reset_and_checked_every_tick() -> None:
    # FMEA RAM-STACK: canary words at the bottom of the stack region, written before main and
    # checked by the 1 kHz tick; a changed word resets with the outputs safe.
    ld = _code(PORT / "stm32f405.ld")
    guard = ld[ld.index(".stack_guard") :]
    assert re.search(r"_sstack_guard\s*=\s*\.\s*;\s*\.\s*=\s*\.\s*\+\s*32\s*;\s*_estack_guard", guard)
    assert ld.index(".noinit") < ld.index(".stack_guard") < ld.index("_end_static")
    startup = _code(PORT / "src" / "startup.c")
    reset = _body(startup, "void Reset_Handler(void)")
    assert reset.index("_sbss[i] = 0u") < reset.index("port_stack_guard_fill()") < reset.index("main()")
    check = _body(startup, "void port_stack_guard_check(void)")
    assert "PORT_STACK_CANARY" in check and "port_fatal_reset(PORT_NOTE_STACK_OVERFLOW" in check
    tick = _body(_code(PORT / "src" / "hal_core.c"), "void SysTick_Handler(void)")
    assert "port_stack_guard_check()" in tick
    port_h = _code(PORT / "include" / "port.h")
    assert re.search(r"#define\s+PORT_STACK_GUARD_WORDS\s+8u", port_h)


def test_simulated_watchdog_is_the_boards() -> None:
    # FMEA WDG-HANG: one number, HAL_WATCHDOG_TIMEOUT_MS (oibar/hal.h), for the board's IWDG and
    # the simulated MCU's default; the rig passes no --watchdog-ms of its own.
    hal_h = _code(ROOT / "firmware" / "hal" / "include" / "oibar" / "hal.h")
    assert re.search(r"#define\s+HAL_WATCHDOG_TIMEOUT_MS\s+250u", hal_h)
    core = _code(PORT / "src" / "hal_core.c")
    assert re.search(r"IWDG->RLR\s*=\s*HAL_WATCHDOG_TIMEOUT_MS\s*\*", core)
    sim = ROOT / "firmware" / "port" / "sim" / "src"
    assert re.search(r"s_wdg_timeout_ms\s*=\s*HAL_WATCHDOG_TIMEOUT_MS\s*;", _code(sim / "hal_sim.c"))
    assert re.search(r"options_t opt = \{\s*-1,\s*HAL_WATCHDOG_TIMEOUT_MS,", _code(sim / "main.c"))
    rig = (ROOT / "hil" / "oibar_hil" / "rig").resolve()
    assert re.search(r"watchdog_ms: int \| None = None", (rig / "scenario.py").read_text(encoding="utf-8"))
    assert re.search(r"watchdog_ms: int \| None = None", (rig / "lockstep.py").read_text(encoding="utf-8"))
