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
