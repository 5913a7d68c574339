# The HIL rig (issue 5, docs/hil.md): the firmware on the simulated MCU (firmware/port/sim)
# in lockstep with the plant, the host link session on simulated time, scenarios, reports.
#   make mission-demo   the nominal mission from 10 m; summary table and report path
#   make hil            every scenario in hil/scenarios (nominal and one per fault)
RIG_PY := PYTHONPATH=$(ROOT)/hil:$(ROOT)/host $(PY) -m oibar_hil.rig

# The rig's pytest suite (tests/hil_rig) runs the simulated MCU built by firmware-host.
TEST_DEPS += firmware-host

.PHONY: mission-demo hil scenarios

mission-demo: firmware-host gen ## the nominal refuelling mission on the HIL rig (10 m to separation), summary + report
	@$(RIG_PY) demo

hil: firmware-host gen ## run every HIL scenario (nominal + faults), summary table, reports in build/hil/
	@$(RIG_PY) all

scenarios: hil ## same as `make hil`
