# The STM32F405 image (firmware/port/stm32f4) and its test under QEMU (tests/qemu).
# Two images from the same sources: the flight image (build/fw-arm) and the emulator image
# (build/fw-arm-qemu, -DOIBAR_QEMU=ON: QEMU's RCC stub and TXE-less USART workarounds), which
# only `make qemu-test` boots. docs/hardware.md.

FW_ARM         := $(BUILD)/fw-arm
FW_ARM_QEMU    := $(BUILD)/fw-arm-qemu
ARM_TOOLCHAIN  := $(ROOT)/firmware/cmake/arm-none-eabi.cmake
# Reported in the handshake; `make firmware-arm FW_BUILD_ID=...` overrides it.
FW_BUILD_ID    ?= $(shell git -C $(ROOT) describe --always --dirty --tags 2>/dev/null || echo unknown)

.PHONY: firmware-arm firmware-arm-qemu qemu-test flash flash-tool

# The images need Debian's ARM toolchain, protoc and nanopb and the nanopb C runtime, no Python
# package: the `firmware` set-up profile (requirements/profiles.conf) makes and touches no .venv.
# Only the C code is generated (not the Python module, which is the host's).
firmware-arm firmware-arm-qemu flash: SETUP_PROFILE = firmware

firmware-arm: $(GEN_C)/oibar.pb.c $(GEN_C)/oibar.pb.h ## cross-build the STM32F405 image (build/fw-arm: .elf .bin .hex) and print its size report
	@mkdir -p $(FW_ARM)
	@cmake -S firmware/port/stm32f4 -B $(FW_ARM) -DCMAKE_TOOLCHAIN_FILE=$(ARM_TOOLCHAIN) \
	  -DCMAKE_BUILD_TYPE=MinSizeRel -DOIBAR_GEN_DIR=$(GEN_C) -DNANOPB_DIR=$(NANOPB_SRC) \
	  -DOIBAR_BUILD_ID='$(FW_BUILD_ID)' >$(BUILD)/fw-arm-configure.log \
	  || { cat $(BUILD)/fw-arm-configure.log; exit 1; }
	@cmake --build $(FW_ARM) -j$(JOBS) -- --no-print-directory >$(BUILD)/fw-arm-build.log 2>&1 \
	  || { cat $(BUILD)/fw-arm-build.log; exit 1; }
	@cat $(FW_ARM)/size-report.txt

firmware-arm-qemu: $(GEN_C)/oibar.pb.c $(GEN_C)/oibar.pb.h ## cross-build the emulator image (build/fw-arm-qemu, OIBAR_QEMU=ON) that qemu-test boots
	@mkdir -p $(FW_ARM_QEMU)
	@cmake -S firmware/port/stm32f4 -B $(FW_ARM_QEMU) -DCMAKE_TOOLCHAIN_FILE=$(ARM_TOOLCHAIN) \
	  -DCMAKE_BUILD_TYPE=MinSizeRel -DOIBAR_GEN_DIR=$(GEN_C) -DNANOPB_DIR=$(NANOPB_SRC) \
	  -DOIBAR_BUILD_ID='$(FW_BUILD_ID)' -DOIBAR_QEMU=ON >$(BUILD)/fw-arm-qemu-configure.log \
	  || { cat $(BUILD)/fw-arm-qemu-configure.log; exit 1; }
	@cmake --build $(FW_ARM_QEMU) -j$(JOBS) -- --no-print-directory >$(BUILD)/fw-arm-qemu-build.log 2>&1 \
	  || { cat $(BUILD)/fw-arm-qemu-build.log; exit 1; }

qemu-test: firmware-arm firmware-arm-qemu gen ## boot the emulator image on QEMU (netduinoplus2), run the link tests; check the flight image has no workaround
	@$(PY) -m pytest tests/qemu -q -p no:cacheprovider

TEST_DEPS += firmware-arm firmware-arm-qemu

# `make flash`: write the flight image to a board through an ST-LINK with OpenOCD (Debian:
# apt-get install openocd). It writes the .elf, so OpenOCD erases only the sectors the image
# occupies (0 and 3 on): the stored parameters in sectors 1-2 survive a reflash (the .bin spans
# them). Not part of `make test`. docs/hardware.md, "Flashing".
#   make flash OPENOCD=/path/to/openocd OPENOCD_INTERFACE=interface/stlink.cfg
OPENOCD           ?= openocd
OPENOCD_INTERFACE ?= interface/stlink.cfg
OPENOCD_TARGET    ?= target/stm32f4x.cfg

flash-tool:
	@command -v $(OPENOCD) >/dev/null 2>&1 || { \
	  echo "flash: '$(OPENOCD)' not found. Install OpenOCD (Debian: sudo apt-get install openocd)" >&2; \
	  echo "       or name it: make flash OPENOCD=/path/to/openocd. Nothing was built or written." >&2; exit 2; }

flash: flash-tool firmware-arm ## write the STM32F405 image to a board through an ST-LINK (OpenOCD; keeps the stored parameters)
	@$(OPENOCD) -f $(OPENOCD_INTERFACE) -f $(OPENOCD_TARGET) \
	  -c "program $(FW_ARM)/oibar_stm32f4.elf verify reset exit" || { \
	  echo "flash: OpenOCD could not program the board (its messages above). Check: the ST-LINK is" >&2; \
	  echo "       plugged in (lsusb: 0483:3748 V2, 0483:374b V2-1), SWDIO/SWCLK/GND/3V3 wired to the" >&2; \
	  echo "       board's SWD header, the board powered; another OpenOCD or st-util not running." >&2; exit 1; }
