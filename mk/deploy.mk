# Issue 60 item 6: the simulated MCU alone on a pty in real time, and `oibar nav` bench-tested
# against it with one command (hil/oibar_hil/sim_mcu.py, docs/hil.md).
#   make sim-mcu     the firmware and the simulated mechanism on a pty; prints the path; Ctrl-C ends
#   make bench-nav   the same, with the rendered camera, and `oibar nav` flying against it for
#                    BENCH_NAV_S seconds (the vehicle holds at 10 m: a link and loop check)
SIM_MCU_PY  := PYTHONPATH=$(ROOT)/hil:$(ROOT)/host $(PY) -m oibar_hil.sim_mcu
BENCH_NAV_S ?= 30

.PHONY: sim-mcu bench-nav

sim-mcu bench-nav: SETUP_PROFILE = demo

sim-mcu: firmware-host gen ## the simulated MCU (real firmware + simulated mechanism) alone on a pty, real time; Ctrl-C ends
	@$(SIM_MCU_PY) --pty

bench-nav: firmware-host gen ## `oibar nav` against the pty sim MCU and the rendered camera for BENCH_NAV_S (30) s; its log in runs/nav/
	@$(SIM_MCU_PY) --pty --frames -- $(VENV)/bin/oibar nav --port {pty} --camera {frames} \
	  --duration-s $(BENCH_NAV_S)
