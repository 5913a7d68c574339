# Issue 59 item 1: the FMEA table (firmware/fmea.toml) is the source of docs/fmea.md.
#   make fmea         write docs/fmea.md from the table (tests/firmware/test_fmea.py checks both)
.PHONY: fmea

fmea: ## docs/fmea.md from firmware/fmea.toml (the failure-mode table); checks its tests exist
	@cd $(ROOT) && $(PY) -m scripts.fmea
