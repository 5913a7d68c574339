"""platformio.ini builds the board image with the CMake build's flags (issue 59, item 4).

PlatformIO cannot build here (its registry is out of reach), so both sides are parsed: the
CMake toolchain file and the stm32f4 CMakeLists on one side, platformio.ini and its extra
script (the link flags, which PlatformIO does not take from build_flags) on the other. The
hard-float ABI must reach the linker: that is the defect this test was written against.
"""

from __future__ import annotations

import ast
import configparser
import re
import shlex
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
TOOLCHAIN = ROOT / "firmware" / "cmake" / "arm-none-eabi.cmake"
PORT_CMAKE = ROOT / "firmware" / "port" / "stm32f4" / "CMakeLists.txt"
PIO_INI = ROOT / "platformio.ini"
HARD_FLOAT = {"-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16"}


def _cmake_set(text: str, name: str) -> list[str]:
    """The words of `set(NAME ...)` in a CMake file, ${OIBAR_ARM_CPU_FLAGS}/${_oibar_cpu} expanded."""
    m = re.search(rf"set\({re.escape(name)}\s+(.*?)\)\s*$", text, re.S | re.M)
    assert m, f"set({name} ...) not found"
    words = shlex.split(m.group(1).replace("\n", " "))
    out: list[str] = []
    for w in words:
        if "${" in w:
            m2 = re.search(r"set\(OIBAR_ARM_CPU_FLAGS\s+(.*?)\)\s*$", text, re.S | re.M)
            assert m2
            w = w.replace("${_oibar_cpu}", m2.group(1)).replace("${OIBAR_ARM_CPU_FLAGS}", m2.group(1))
        out += w.split()
    return [w for w in out if w not in ("CACHE", "STRING")]


def _cmake_block(text: str, command: str) -> list[str]:
    m = re.search(rf"{command}\(\$\{{IMAGE\}} PRIVATE(.*?)\)\n", text, re.S)
    assert m, command
    return shlex.split(m.group(1))


def cmake_flags() -> tuple[set[str], set[str], dict[str, str]]:
    tc = TOOLCHAIN.read_text()
    port = PORT_CMAKE.read_text()
    compile_ = set(_cmake_set(tc, "CMAKE_C_FLAGS_INIT")) | set(
        _cmake_set(tc, "CMAKE_C_FLAGS_MINSIZEREL_INIT")
    )
    assert re.search(r"set\(CMAKE_C_STANDARD 11\)", port) and re.search(
        r"set\(CMAKE_C_EXTENSIONS OFF\)", port
    )
    compile_.add("-std=c11")
    warnings = set(_cmake_set(port, "OIBAR_WARNINGS"))
    link = set(_cmake_set(tc, "CMAKE_EXE_LINKER_FLAGS_INIT"))
    link |= {f for f in _cmake_block(port, "target_link_options") if not f.startswith(("-T", "-Wl,-Map="))}
    libs = _cmake_block(port, "target_link_libraries")
    if "m" in libs:
        link.add("-lm")
    defines = {}
    for d in _cmake_block(port, "target_compile_definitions"):
        name, _, value = d.partition("=")
        defines[name] = value
    defines["PB_NO_ERRMSG"] = re.search(r"nanopb PUBLIC PB_NO_ERRMSG=(\d+)", port).group(1)
    return compile_ | warnings, link, defines


def pio_flags() -> tuple[set[str], set[str], dict[str, str]]:
    cfg = configparser.ConfigParser(interpolation=None, inline_comment_prefixes=(";",))
    cfg.read(PIO_INI)
    env = cfg["env:stm32f405"]
    compile_: set[str] = set()
    defines: dict[str, str] = {}
    for key in ("build_flags", "build_src_flags"):
        for line in env.get(key, "").splitlines():
            line = line.strip()
            if not line:
                continue
            if line.startswith("!"):  # the build id from git describe, as CMake's
                assert "OIBAR_BUILD_ID" in line
                defines["OIBAR_BUILD_ID"] = "<git describe>"
                continue
            for w in line.split():
                if w.startswith("-D"):
                    name, _, value = w[2:].partition("=")
                    defines[name] = value
                elif not w.startswith("-I"):
                    compile_.add(w)
    scripts = env.get("extra_scripts", "").split()
    script = next(s for s in scripts if s.endswith("pio_link_flags.py"))
    tree = ast.parse((ROOT / script.removeprefix("pre:")).read_text())
    consts = {
        t.id: ast.literal_eval(n.value)
        for n in tree.body
        if isinstance(n, ast.Assign)
        for t in n.targets
        if isinstance(t, ast.Name)
    }
    link = set(consts["LINK_FLAGS"]) | {f"-l{lib}" for lib in consts["LINK_LIBS"]}
    assert env["board_build.ldscript"] == "firmware/port/stm32f4/stm32f405.ld"
    return compile_, link, defines


def test_compile_flags_are_the_cmake_builds() -> None:
    cm, _, _ = cmake_flags()
    pio, _, _ = pio_flags()
    assert pio == cm, f"only in platformio.ini: {sorted(pio - cm)}; only in CMake: {sorted(cm - pio)}"


def test_link_flags_are_the_cmake_builds_hard_float_included() -> None:
    _, cm, _ = cmake_flags()
    _, pio, _ = pio_flags()
    assert cm >= HARD_FLOAT and pio >= HARD_FLOAT
    assert pio == cm, f"only in platformio: {sorted(pio - cm)}; only in CMake: {sorted(cm - pio)}"


def test_defines_are_the_cmake_builds() -> None:
    _, _, cm = cmake_flags()
    _, _, pio = pio_flags()
    assert set(pio) == set(cm)
    assert pio["BOARD_HSE_HZ"] == cm["BOARD_HSE_HZ"].replace("${OIBAR_HSE_HZ}", "8000000")
    assert pio["PB_NO_ERRMSG"] == cm["PB_NO_ERRMSG"] == "1"
    assert pio["OIBAR_QEMU"] == "0"  # the flight image, never the emulator's
    assert pio["OIBAR_FW_VERSION"] == '\\"0.1.0\\"'
    assert re.search(r"project\(oibar_stm32f4 VERSION 0\.1\.0", PORT_CMAKE.read_text())
