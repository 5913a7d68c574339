"""The short version of the HIL fault matrix (`make fault-matrix` runs every cell): one
phase per fault and one fault per phase, each cell checked by the same code as the full
matrix (generic invariants + the cell's expected outcome), plus the matrix's bookkeeping."""

import pytest

from oibar_hil.rig import matrix as mx
from oibar_hil.rig.faults import FAULT_TYPES

# Every fault once, every phase at least once (and none of them the scenario of test_scenarios).
SUBSET = [
    ("link_loss", "approach"),
    ("bit_errors", "approach"),
    ("pressure_sensor_range", "reception"),
    ("latch_stall", "reception"),
    ("host_crash", "reception"),
    ("valve_stuck_open", "hard_docking"),
    ("watchdog_reset", "hard_docking"),
    ("pressure_sensor_stuck", "hard_docked"),
    ("actuator_jam", "hard_docked"),
    ("valve_stuck_closed", "transferring"),
    ("overpressure", "unmating"),
    # issue 16 (fw-drv): valve preconditions and sensor glitches, mid-fill
    ("latch_wire_break", "transferring"),
    ("adc_glitch", "transferring"),
    ("adc_glitch_run", "transferring"),
    # issue 16 (fw-link): the replay window
    ("replay", "transferring"),
    # issue 17 (rig): the host's own failures
    ("camera_unplugged", "approach"),
    ("slow_inference", "approach"),
    ("nav_hang", "hard_docked"),
    ("serial_unplugged", "unmating"),
    # issue 16 (fw-app): abort with slow valves, host-side parameter attack
    ("valve_slow_close", "transferring"),
    ("param_attack", "hard_docked"),
]


def test_subset_covers_every_fault_and_every_phase():
    # the FMEA's new modes (issue 59 item 5) in NEW_SUBSET below
    assert {f for f, _ in SUBSET + NEW_SUBSET} == set(FAULT_TYPES)
    assert {p for _, p in SUBSET} == set(mx.PHASE_KEYS)


def test_every_cell_has_an_expected_outcome_or_a_reason():
    cells = mx.all_cells()
    assert len(cells) == len(FAULT_TYPES) * len(mx.PHASES) >= 126
    for f, p in cells:
        e = mx.expectation(f, p)
        if isinstance(e, str):
            assert len(e) > 20, f"{f}@{p}: n.a. needs a reason"
            continue
        assert e.outcome in ("completed", "aborted", "safed")
        assert e.final_state == ("STATE_FAULT" if e.outcome == "safed" else "STATE_IDLE")
        sc = mx.cell_scenario(f, p, e)  # the scenario loader accepts it
        assert sc.faults[0].type == f and sc.faults[0].at_state.startswith("STATE_")
        # Nothing may vent, except where a cell states its own (small) bound and why: a valve
        # failing open with the couplings already half-mated vents until the firmware re-seats.
        bound = e.extra.get("fuel_lost_max_kg", mx.FUEL_LOST_MAX_KG)
        assert sc.expect["fuel_lost_max_kg"] == bound <= 0.010
        assert bound == mx.FUEL_LOST_MAX_KG or "vents" in e.why


def test_not_applicable_cells_are_reported_not_skipped():
    na = [c for c in mx.all_cells() if isinstance(mx.expectation(*c), str)]
    r = mx.run_cell(*na[0])
    assert r.status == "n.a." and r.reason
    table = mx.markdown([r])
    assert "n.a.¹" in table and "not run" in table


@pytest.mark.parametrize("fault,phase", SUBSET, ids=[f"{f}@{p}" for f, p in SUBSET])
def test_fault_matrix_cell(fault, phase, sim_mcu_path):
    r = mx.run_cell(fault, phase, str(sim_mcu_path))
    assert r.status == "pass", f"{fault}@{phase}: {r.reason}"
    ids = {c["id"] for c in r.checks}
    assert {
        "REQ-VALVES",
        "REQ-SAFE-END",
        "REQ-FORCE-HARD",
        "G-INJECTED",
        "G-END",
        "G-VALVES",
        "EXP-fuel_lost_max_kg",
        "EXP-faults",
        "EXP-outcome",
    } <= ids


def test_valve_failing_open_while_unmating_is_reseated_not_left_venting(sim_mcu_path):
    # Was the matrix's one unsafe cell: FAULT stopped the plane half-mated and the line vented
    # until the tank was empty (72 g in the run). The firmware now re-seats the plane.
    r = mx.run_cell("valve_stuck_open", "unmating", str(sim_mcu_path))
    assert r.status == "pass", r.reason
    assert r.fuel_lost_kg < 0.010


def test_one_adc_glitch_mid_fill_is_not_a_fault_but_a_run_is(sim_mcu_path):
    # Issue 16 item 9: one bad conversion used to close the valves and latch a range fault
    # mid-transfer; a run of them must still trip (bound 10 ms).
    one = mx.run_cell("adc_glitch", "transferring", str(sim_mcu_path))
    assert one.status == "pass" and one.outcome == "completed" and not one.faults_seen, one.reason
    run = mx.run_cell("adc_glitch_run", "transferring", str(sim_mcu_path))
    assert run.status == "pass" and "FAULT_PRESSURE_SENSOR_RANGE" in run.faults_seen, run.reason
    assert run.detect_s is not None and run.detect_s <= 0.05
    assert one.fuel_lost_kg == run.fuel_lost_kg == 0.0


def test_broken_latch_wire_is_detected_in_every_phase(sim_mcu_path):
    # Issue 16 item 4: the broken wire reads "not engaged" (never "engaged") and the pair's
    # implausible state is a fault that holds; nothing vents.
    for phase in mx.PHASE_KEYS:
        r = mx.run_cell("latch_wire_break", phase, str(sim_mcu_path))
        assert r.status == "pass", f"{phase}: {r.reason}"
        assert "FAULT_LATCH_SENSOR" in r.faults_seen and r.fuel_lost_kg == 0.0


def test_stuck_target_sensor_behind_a_line_sensor_failed_low_is_still_stopped_by_the_mcu(sim_mcu_path):
    # The double fault the line witness cannot see: the line's sensor stuck from power-up at the
    # 100 kPa the vented line held (latent: a closed line may read that), and the target tank's
    # sensor freezes mid-fill above it, so no lead shows. The supply tank drains into the real
    # target tank all the same, and SAFETY_RULE_FILL_MUST_PROGRESS's second witness (the supply
    # falling OIBAR_FILL_MIN_DRAIN_KPA over fill_stall_ms with no rise) closes the valves before
    # the host's 5 s guard. Before it, only the host (or transfer_max_ms) ended the fill.
    from oibar_hil.rig.checks import evaluate
    from oibar_hil.rig.faults import FaultSpec
    from oibar_hil.rig.runner import Rig

    exp = mx.expectation("pressure_sensor_stuck", "transferring")
    sc = mx.cell_scenario("pressure_sensor_stuck", "transferring", exp)
    sc.plant["line_initial_kpa"] = 100.0
    sc.faults.append(FaultSpec("pressure_sensor_stuck", at_s=0.0, args={"sensor": "line", "kpa": 100.0}))
    result = Rig(sc, mcu_path=sim_mcu_path).run()
    failed = [f"{c.id} ({c.measured})" for c in evaluate(result) if c.ok is False]
    assert not failed, failed
    m = result.metrics
    assert "FAULT_FILL_STALLED" in m["faults_seen"]
    tv_stuck_s = [
        t for t, note in result.notes if note.startswith("inject pressure_sensor_stuck {'sensor': 'tv'")
    ]
    assert len(tv_stuck_s) == 1 and 2.5 <= m["first_fault_s"] - tv_stuck_s[0] <= 3.5
    assert m["fuel_lost_kg"] == 0.0


def test_stuck_target_sensor_is_stopped_by_the_mcu_not_left_to_the_host(sim_mcu_path):
    # Firmware SAFETY_RULE_FILL_MUST_PROGRESS: the target tank's sensor freezes mid-fill; the
    # line, rising with the real tank, reads above it, so the MCU closes the valves after
    # fill_stall_ms (3 s, counted from the reading's last 5 kPa rise, up to ~0.2 s before the
    # freeze here), before the host's own 5 s fill-stall abort. Before the rule only the host
    # (or, with a silent host, the over-pressure trip) ended such a fill.
    r = mx.run_cell("pressure_sensor_stuck", "transferring", str(sim_mcu_path))
    assert r.status == "pass", r.reason
    assert "FAULT_FILL_STALLED" in r.faults_seen
    assert r.detect_s is not None and 2.5 <= r.detect_s <= 3.5
    assert r.fuel_lost_kg == 0.0


# Issue 59 item 5: the FMEA's new failure modes (firmware/fmea.toml), one phase each here (the
# phase where each matters most); `make fault-matrix` and the slow test below run every phase.
NEW_SUBSET = [
    ("plane_retracted_wire_break", "unmating"),
    ("home_wire_break", "unmating"),
    ("switch_stuck", "transferring"),
    ("plane_pos_adc_fail", "transferring"),
    ("backflow", "transferring"),
    ("mcu_reset", "transferring"),
]


def test_new_subset_covers_every_new_mode():
    assert {f for f, _ in NEW_SUBSET} == set(mx.NEW_MODES)


@pytest.mark.parametrize("fault,phase", NEW_SUBSET, ids=[f"{f}@{p}" for f, p in NEW_SUBSET])
def test_new_failure_mode_cell(fault, phase, sim_mcu_path):
    r = mx.run_cell(fault, phase, str(sim_mcu_path))
    assert r.status == "pass", f"{fault}@{phase}: {r.reason}"
    ids = {c["id"]: c for c in r.checks}
    assert ids["G-LATCH"]["ok"] is True and ids["EXP-fuel_lost_max_kg"]["ok"] is True
    assert r.fuel_lost_kg == 0.0


@pytest.mark.slow
@pytest.mark.parametrize("fault", mx.NEW_MODES)
def test_new_failure_mode_in_every_phase_vents_nothing_and_keeps_the_latch(fault, sim_mcu_path):
    # Safety alone (the cell's expected outcome is checked by `make fault-matrix`): nothing vented
    # and the latch never released with the plane out, in every phase.
    for phase in mx.PHASE_KEYS:
        r = mx.run_cell(fault, phase, str(sim_mcu_path))
        checks = {c["id"]: c for c in r.checks}
        assert r.fuel_lost_kg == 0.0, f"{fault}@{phase}"
        assert checks["G-LATCH"]["ok"] is True, f"{fault}@{phase}: {checks['G-LATCH']['measured']}"
        assert checks["REQ-VALVES"]["ok"] is True, f"{fault}@{phase}"


def test_reset_mid_transfer_keeps_the_flash_and_vents_nothing(sim_mcu_path):
    # The MCU restarts with the valves open: outputs off at once (the valves close by their
    # springs within a stroke), it boots into FAULT away from home with its parameter flash
    # attached (a blank image: defaults and an event, never FAULT_PARAMS_INVALID).
    r = mx.run_cell("mcu_reset", "transferring", str(sim_mcu_path))
    assert r.status == "pass", r.reason
    assert r.valves_open_at_injection and r.valves_closed_s is not None and r.valves_closed_s <= 0.1
    assert "FAULT_RESET_AWAY_FROM_HOME" in r.faults_seen
    assert "FAULT_PARAMS_INVALID" not in r.faults_seen
    assert r.fuel_lost_kg == 0.0
