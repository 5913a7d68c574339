# The STM32F405 image (firmware/port/stm32f4) and its test under QEMU (tests/qemu).
# Two images from the same sources: the flight image (build/fw-arm) and the emulator image
# (build/fw-arm-qemu, -DOIBAR_QEMU=ON: QEMU's RCC stub and TXE-less USART workarounds), which
# only `make qemu-test` boots. docs/hardware.md.

FW_ARM         := $(BUILD)/fw-arm
FW_ARM_QEMU    := $(BUILD)/fw-arm-qemu
ARM_TOOLCHAIN  := $(ROOT)/firmware/cmake/arm-none-eabi.cmake
# Reported in the handshake; `make firmware-arm FW_BUILD_ID=...` overrides it.
FW_BUILD_ID    ?= $(shell git -C $(ROOT) describe --always --dirty --tags 2>/dev/null || echo unknown)

.PHONY: firmware-arm firmware-arm-qemu qemu-test

firmware-arm: gen ## cross-build the STM32F405 image (build/fw-arm: .elf .bin .hex) and print its size report
	@mkdir -p $(FW_ARM)
	@cmake -S firmware/port/stm32f4 -B $(FW_ARM) -DCMAKE_TOOLCHAIN_FILE=$(ARM_TOOLCHAIN) \
	  -DCMAKE_BUILD_TYPE=MinSizeRel -DOIBAR_GEN_DIR=$(GEN_C) -DNANOPB_DIR=$(NANOPB_SRC) \
	  -DOIBAR_BUILD_ID='$(FW_BUILD_ID)' >$(BUILD)/fw-arm-configure.log \
	  || { cat $(BUILD)/fw-arm-configure.log; exit 1; }
	@cmake --build $(FW_ARM) -j$(JOBS) -- --no-print-directory >$(BUILD)/fw-arm-build.log 2>&1 \
	  || { cat $(BUILD)/fw-arm-build.log; exit 1; }
	@cat $(FW_ARM)/size-report.txt

firmware-arm-qemu: gen ## cross-build the emulator image (build/fw-arm-qemu, OIBAR_QEMU=ON) that qemu-test boots
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
