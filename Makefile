# OIBAR front door. `make demo` and `make test` do all set-up themselves (scripts/setup.sh).
# `make help` lists the targets.

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := help

ROOT       := $(abspath .)
VENV       := $(ROOT)/.venv
PY         := $(VENV)/bin/python
BUILD      := $(ROOT)/build
GEN_C      := $(BUILD)/gen/c
GEN_PY     := $(ROOT)/host/oibar/_generated
FW_HOST    := $(BUILD)/fw-host
# Your own Unity / nanopb sources: make test UNITY_DIR=/path NANOPB_DIR=/path
UNITY_DIR  ?=
NANOPB_DIR ?=
UNITY_SRC  := $(or $(UNITY_DIR),$(ROOT)/.cache/src/unity)
NANOPB_SRC := $(or $(NANOPB_DIR),$(ROOT)/.cache/src/nanopb)
JOBS       ?= $(shell nproc)
# The Python packages `make setup` installs: a profile of requirements/profiles.conf. flight (the
# host software alone), demo (the simulated rig, no torch; `make demo` and the rig's targets),
# train (`make train` and the other model targets) or test (everything, the default). A venv set
# up for a larger profile serves the smaller ones; `make demo SETUP_PROFILE=test` overrides.
SETUP_PROFILE ?= test

PROTO      := proto/oibar.proto
PROTO_OPTS := proto/oibar.options

# Each part may bring its own targets in mk/<part>.mk; what `make test` must build first for
# that part goes into TEST_DEPS there.
TEST_DEPS  :=
-include mk/*.mk

.PHONY: help setup gen lint firmware-host test test-c test-py golden demo clean distclean

help: ## list the targets
	@grep -hE '^[a-zA-Z_-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-14s %s\n", $$1, $$2}'

setup: ## install what is missing (Debian packages, .venv, Unity and nanopb sources); SETUP_PROFILE=flight|demo|train|test
	@UNITY_DIR='$(UNITY_DIR)' NANOPB_DIR='$(NANOPB_DIR)' SETUP_PROFILE='$(SETUP_PROFILE)' bash scripts/setup.sh

# --- code generation (at build time, never committed) -------------------------------------
$(GEN_C)/oibar.pb.c $(GEN_C)/oibar.pb.h &: $(PROTO) $(PROTO_OPTS) | setup
	@mkdir -p $(GEN_C)
	@cd proto && nanopb_generator.py -q -D $(GEN_C) -f oibar.options oibar.proto

# The .pyi stub types the generated messages for mypy (`make lint`).
$(GEN_PY)/oibar_pb2.py $(GEN_PY)/oibar_pb2.pyi &: $(PROTO) | setup
	@mkdir -p $(GEN_PY)
	@protoc -Iproto --python_out=$(GEN_PY) --pyi_out=$(GEN_PY) $(PROTO)
	@touch $(GEN_PY)/__init__.py

gen: $(GEN_C)/oibar.pb.c $(GEN_PY)/oibar_pb2.py $(GEN_PY)/oibar_pb2.pyi ## generate the C (nanopb) and Python (protoc) code from proto/

# --- firmware, host build (tests, tools, simulated MCU) -----------------------------------
firmware-host: gen ## build the firmware libraries, tools and Unity suites for this machine (ASan+UBSan)
	@cmake -S firmware -B $(FW_HOST) -DCMAKE_BUILD_TYPE=Debug -DOIBAR_GEN_DIR=$(GEN_C) \
	  -DNANOPB_DIR=$(NANOPB_SRC) -DUNITY_DIR=$(UNITY_SRC) >$(BUILD)/fw-host-configure.log \
	  || { cat $(BUILD)/fw-host-configure.log; exit 1; }
	@cmake --build $(FW_HOST) -j$(JOBS) -- --no-print-directory >$(BUILD)/fw-host-build.log 2>&1 \
	  || { cat $(BUILD)/fw-host-build.log; exit 1; }
	@echo "firmware-host: built in build/fw-host"

# --- lint and types -----------------------------------------------------------------------
# Settings in pyproject.toml (repository root). mypy is strict on oibar.link, oibar.nav and
# oibar.geometry and checks the rest of host/oibar leniently.
# LINT_FORMAT=0 skips the format check (while a change is half done); `ruff format .` fixes it.
LINT_FORMAT ?= 1
RUFF       := $(VENV)/bin/ruff
MYPY       := $(VENV)/bin/mypy

lint: gen ## ruff check, ruff format --check (when LINT_FORMAT=1) and mypy
	@echo "== ruff check" && $(RUFF) check --quiet $(ROOT) && echo "   no findings"
	@if [ "$(LINT_FORMAT)" = 1 ]; then echo "== ruff format --check" && $(RUFF) format --check --quiet $(ROOT) \
	  && echo "   formatted"; else echo "== ruff format --check: off (LINT_FORMAT=0)"; fi
	@echo "== mypy" && cd $(ROOT) && $(MYPY)

# --- tests --------------------------------------------------------------------------------
test: lint firmware-host gen $(TEST_DEPS) ## lint, then run every test suite (Unity for C, pytest for Python) and print the counts
	@$(PY) scripts/run_tests.py --fw-build $(FW_HOST)

test-c: firmware-host ## run only the firmware Unity suites
	@$(PY) scripts/run_tests.py --fw-build $(FW_HOST) --only c

test-py: gen $(TEST_DEPS) ## run only the pytest suites
	@$(PY) scripts/run_tests.py --fw-build $(FW_HOST) --only py

golden: firmware-host gen ## rewrite the golden link frames on purpose (C writes mcu_to_host, Python host_to_mcu)
	@OIBAR_GOLDEN_WRITE=1 $(FW_HOST)/tests/test_golden
	@OIBAR_GOLDEN_WRITE=1 $(PY) -m pytest -q -p no:cacheprovider tests/host/test_golden.py
	@git status --short tests/golden

# --- demo ---------------------------------------------------------------------------------
# No torch: the demo flies the exported ONNX model (SETUP_PROFILE applies to the prerequisites too).
demo: SETUP_PROFILE = demo
demo: firmware-host gen ## run the simulated mission end to end (sim MCU + rig), print a summary and the report path
	@$(PY) scripts/demo.py

clean: ## remove build outputs (keeps .venv and the source cache)
	rm -rf $(BUILD) $(GEN_PY)

distclean: clean ## also remove .venv and .cache
	rm -rf $(VENV) .cache
