# The property test through the link layer (tests/firmware/test_link_property.c, issue 16):
# `make test` runs 100,000 steps with a fresh seed (printed); this runs the long variant.
#   make property-link-long                                 10 million steps, fresh seed
#   make property-link-long LINK_PROPERTY_SEED=123456       replay a failing run's seed
LINK_PROPERTY_STEPS ?= 10000000
LINK_PROPERTY_SEED  ?=

.PHONY: property-link-long

property-link-long: firmware-host ## link-layer property test, long run (LINK_PROPERTY_STEPS=1e7; LINK_PROPERTY_SEED=n to replay)
	@OIBAR_LINK_PROPERTY_STEPS=$(LINK_PROPERTY_STEPS) OIBAR_LINK_PROPERTY_SEED=$(LINK_PROPERTY_SEED) \
	  $(FW_HOST)/tests/test_link_property
