# OibarNet (models/oibar_models, issue 7): training, ONNX export, evaluation.
# MODEL_CONFIG picks the experiment (one YAML per experiment under models/configs/).
MODEL_CONFIG ?= models/configs/oibarnet_lite.yaml
TRAIN_ARGS   ?=
EVAL_ARGS    ?=

.PHONY: train export eval

train: setup ## train OibarNet on `make dataset` output (resumes runs/<name>/; MODEL_CONFIG=..., TRAIN_ARGS="train.epochs=3")
	@$(PY) -m oibar_models.train --config $(MODEL_CONFIG) $(TRAIN_ARGS)

export: setup ## export the best checkpoint to ONNX with metadata and check it against PyTorch (models/<name>.onnx)
	@$(PY) -m oibar_models.export --config $(MODEL_CONFIG)

eval: setup ## evaluate the ONNX model on test sequences 1 and 8: tables, error plots, overlays, latency (runs/<name>/eval)
	@$(PY) -m oibar_models.evaluate --config $(MODEL_CONFIG) $(EVAL_ARGS)

ENVELOPE_DIR ?= $(ROOT)/data/envelope

.PHONY: dataset-envelope
dataset-envelope: setup ## render the envelope-mode test sequence (seq01_envelope) that `make eval` also reports
	@$(PY) -m oibar_hil.dataset --out $(ENVELOPE_DIR) --seqs 1 --envelope --workers $(JOBS)
