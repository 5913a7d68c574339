# Benchmarks (issue 10): every figure of docs/benchmarks.md measured on this machine, with the
# machine, the versions, the targets and the gaps: pose inference per backbone (float32 / INT8),
# the navigation cycle, the HIL speed factor, the renderer and data-set writer, the STM32F405
# image per module and the step interrupt's cost (callgrind), the link over a pty and QEMU.
#   make bench                                  everything (~15 min on 2 cores, progress printed)
#   make bench BENCH_ARGS=--quick               a ~1 min smoke run (short time boxes, a subset)
#   make bench BENCH_ARGS='--only pose,link'    some sections (see `--list`)
# Also writes build/bench/benchmarks.json (every row with its raw numbers).
BENCH_ARGS ?=
BENCH_PY   := OIBAR_FW_BUILD=$(FW_HOST) OIBAR_GEN_C=$(GEN_C) OIBAR_NANOPB_DIR=$(NANOPB_SRC) \
  PYTHONPATH=$(ROOT)/bench:$(ROOT)/models:$(ROOT)/hil:$(ROOT)/host $(PY) -m oibar_bench

.PHONY: bench

bench: firmware-host firmware-arm firmware-arm-qemu gen ## measure every figure into docs/benchmarks.md (~15 min; BENCH_ARGS=--quick for ~1 min)
	@$(BENCH_PY) $(BENCH_ARGS)
