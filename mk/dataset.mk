# Synthetic data set (hil/oibar_hil): the paper's 12 sequences into data/synthetic (git-ignored).
DATASET_DIR ?= $(ROOT)/data/synthetic
DATASET_ARGS ?=

.PHONY: dataset

# Rendering needs the simulator, not torch (Makefile, SETUP_PROFILE).
dataset dataset-train dataset-val dataset-envelope dataset-train-dr: SETUP_PROFILE = demo

dataset: setup ## render the 12 synthetic sequences into data/synthetic (resumable; DATASET_ARGS="--seqs 1,8")
	@$(PY) -m oibar_hil.dataset --out $(DATASET_DIR) --workers $(JOBS) $(DATASET_ARGS)

# The keypoint model's scene sets (issue 15), from the committed spec files in models/scenes/:
# train (96 scenes) and validation (22 scenes) are our own, disjoint from each other and from the
# paper's test sequences 1 and 8 (`make dataset DATASET_ARGS="--seqs 1,8"` renders those).
# SHARD=i/N renders every N-th scene from the i-th, for batch schedulers.
# TRAIN_SPEC=models/scenes/train_turned.json adds the 24 turned runs of the 2026-11-27 study.
# TRAIN_SPEC=models/scenes/train_sunfill.json adds to those 80 runs at every Sun the split allows (stage 18).
# TRAIN_SPEC=models/scenes/train_nearaxis.json adds to those 24 runs that wander only 0.06-0.15 m off the axis (stages 20, 21).
# TRAIN_SPEC=models/scenes/train_sunwander.json: train_turned.json, the near-axis runs and the Sun-filled looks, half off the axis (stage 23).
SHARD ?=
TRAIN_SPEC ?= models/scenes/train.json
.PHONY: dataset-train dataset-val
dataset-train: setup ## render the training scenes (TRAIN_SPEC, default models/scenes/train.json) into data/train (resumable; SHARD=i/N)
	@$(PY) -m oibar_hil.dataset --out $(ROOT)/data/train --spec $(TRAIN_SPEC) --workers $(JOBS) $(if $(SHARD),--shard $(SHARD))

# The domain-randomised training scenes (issue 58, part 3): 288 scenes, each in a look drawn by
# oibar_hil.randomize (materials, lamps, backdrop, vignetting, lens distortion), every 24th frame
# (~43k frames, train.json's size class). Our renderer only: no model trains on a Mitsuba frame.
.PHONY: dataset-train-dr
dataset-train-dr: setup ## render the domain-randomised training scenes (models/scenes/train_dr.json) into data/train_dr (resumable; SHARD=i/N)
	@$(PY) -m oibar_hil.dataset --out $(ROOT)/data/train_dr --spec models/scenes/train_dr.json --workers $(JOBS) $(if $(SHARD),--shard $(SHARD))

dataset-val: setup ## render the validation scenes (models/scenes/val.json) into data/val (resumable; SHARD=i/N)
	@$(PY) -m oibar_hil.dataset --out $(ROOT)/data/val --spec models/scenes/val.json --workers $(JOBS) $(if $(SHARD),--shard $(SHARD))

# The validation looks of the second renderer (issue 58): six validation scenes drawn by Mitsuba 3
# with our materials and lights, and in the lab's look. One process (Mitsuba threads itself);
# about 2 s (lab, perlin) to 7 s (iss) a frame on 2 cores, 30-40 min for both.
.PHONY: dataset-looks
dataset-looks: SETUP_PROFILE = looks
dataset-looks: setup ## render the Mitsuba validation looks (models/scenes/val_mitsuba.json, val_lab.json) into data/ (resumable)
	@$(PY) -m oibar_hil.dataset --out $(ROOT)/data/val_lab --spec models/scenes/val_lab.json --workers 1
	@$(PY) -m oibar_hil.dataset --out $(ROOT)/data/val_mitsuba --spec models/scenes/val_mitsuba.json --workers 1

# The roll sweep (validation): one approach at 13 rolls about the docking axis, our renderer, 401
# frames, under a minute on 2 cores; `kp_evaluate --sets val_roll` reads it (docs/model_card.md).
.PHONY: dataset-val-roll
dataset-val-roll: SETUP_PROFILE = demo
dataset-val-roll: setup ## render the roll sweep (models/scenes/val_roll.json) into data/val_roll
	@$(PY) -m oibar_hil.dataset --out $(ROOT)/data/val_roll --spec models/scenes/val_roll.json --workers $(JOBS)

# THE FROZEN TEST SET (issue 58, part 6): six scenes of their own seeds, off-axis, turned and rolled
# approaches, in our renderer (every 4th frame) and in Mitsuba's two looks (every 48th frame).
# Never used for a choice; `make eval-test-frozen` reads it once per shipped model.
.PHONY: dataset-test-frozen dataset-test-frozen-looks
dataset-test-frozen: SETUP_PROFILE = demo
dataset-test-frozen: setup ## render the frozen test set, our renderer (models/scenes/test_frozen.json) into data/test_frozen
	@$(PY) -m oibar_hil.dataset --out $(ROOT)/data/test_frozen --spec models/scenes/test_frozen.json --workers $(JOBS)
dataset-test-frozen-looks: SETUP_PROFILE = looks
dataset-test-frozen-looks: setup ## render the frozen test set's Mitsuba looks (test_frozen_mitsuba.json, test_frozen_lab.json) into data/
	@$(PY) -m oibar_hil.dataset --out $(ROOT)/data/test_frozen_lab --spec models/scenes/test_frozen_lab.json --workers 1
	@$(PY) -m oibar_hil.dataset --out $(ROOT)/data/test_frozen_mitsuba --spec models/scenes/test_frozen_mitsuba.json --workers 1
