# Coverage-guided fuzzing of the firmware (libFuzzer + ASan + UBSan, clang).
#   make fuzz                                  10 million executions per target (the documented campaign)
#   make fuzz FUZZ_RUNS=100000                 a shorter run
#   make fuzz FUZZ_TARGETS=fuzz_dispatch FUZZ_JOBS=16
#                                              one target, on 16 parallel libFuzzer processes that share a corpus
# Campaigns resume: tests/fuzz/campaign.py keeps a ledger per target in build/fuzz/ and runs only
# the executions still missing (FUZZ_FRESH=1 starts a new ledger).
# `make test` runs a short bounded campaign through tests/fuzz/test_fuzz_short.py.
# `make fuzz-corpus` folds a campaign's corpus, minimised, into the committed seeds.
FUZZ_BUILD   := $(BUILD)/fuzz
FUZZ_OBJ     := $(FUZZ_BUILD)/obj
FUZZ_RUNS    ?= 10000000
FUZZ_JOBS    ?= $(JOBS)
FUZZ_TARGETS ?= fuzz_frame fuzz_dispatch
FUZZ_CFLAGS  := -g -O1 -std=c11 -fsanitize=address,undefined -fno-sanitize-recover=all \
  -Wall -Wextra -Werror -Wno-unused-parameter -MMD -MP \
  -Ifirmware/link/include -Ifirmware/app/include -Ifirmware/hal/include \
  -Itests/firmware/support -isystem $(GEN_C) -isystem $(NANOPB_SRC)

# Three kinds of code, three kinds of instrumentation (all of it under ASan + UBSan):
#  cmp   code whose branches depend on the input's bytes (framing, link, dispatcher, state
#        machine, safety checks, protobuf decoding): edge counters and comparison tracing, so
#        libFuzzer learns the opcodes and magic values it has to hit;
#  edge  firmware driven by time and the plant, not by the input (drivers, parameters, faults,
#        pressure loop, events), the telemetry encoder and nanopb's field iterator (walked
#        field by field for every telemetry frame): edge counters only. Comparison
#        tracing in these 1 kHz paths took 70 % of the dispatcher target's time (perf) and
#        taught the fuzzer nothing;
#  none  the test harness (fake HAL and plant model): not code under test, no coverage.
FUZZ_CMP_SRCS  = $(wildcard firmware/link/src/*.c) \
  $(addprefix firmware/app/src/,app.c app_link.c fsm.c safety.c) \
  $(NANOPB_SRC)/pb_decode.c $(GEN_C)/oibar.pb.c
FUZZ_EDGE_SRCS = $(filter-out $(FUZZ_CMP_SRCS),$(wildcard firmware/app/src/*.c)) \
  $(NANOPB_SRC)/pb_encode.c $(NANOPB_SRC)/pb_common.c
FUZZ_NONE_SRCS = tests/firmware/support/fake_hal.c

fuzz_objs = $(foreach s,$(2),$(FUZZ_OBJ)/$(1)/$(basename $(notdir $(s))).o)
FUZZ_OBJS = $(call fuzz_objs,cmp,$(FUZZ_CMP_SRCS)) $(call fuzz_objs,edge,$(FUZZ_EDGE_SRCS)) \
  $(call fuzz_objs,none,$(FUZZ_NONE_SRCS))

# The nanopb sources are fetched by `make setup`: on a fresh clone they appear only then.
$(addprefix $(NANOPB_SRC)/,pb_common.c pb_encode.c pb_decode.c): | setup ;

# One compile rule per source: $(1) kind, $(2) source, $(3) coverage flags.
define FUZZ_OBJ_RULE
$(FUZZ_OBJ)/$(1)/$(basename $(notdir $(2))).o: $(2) | setup gen
	@mkdir -p $$(@D)
	@clang $$(FUZZ_CFLAGS) $(3) -c -o $$@ $$<
endef
$(foreach s,$(FUZZ_CMP_SRCS),$(eval $(call FUZZ_OBJ_RULE,cmp,$(s),-fsanitize=fuzzer-no-link)))
$(foreach s,$(FUZZ_EDGE_SRCS),$(eval $(call FUZZ_OBJ_RULE,edge,$(s),-fsanitize=fuzzer-no-link -fno-sanitize-coverage=trace-cmp)))
$(foreach s,$(FUZZ_NONE_SRCS),$(eval $(call FUZZ_OBJ_RULE,none,$(s),)))
-include $(wildcard $(FUZZ_OBJ)/*/*.d $(FUZZ_BUILD)/*.d)

TEST_DEPS += fuzz-build

.PHONY: fuzz-build fuzz fuzz-corpus

$(FUZZ_BUILD)/%: tests/fuzz/%.c $(FUZZ_OBJS) | setup
	@mkdir -p $(FUZZ_BUILD)
	@clang $(FUZZ_CFLAGS) -fsanitize=fuzzer -o $@ $< $(FUZZ_OBJS)

$(FUZZ_BUILD)/seeds/.stamp: tests/fuzz/make_seeds.py tests/fuzz/corpus.py tests/fuzz/corpus.tar.gz \
                            $(wildcard tests/golden/*/*.hex) $(GEN_PY)/oibar_pb2.py
	@rm -rf $(FUZZ_BUILD)/seeds
	@$(PY) tests/fuzz/make_seeds.py --out $(FUZZ_BUILD)/seeds
	@touch $@

fuzz-build: gen $(addprefix $(FUZZ_BUILD)/,fuzz_frame fuzz_dispatch) $(FUZZ_BUILD)/seeds/.stamp ## build the libFuzzer targets and their seed corpora

# After a campaign: fold what it found into the committed seeds (tests/fuzz/corpus.tar.gz).
fuzz-corpus: fuzz-build ## merge build/fuzz/corpus into tests/fuzz/corpus.tar.gz (libFuzzer -merge=1)
	@$(PY) tests/fuzz/corpus.py pack --build $(FUZZ_BUILD)

fuzz: fuzz-build ## fuzz the firmware (FUZZ_RUNS executions per target on FUZZ_JOBS processes; resumes)
	@for t in $(FUZZ_TARGETS); do \
	  $(PY) tests/fuzz/campaign.py --build $(FUZZ_BUILD) --target $$t --runs $(FUZZ_RUNS) \
	    --jobs $(FUZZ_JOBS) $(if $(FUZZ_FRESH),--fresh) || exit 1; \
	done
