"""The flight image (``make firmware-arm``, build/fw-arm) against the emulator image
(``make firmware-arm-qemu``, build/fw-arm-qemu): the emulator workarounds are in the second
only, and the board set-up that QEMU cannot show (brown-out level, watchdog frozen under the
debugger) is in both. Read from the images themselves (symbols and the bytes of .text).
"""

from __future__ import annotations

import shutil
import struct
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FLIGHT = ROOT / "build" / "fw-arm"
EMULATOR = ROOT / "build" / "fw-arm-qemu"
NAME = "oibar_stm32f4"

# Constants the code can only reach as literal words: the DBGMCU base (IWDG frozen
# while the core is halted) and the first option-key (brown-out level programmed).
DBGMCU_BASE = 0xE0042000  # APB1_FZ is at +8, reached from this base
FLASH_OPTKEY1 = 0x08192A3B


def _image(build: Path) -> bytes:
    path = build / f"{NAME}.bin"
    if not path.is_file():
        pytest.skip(f"{path} missing: run `make firmware-arm firmware-arm-qemu`")
    return path.read_bytes()


def _symbols(build: Path) -> set[str]:
    nm = shutil.which("arm-none-eabi-nm")
    if nm is None:
        pytest.skip("arm-none-eabi-nm not installed")
    out = subprocess.run([nm, str(build / f"{NAME}.elf")], check=True, capture_output=True, text=True)
    return {line.split()[-1] for line in out.stdout.splitlines() if line.strip()}


def _has_word(image: bytes, word: int) -> bool:
    return struct.pack("<I", word) in image


def _cache_option(build: Path, name: str) -> str:
    for line in (build / "CMakeCache.txt").read_text().splitlines():
        if line.startswith(f"{name}:"):
            return line.split("=", 1)[1]
    return ""


def test_flight_image_has_no_emulator_workaround() -> None:
    _image(FLIGHT)
    assert _cache_option(FLIGHT, "OIBAR_QEMU") in ("OFF", "")
    # The USART interrupt forced every millisecond (QEMU's USART raises no TXE interrupt).
    assert "port_uart_service_kick" not in _symbols(FLIGHT)


def test_emulator_image_carries_the_workarounds() -> None:
    _image(EMULATOR)
    assert _cache_option(EMULATOR, "OIBAR_QEMU") == "ON"
    assert "port_uart_service_kick" in _symbols(EMULATOR)


@pytest.mark.parametrize("build", [FLIGHT, EMULATOR], ids=["flight", "emulator"])
def test_watchdog_frozen_under_debugger_and_brownout_programmed(build: Path) -> None:
    image = _image(build)
    assert _has_word(image, DBGMCU_BASE)
    assert _has_word(image, FLASH_OPTKEY1)


# --- clock security and the stack guard (FMEA CLOCK-HSE, RAM-STACK), read from the image ------

RCC_CR_CSSON = 1 << 19
STACK_CANARY = 0x5AC4C0DE  # port.h PORT_STACK_CANARY
STACK_GUARD_BYTES = 32  # port.h PORT_STACK_GUARD_WORDS * 4


def _addresses(build: Path) -> dict[str, int]:
    nm = shutil.which("arm-none-eabi-nm")
    if nm is None:
        pytest.skip("arm-none-eabi-nm not installed")
    out = subprocess.run([nm, str(build / f"{NAME}.elf")], check=True, capture_output=True, text=True)
    found: dict[str, int] = {}
    for line in out.stdout.splitlines():
        parts = line.split()
        if len(parts) == 3:
            found[parts[2]] = int(parts[0], 16)
    return found


def _disassembly(build: Path, symbol: str) -> str:
    objdump = shutil.which("arm-none-eabi-objdump")
    if objdump is None:
        pytest.skip("arm-none-eabi-objdump not installed")
    out = subprocess.run(
        [objdump, "-d", f"--disassemble={symbol}", str(build / f"{NAME}.elf")],
        check=True,
        capture_output=True,
        text=True,
    )
    start = out.stdout.find(f"<{symbol}>:")
    assert start >= 0, f"{symbol} not in the image"
    return out.stdout[start:]


def _calls(asm: str) -> list[str]:
    """The functions a disassembled function calls (bl) or tail-calls (b.w), in order."""
    return [
        line.rsplit("<", 1)[1].rstrip(">")
        for line in asm.splitlines()
        if "\tbl\t" in line or "\tb.w\t" in line
    ]


@pytest.mark.parametrize("build", [FLIGHT, EMULATOR], ids=["flight", "emulator"])
def test_nmi_vector_points_at_the_clock_security_handler(build: Path) -> None:
    image = _image(build)
    nmi_vector = struct.unpack_from("<I", image, 2 * 4)[0]
    assert nmi_vector == _addresses(build)["NMI_Handler"] | 1, "the NMI vector is not NMI_Handler"


def test_clock_security_is_switched_on() -> None:
    _image(FLIGHT)
    asm = _disassembly(FLIGHT, "clock_init")
    assert f"#{RCC_CR_CSSON}" in asm, "clock_init never sets RCC_CR.CSSON"


def test_nmi_handler_safes_the_outputs_before_the_reset() -> None:
    _image(FLIGHT)
    calls = _calls(_disassembly(FLIGHT, "NMI_Handler"))
    assert "port_outputs_safe" in calls and "port_fatal_reset" in calls, calls
    assert calls.index("port_outputs_safe") < calls.index("port_fatal_reset"), calls


@pytest.mark.parametrize("build", [FLIGHT, EMULATOR], ids=["flight", "emulator"])
def test_stack_guard_lies_between_the_static_data_and_the_stack(build: Path) -> None:
    image = _image(build)
    sym = _addresses(build)
    lo, hi = sym["_sstack_guard"], sym["_estack_guard"]
    assert hi - lo == STACK_GUARD_BYTES
    assert sym["_ebss"] <= lo and hi <= sym["_end_static"] < sym["_estack"] - 8 * 1024
    ram_statics = [a for n, a in sym.items() if 0x20000000 <= a < lo and not n.startswith("_")]
    assert ram_statics and max(ram_statics) < lo, "a static variable lies in or above the guard"
    assert _has_word(image, STACK_CANARY), "the canary is never written"


@pytest.mark.parametrize("build", [FLIGHT, EMULATOR], ids=["flight", "emulator"])
def test_stack_guard_is_checked_every_tick_and_resets(build: Path) -> None:
    _image(build)
    assert "port_stack_guard_check" in _calls(_disassembly(build, "SysTick_Handler"))
    assert "port_fatal_reset" in _calls(_disassembly(build, "port_stack_guard_check"))
    reset = _disassembly(build, "Reset_Handler")
    assert "port_stack_guard_fill" in _calls(reset), "the reset handler never writes the guard"
