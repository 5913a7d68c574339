"""The OIBAR HIL rig (issue 5): the real firmware on a simulated MCU, in lockstep with a
simulated approach and mechanism, driven by the host's own navigation daemon cycle
(oibar.nav.daemon.NavDaemon.cycle) and link core (oibar.link.core, through LinkSession) on
simulated time.

Modules, one idea each:
  lockstep    the plant's end of the lockstep channel; the sim-MCU process
  wire        the serial cable, where link faults happen
  world       the service vehicle's relative 6-DOF motion
  mechanism   probe/drogue, latches, plane, valves, tanks and sensors
  faults      fault injection by scenario
  scenario    YAML scenario files
  navigation  the daemon's frame and navigator: ground truth, or the rendered camera + the host's navigator
  camera      the rendered camera (the synthetic world's renderer for the rig's current pose)
  runner      the lockstep loop, the daemon's cycle every guidance period, the measurements
  checks      requirements and expected outcomes, pass/fail
  report      the mission report (HTML + PNG plots)
  cli         `python -m oibar_hil.rig run|all|demo`
  sitl        `make sitl`: the real `oibar nav` program flies the mission against the rig
  soak        the short mission looped for an hour of simulated time (memory, deadlines)
  matrix      the fault matrix: every fault type in every phase
  capture_study, probe   studies: the capture envelope, the network's response to guidance
"""
