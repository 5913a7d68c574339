# CMake toolchain file: GNU Arm Embedded (arm-none-eabi-gcc) for the STM32F405
# (Cortex-M4F). Used by the cross build in firmware/port/stm32f4/ (`make firmware-arm`).
set(CMAKE_SYSTEM_NAME Generic)
set(CMAKE_SYSTEM_PROCESSOR arm)

set(OIBAR_ARM_PREFIX arm-none-eabi- CACHE STRING "Prefix of the cross tools")
find_program(CMAKE_C_COMPILER ${OIBAR_ARM_PREFIX}gcc REQUIRED)
find_program(CMAKE_OBJCOPY ${OIBAR_ARM_PREFIX}objcopy REQUIRED)
find_program(CMAKE_SIZE ${OIBAR_ARM_PREFIX}size REQUIRED)
find_program(CMAKE_NM ${OIBAR_ARM_PREFIX}nm REQUIRED)
find_program(CMAKE_READELF ${OIBAR_ARM_PREFIX}readelf REQUIRED)
set(CMAKE_ASM_COMPILER ${CMAKE_C_COMPILER})

# The compiler check would try to link a hosted program; a static library is enough.
set(CMAKE_TRY_COMPILE_TARGET_TYPE STATIC_LIBRARY)

# Cortex-M4 with its single-precision FPU, hard-float calling convention.
set(OIBAR_ARM_CPU_FLAGS -mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16)
string(REPLACE ";" " " _oibar_cpu "${OIBAR_ARM_CPU_FLAGS}")
# Every object in its own section so --gc-sections can drop what is unused.
# -fno-short-enums: arm-none-eabi sizes an enum to its largest value, so a
# nanopb enum field would be one byte and an opcode the firmware does not
# know (say 999 from a newer host) would fail to decode and be dropped in
# silence, where the host build answers NACK_UNKNOWN_OPCODE. 32-bit enums
# keep both builds decoding alike. No enum crosses into newlib, so its
# short-enum objects are safe to link (hence --no-enum-size-warning).
set(CMAKE_C_FLAGS_INIT "${_oibar_cpu} -ffunction-sections -fdata-sections -fno-common -fno-short-enums")
set(CMAKE_EXE_LINKER_FLAGS_INIT
    "${_oibar_cpu} --specs=nano.specs -nostartfiles -Wl,--gc-sections -Wl,--no-enum-size-warning")
set(CMAKE_C_FLAGS_MINSIZEREL_INIT "-Os -g3")

# Never pick up the build machine's headers or libraries.
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE ONLY)
