# Coverage-guided fuzzing of the firmware (libFuzzer + ASan + UBSan, clang).
#   make fuzz                      10 million executions per target (the documented campaign)
#   make fuzz FUZZ_RUNS=100000     a shorter run
# `make test` runs a short bounded campaign through tests/fuzz/test_fuzz_short.py.
FUZZ_BUILD  := $(BUILD)/fuzz
FUZZ_RUNS   ?= 10000000
FUZZ_TARGETS := fuzz_frame fuzz_dispatch
FUZZ_CFLAGS := -g -O1 -std=c11 -fsanitize=fuzzer,address,undefined -fno-sanitize-recover=all \
  -Wall -Wextra -Werror -Wno-unused-parameter \
  -Ifirmware/link/include -Ifirmware/app/include -Ifirmware/hal/include \
  -Itests/firmware/support -isystem $(GEN_C) -isystem $(NANOPB_SRC)
FUZZ_LIB_SRCS = $(wildcard firmware/link/src/*.c firmware/app/src/*.c) tests/firmware/support/fake_hal.c
FUZZ_EXT_SRCS = $(NANOPB_SRC)/pb_common.c $(NANOPB_SRC)/pb_encode.c $(NANOPB_SRC)/pb_decode.c $(GEN_C)/oibar.pb.c

TEST_DEPS += fuzz-build

.PHONY: fuzz-build fuzz

$(FUZZ_BUILD)/%: tests/fuzz/%.c $(FUZZ_LIB_SRCS) $(GEN_C)/oibar.pb.c | setup
	@mkdir -p $(FUZZ_BUILD)
	@clang $(FUZZ_CFLAGS) -o $@ $< $(FUZZ_LIB_SRCS) $(FUZZ_EXT_SRCS)

$(FUZZ_BUILD)/seeds/.stamp: tests/fuzz/make_seeds.py $(wildcard tests/golden/*/*.hex) $(GEN_PY)/oibar_pb2.py
	@$(PY) tests/fuzz/make_seeds.py --out $(FUZZ_BUILD)/seeds
	@touch $@

fuzz-build: gen $(addprefix $(FUZZ_BUILD)/,$(FUZZ_TARGETS)) $(FUZZ_BUILD)/seeds/.stamp ## build the libFuzzer targets and their seed corpora

fuzz: fuzz-build ## fuzz the firmware frame decoder and dispatcher (FUZZ_RUNS executions each)
	@for t in $(FUZZ_TARGETS); do \
	  mkdir -p $(FUZZ_BUILD)/corpus/$$t; \
	  echo "== $$t: $(FUZZ_RUNS) runs"; \
	  $(FUZZ_BUILD)/$$t -runs=$(FUZZ_RUNS) -print_final_stats=1 -artifact_prefix=$(FUZZ_BUILD)/crash- \
	    $(FUZZ_BUILD)/corpus/$$t $(FUZZ_BUILD)/seeds/$${t#fuzz_} 2>&1 | tee $(FUZZ_BUILD)/$$t.log | \
	    grep -E '^(#[0-9]+ +(DONE|pulse)|stat::|==[0-9]+==ERROR|SUMMARY)' ; \
	  test $${PIPESTATUS[0]} -eq 0 || exit 1; \
	done
