# Synthetic data set (hil/oibar_hil): the paper's 12 sequences into data/synthetic (git-ignored).
DATASET_DIR ?= $(ROOT)/data/synthetic
DATASET_ARGS ?=

.PHONY: dataset

dataset: setup ## render the 12 synthetic sequences into data/synthetic (resumable; DATASET_ARGS="--seqs 1,8")
	@$(PY) -m oibar_hil.dataset --out $(DATASET_DIR) --workers $(JOBS) $(DATASET_ARGS)
