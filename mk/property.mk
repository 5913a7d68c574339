# The firmware property test (tests/firmware/test_app_property.c) at length. `make test` runs it
# with 10^5 random steps and a fresh seed; this runs 10^7 (about 100 x longer), not part of
# `make test`. PROPERTY_SEED=<n> replays a run (the seed is printed first), PROPERTY_STEPS=<n>
# sets another length.
PROPERTY_STEPS ?= 10000000
PROPERTY_SEED  ?=

.PHONY: property-long

property-long: firmware-host ## the firmware property test with 10^7 random steps (PROPERTY_SEED=<n> to replay)
	@OIBAR_PROPERTY_STEPS=$(PROPERTY_STEPS) OIBAR_PROPERTY_SEED=$(PROPERTY_SEED) \
	  $(FW_HOST)/tests/test_app_property
