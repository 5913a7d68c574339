"""PlatformIO extra script (platformio.ini, ``extra_scripts = pre:...``): the link flags of the
CMake build (firmware/cmake/arm-none-eabi.cmake, CMAKE_EXE_LINKER_FLAGS_INIT, and
firmware/port/stm32f4/CMakeLists.txt, target_link_options). PlatformIO passes build_flags to the
compiler only; without these the linker picks the soft-float newlib for a hard-float image.
tests/board/test_platformio_flags.py compares LINK_FLAGS with the CMake lists.
Not exercised here (PlatformIO cannot reach its registry from our machines)."""

LINK_FLAGS = [
    "-mcpu=cortex-m4",
    "-mthumb",
    "-mfloat-abi=hard",
    "-mfpu=fpv4-sp-d16",
    "--specs=nano.specs",
    "-nostartfiles",
    "-Wl,--gc-sections",
    "-Wl,--no-enum-size-warning",
    "-Wl,--cref",
    "-Wl,--print-memory-usage",
    "-Wl,--no-warn-rwx-segments",
]
LINK_LIBS = ["m"]

try:
    Import("env")  # type: ignore[name-defined]  # noqa: F821  (SCons, inside PlatformIO only)
except NameError:  # imported by the test, outside SCons
    pass
else:
    env.Append(LINKFLAGS=LINK_FLAGS, LIBS=LINK_LIBS)  # type: ignore[name-defined]  # noqa: F821
