"""Parameter persistence on the STM32F405 (issue 59, item 3), where QEMU cannot show it:
netduinoplus2 has no flash controller. Read from the linked flight image (build/fw-arm) and
the driver's source instead, as test_flight_image.py does:

- sectors 1 and 2 (0x08004000..0x0800BFFF) are reserved: no loadable byte lands there, the
  vector table sits in sector 0 and the code from sector 3;
- the erase/program wait runs from RAM (.ramfunc), calls nothing, and reloads the watchdog
  while it polls BSY;
- the driver erases sectors 1 and 2 by number with PSIZE x32 and polls BSY;
- the build check itself fails an image that overlaps the sectors.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FLIGHT = ROOT / "build" / "fw-arm"
ELF = FLIGHT / "oibar_stm32f4.elf"
DRIVER = ROOT / "firmware" / "port" / "stm32f4" / "src" / "hal_flash.c"
LDSCRIPT = ROOT / "firmware" / "port" / "stm32f4" / "stm32f405.ld"
CHECK = ROOT / "firmware" / "port" / "stm32f4" / "check_image.cmake"

PARAM_START, PARAM_END = 0x08004000, 0x0800C000
RAM_START, RAM_END = 0x20000000, 0x20020000


def _tool(name: str) -> str:
    path = shutil.which(f"arm-none-eabi-{name}")
    if path is None:
        pytest.skip(f"arm-none-eabi-{name} not installed")
    return path


def _elf() -> Path:
    if not ELF.is_file():
        pytest.skip(f"{ELF} missing: run `make firmware-arm`")
    return ELF


def _symbols() -> dict[str, int]:
    out = subprocess.run([_tool("nm"), str(_elf())], check=True, capture_output=True, text=True).stdout
    syms = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3:
            syms[parts[2]] = int(parts[0], 16)
    return syms


def _loads() -> list[tuple[int, int]]:
    """(physical address, file size) of every LOAD program header."""
    out = subprocess.run(
        [_tool("readelf"), "-lW", str(_elf())], check=True, capture_output=True, text=True
    ).stdout
    rows = re.findall(r"^\s*LOAD\s+0x[0-9a-f]+\s+0x[0-9a-f]+\s+(0x[0-9a-f]+)\s+(0x[0-9a-f]+)", out, re.M)
    assert rows, out
    return [(int(a, 16), int(n, 16)) for a, n in rows]


def test_parameter_sectors_hold_no_byte_of_the_image() -> None:
    syms = _symbols()
    assert (syms["_param_flash_start"], syms["_param_flash_end"]) == (PARAM_START, PARAM_END)
    for addr, size in _loads():
        if size:
            assert addr + size <= PARAM_START or addr >= PARAM_END, f"LOAD at {addr:#x}+{size:#x}"
    # The vector table in sector 0 (where the core boots from), the code from sector 3 on.
    assert syms["g_vectors"] == 0x08000000
    assert syms["Reset_Handler"] & ~1 >= PARAM_END and syms["main"] & ~1 >= PARAM_END


def test_flash_wait_runs_from_ram_and_calls_nothing() -> None:
    syms = _symbols()
    fn = syms["port_flash_ram_wait"] & ~1
    assert RAM_START <= fn < RAM_END, f"port_flash_ram_wait at {fn:#x}"
    # Copied by the reset handler's .data loop: its load address is in flash, after the code.
    assert any(addr >= PARAM_END and size and addr < 0x08100000 for addr, size in _loads())
    dis = subprocess.run(
        [_tool("objdump"), "-d", "-j", ".data", str(_elf())], check=True, capture_output=True, text=True
    ).stdout
    body = dis.split("<port_flash_ram_wait>:", 1)[1].split("\n\n", 1)[0]
    # No call and no branch out: everything it executes (and its literal pool) is in RAM.
    assert not re.search(r"\bblx?\b", body), body
    for target in re.findall(
        r"\bb(?:\.n|\.w|eq|ne|pl|mi|cs|cc|hi|ls|ge|lt|gt|le)?(?:\.n|\.w)?\s+([0-9a-f]{8})\b", body
    ):
        assert RAM_START <= int(target, 16) < RAM_END, body
    # It reloads the IWDG (key 0xAAAA) inside the BSY poll.
    assert "0xaaaa" in body.lower()


def test_driver_erases_sectors_1_and_2_with_psize_x32_and_polls_bsy() -> None:
    src = DRIVER.read_text()
    assert re.search(r"#define PARAM_FLASH_BASE 0x08004000u", src)
    assert re.search(r"#define PARAM_FIRST_SECTOR 1u", src)
    assert "FLASH->KEYR = FLASH_KEY1" in src and "FLASH->KEYR = FLASH_KEY2" in src
    assert "FLASH_CR_SER | (snb << FLASH_CR_SNB_POS)" in src and "FLASH_CR_STRT" in src
    assert src.count("FLASH_CR_PSIZE_X32") >= 2  # erase and program
    assert "FLASH_CR_PG" in src and "FLASH_SR_BSY" in src
    assert re.search(r'__attribute__\(\(section\("\.ramfunc"\)', src)
    # Interrupts masked around each operation: a vector fetched from flash would stall.
    assert src.count("hal_critical_enter()") >= 2
    regs = (ROOT / "firmware/port/stm32f4/include/stm32f4_regs.h").read_text()
    for name, value in {
        "FLASH_KEY1": "0x45670123u",
        "FLASH_KEY2": "0xCDEF89ABu",
        "FLASH_CR_PSIZE_X32": "(2u << 8)",
        "FLASH_CR_SER": "(1u << 1)",
        "FLASH_CR_STRT": "(1u << 16)",
        "FLASH_SR_BSY": "(1u << 16)",
    }.items():
        assert re.search(rf"#define {name} {re.escape(value)}", regs), name
    ld = LDSCRIPT.read_text()
    assert re.search(r"PARAMS \(r\)\s*: ORIGIN = 0x08004000, LENGTH = 32K", ld)
    assert "*(.ramfunc .ramfunc.*)" in ld


def test_build_check_refuses_an_image_in_the_parameter_sectors(tmp_path: Path) -> None:
    """check_image.cmake on an image linked with code at 0x08004000 must fail."""
    gcc, cmake = _tool("gcc"), shutil.which("cmake")
    if cmake is None:
        pytest.skip("cmake not installed")
    src = tmp_path / "t.c"
    src.write_text("void Reset_Handler(void); void Reset_Handler(void) { for (;;) {} }\n")
    ld = tmp_path / "t.ld"
    ld.write_text(
        "MEMORY { FLASH (rx) : ORIGIN = 0x08004000, LENGTH = 64K }\n"
        "ENTRY(Reset_Handler)\n"
        "_param_flash_start = 0x08004000; _param_flash_end = 0x0800C000;\n"
        "SECTIONS { .text : { *(.text*) } > FLASH }\n"
    )
    elf = tmp_path / "bad.elf"
    subprocess.run(
        [gcc, "-mcpu=cortex-m4", "-mthumb", "-nostdlib", "-T", str(ld), str(src), "-o", str(elf)],
        check=True,
        capture_output=True,
    )
    args = [
        cmake,
        f"-DELF={elf}",
        f"-DOUT_DIR={tmp_path}",
        f"-DOBJCOPY={_tool('objcopy')}",
        f"-DSIZE={_tool('size')}",
        f"-DNM={_tool('nm')}",
        f"-DREADELF={_tool('readelf')}",
        "-DFLASH_BUDGET=65536",
        "-DRAM_BUDGET=16384",
        "-P",
        str(CHECK),
    ]
    r = subprocess.run(args, capture_output=True, text=True)
    assert r.returncode != 0 and "inside the parameter sectors" in r.stderr, r.stderr
    assert not (tmp_path / "size-report.txt").exists()
