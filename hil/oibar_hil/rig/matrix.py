"""The HIL fault matrix (issue 11): every fault type of the rig injected in every phase of the
mission, each cell checked against generic safety invariants plus its expected outcome.

    python -m oibar_hil.rig.matrix [--jobs N] [--doc docs/reliability.md] [--only FAULT[@PHASE]]

A cell is one rig run (the runner, checks and scenario code of the rig, unchanged): the short
mission from 1.2 m (fill 300 -> 600 kPa) with one fault injected by an ``at_state`` trigger.

Every applicable cell is checked for (ids G-* here, REQ-*/EXP-* from ``checks.py``):
- REQ-VALVES    no valve coil energised outside STATE_TRANSFERRING (counted by the MCU, per ms);
- REQ-FORCE-*   contact force < 30 N soft-docking, < 60 N throughout; REQ-CAPTURE envelope;
- REQ-SAFE-END  both coils off at the end;
- EXP-fuel_lost_max_kg  no gas vented (bound ``FUEL_LOST_MAX_KG``);
- EXP-faults    the MCU raised the expected fault code(s) (ground truth), or none;
- EXP-outcome / EXP-final_state  the cell's expected outcome (below);
- G-INJECTED    the phase was reached and the fault injected (a cell never silently passes);
- G-END         the mission ended completed, aborted or safed (never timed out / still
                running), not in TRANSFERRING, valves sensed closed unless one is stuck open;
- G-VALVES      valves that were open at the injection sensed closed within the fault's
                stated bound (``VALVES_CLOSED_BOUND_S``);
- G-LATCH       the latch never released with the plane away from retracted (ground truth,
                every exchange: the cam at its release position, the plane beyond 2.5 mm);
- G-REPORTED    the host was told: every expected fault reached it, as EVT_FAULT or in the
                fault flags of the telemetry it received (a fault raised while the link is
                down, or before the handshake after a reset, can only arrive the second way).

Cells where a fault cannot occur observably in a phase are "not applicable", with the reason.
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from oibar_hil.rig.checks import Check
from oibar_hil.rig.faults import FAULT_TYPES, NEW_MODES
from oibar_hil.rig.runner import REPO_ROOT
from oibar_hil.rig.scenario import Scenario

FUEL_LOST_MAX_KG = 0.0  # the couplings must never vent (checks.py allows 1e-9 for rounding)
MAX_SIM_TIME_S = 240.0
# G-LATCH: "retracted" as the firmware judges it (OIBAR_PLANE_RETRACTED_MAX_MM, app_params.h):
# the end switch and the position sensor agree within this; the couplings part at ~30 mm
LATCH_PLANE_MAX_MM = 2.5  # a cell that has not ended by then is "stuck"
DOC_PATH = REPO_ROOT / "docs" / "reliability.md"
BEGIN, END = "<!-- fault-matrix:begin -->", "<!-- fault-matrix:end -->"


@dataclass(frozen=True)
class Phase:
    key: str
    title: str
    at_state: str
    after_s: float
    note: str


PHASES = (
    Phase(
        "approach",
        "approach (APPROACH_READY)",
        "STATE_APPROACH_READY",
        2.0,
        "armed, closing on the drogue at ~1 m",
    ),
    Phase(
        "reception",
        "reception + soft dock",
        "STATE_RECEPTION",
        0.5,
        "probe in the drogue, pushing until the latches engage",
    ),
    Phase(
        "hard_docking", "hard docking", "STATE_HARD_DOCKING", 1.0, "fluidic plane extending (~10 mm of 40)"
    ),
    Phase(
        "hard_docked",
        "hard docked / arming",
        "STATE_HARD_DOCKED",
        0.0,
        "mated, valves closed, before ARM_TRANSFER",
    ),
    Phase("transferring", "transferring", "STATE_TRANSFERRING", 1.0, "valves open, filling"),
    Phase(
        "unmating",
        "unmating / separation",
        "STATE_UNMATING",
        0.5,
        "fill done, plane retracting (~35 mm, couplings half-mated)",
    ),
)
PHASE_KEYS = tuple(p.key for p in PHASES)

# How each fault type is injected in the matrix (FaultSpec fields besides the trigger).
FAULT_ARGS: dict[str, dict[str, Any]] = {
    "link_loss": {"duration_s": 3.0},
    "bit_errors": {"ber": 2.0e-4},  # until the end of the mission
    "pressure_sensor_stuck": {"sensor": "tv"},
    "pressure_sensor_range": {"sensor": "tv", "level": "high"},
    "valve_stuck_open": {"valve": "sv"},  # when closed: the valve fails open
    "valve_stuck_closed": {"valve": "tv"},
    "latch_stall": {},
    "actuator_jam": {},  # permanent: the plane never frees
    "overpressure": {"tank": "sv", "rate_kpa_s": 300, "peak_kpa": 2700, "hold_s": 3.0},
    "watchdog_reset": {},
    "host_crash": {"duration_s": 4.0},
    # issue 16 (fw-drv): latch switch pair, ADC glitches
    "latch_wire_break": {"wire": "no"},  # the engaged contact's wire, for good
    "adc_glitch": {"sensor": "tv", "samples": 1},  # one bad conversion
    "adc_glitch_run": {"sensor": "tv", "samples": 20},  # 20 in a row (bound: 10 ms)
    "replay": {"period_s": 0.25},  # until the end of the mission
    # the host's own failures (issue 17), through NavDaemon.cycle and the link core
    "camera_unplugged": {"duration_s": 3.0},
    "serial_unplugged": {"duration_s": 3.0},
    "nav_hang": {"duration_s": 3.0},
    "slow_inference": {"duration_s": 3.0, "latency_s": 0.3},
    "valve_slow_close": {"stroke_s": 0.3, "host_abort": True},  # until the end of the mission
    # Each protection zeroed or loosened past its margin (docs/firmware.md, "Safety limits").
    "param_attack": {
        "values": {
            "soft_dock_max_force_n": 0,
            "hard_dock_max_force_n": 0,
            "overpressure_kpa": 3000,
            "press_sv_kpa_per_count": 0.1,
            "press_tv_kpa_per_count": 0.1,
            "press_line_kpa_per_count": 10,
            "press_zero_counts": 1000,
            "press_min_counts": 0,
            "press_max_counts": 4095,
            "press_max_rate_kpa_s": 100000,
            "force_n_per_count": 0.001,
            "valve_mismatch_ms": 2000,
            "plane_coupling_mm": 40,
            "nav_min_confidence": 0,
            "fill_stall_ms": 600000,
            "capture_max_speed_mm_s": 200,
            "capture_max_misalign_deg": 45,
            "plane_mm_per_count": 0.02,
        }
    },
    # issue 59 item 5: the FMEA's new failure modes (firmware/fmea.toml), each for good
    "plane_retracted_wire_break": {},
    "home_wire_break": {},
    "switch_stuck": {"switch": "plane_extended", "level": False},  # a broken lever: never actuated
    "plane_pos_adc_fail": {},
    # the supply falls at 1000 kPa/s (under the 2000 kPa/s rate check: a real tank) to 250 kPa,
    # below the target tank (300 -> 600 kPa)
    "backflow": {"sv_kpa": 250.0, "rate_kpa_s": 1000.0},
    "mcu_reset": {},  # reset pin: the MCU boots again, the parameter flash kept (rig.flash_image)
}
FAULT_TITLES = {
    "link_loss": "link loss 3 s",
    "bit_errors": "bit errors (BER 2e-4)",
    "pressure_sensor_stuck": "TV pressure sensor stuck",
    "pressure_sensor_range": "TV pressure sensor out of range",
    "valve_stuck_open": "SV valve stuck open",
    "valve_stuck_closed": "TV valve stuck closed",
    "latch_stall": "latch stall",
    "actuator_jam": "plane actuator jam",
    "overpressure": "SV over-pressure 2700 kPa",
    "watchdog_reset": "watchdog reset (main loop hang)",
    "host_crash": "host crash 4 s",
    "latch_wire_break": "latch switch wire broken",
    "adc_glitch": "TV pressure: 1 bad ADC sample",
    "adc_glitch_run": "TV pressure: 20 bad ADC samples",
    "replay": "replayed ARM/START",
    "camera_unplugged": "camera unplugged 3 s",
    "serial_unplugged": "serial port unplugged 3 s",
    "nav_hang": "navigation loop hung 3 s",
    "slow_inference": "inference 300 ms (3 periods) for 3 s",
    "valve_slow_close": "valves stroke 300 ms, host aborts",
    "param_attack": "host loosens every protection",
    "plane_retracted_wire_break": "plane retracted switch: broken wire",
    "home_wire_break": "latch home switch: broken wire",
    "switch_stuck": "plane extended switch stuck open",
    "plane_pos_adc_fail": "plane position ADC fails",
    "backflow": "supply below target (back-flow)",
    "mcu_reset": "MCU reset (pin), flash kept",
}
assert set(FAULT_ARGS) == set(FAULT_TYPES), "a fault type of the rig is missing from the matrix"

# Valves open at the injection must be sensed closed within this (s after the injection).
# None: the fault does not require closing them (the fill goes on) or the valve cannot close.
VALVES_CLOSED_BOUND_S: dict[str, float | None] = {
    "link_loss": 1.5,  # link timeout 1 s + 50 ms stroke
    "bit_errors": None,  # the link copes; the fill completes
    "pressure_sensor_stuck": 3.5,  # the MCU's fill-stall check: lead at once, fill_stall_ms 3 s + stroke
    "pressure_sensor_range": 0.2,  # range check (debounce) + stroke
    "valve_stuck_open": None,  # the stuck valve cannot close: coils off within 50 ms instead
    "valve_stuck_closed": 0.4,  # mismatch 200 ms + stroke of the other valve
    "latch_stall": None,  # latent until the latch release
    "actuator_jam": None,  # latent until the plane moves
    "overpressure": 3.0,  # ramp 300 kPa/s to the 2600 kPa trip (~1.7 s) + stroke
    "watchdog_reset": 0.3,  # watchdog 100 ms, outputs off at reset + stroke
    "host_crash": 1.5,  # link timeout 1 s + stroke
    "latch_wire_break": 0.1,  # debounce 10 ms (the pair reads "not engaged") + stroke
    "adc_glitch": None,  # one sample is not a fault: the fill goes on
    "adc_glitch_run": 0.1,  # bad-run bound 10 ms + stroke
    "replay": None,  # refused frames: the fill goes on
    "camera_unplugged": None,  # navigation only: the mechanism goes on
    "serial_unplugged": 1.5,  # as a link loss: the MCU's link timeout 1 s + stroke
    "nav_hang": 1.5,  # no heartbeat from a hung loop: link timeout 1 s + stroke
    "slow_inference": None,  # late cycles still beat the link timeout: the fill goes on
    "valve_slow_close": 0.4,  # the 300 ms stroke + debounce
    "param_attack": None,  # refused: nothing changes, the fill goes on
    "plane_retracted_wire_break": None,  # the fill goes on: the switch is not read while mated
    "home_wire_break": None,  # latent until the latch homes
    "switch_stuck": 0.1,  # the extended switch is a valve precondition: debounce 10 ms + stroke
    "plane_pos_adc_fail": 0.1,  # bad run 10 ms: FAULT_PLANE_POSITION + stroke
    "backflow": 2.5,  # the supply's fall to below the target (~1.8 s) + the no-back-flow check + stroke
    "mcu_reset": 0.1,  # outputs off at the reset + stroke
}

NOT_APPLICABLE: dict[tuple[str, str], str] = {
    (
        "valve_stuck_closed",
        "unmating",
    ): "the valves are closed for good after the fill and never commanded again: a valve stuck "
    "closed is indistinguishable from a healthy one (the plant is identical)",
}


@dataclass
class Expect:
    outcome: str
    faults: list[str]
    final_state: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)  # more scenario ``expect`` keys
    why: str = ""


def _final(outcome: str) -> str:
    return "STATE_FAULT" if outcome == "safed" else "STATE_IDLE"


def expectation(fault: str, phase: str) -> Expect | str:
    """The expected safe outcome of one cell, or the reason it is not applicable."""
    if (fault, phase) in NOT_APPLICABLE:
        return NOT_APPLICABLE[(fault, phase)]
    late = phase == "unmating"
    before_fill = phase in ("approach", "reception", "hard_docking", "hard_docked")
    if fault in ("link_loss", "host_crash"):
        e = Expect(
            "aborted",
            ["FAULT_HOST_LINK_LOSS"],
            why="MCU declares link loss after 1 s, safes; new/re-handshaken host clears, separates",
        )
    elif fault == "bit_errors":
        e = Expect(
            "completed",
            [],
            extra={"min_crc_errors": 1, "tv_min_kpa": 595},
            why="CRC drops and retransmissions: nominal",
        )
    elif fault == "pressure_sensor_stuck":
        if late:
            e = Expect("completed", [], why="the reading is no longer used after the fill")
        else:
            e = Expect(
                "aborted",
                ["FAULT_FILL_STALLED"],
                why="in range, but the line reads above the frozen tank: the MCU stops the fill after "
                "3 s (before the host's 5 s stall abort); the host clears, separates",
            )
    elif fault == "pressure_sensor_range":
        e = Expect(
            "safed",
            ["FAULT_PRESSURE_SENSOR_RANGE"],
            why="range fault at once; not clearable while broken: hold, valves closed",
        )
    elif fault == "valve_stuck_open" and late:
        # The plane is already past the seals when the valve fails: the line vents from the
        # failure until the 200 ms mismatch detection plus the plane's re-seat to full mate
        # (firmware SAFETY_RULE_NO_HALF_MATED_WITH_VALVE_OPEN), about 0.6 s at ~8 g/s.
        e = Expect(
            "safed",
            ["FAULT_VALVE_MISMATCH"],
            extra={"coils_off_within_s_of_fault": 0.05, "fuel_lost_max_kg": 0.010},
            why="mismatch after 200 ms; FAULT re-seats the half-mated plane; vents < 10 g",
        )
    elif fault == "valve_stuck_open":
        e = Expect(
            "safed",
            ["FAULT_VALVE_MISMATCH"],
            extra={"coils_off_within_s_of_fault": 0.05},
            why="mismatch after 200 ms, coils off; not clearable: hold, nothing vented",
        )
    elif fault == "valve_stuck_closed":
        e = Expect(
            "aborted",
            ["FAULT_VALVE_MISMATCH"],
            extra={"coils_off_within_s_of_fault": 0.05},
            why=("latent until START_TRANSFER; " if before_fill else "")
            + "mismatch after 200 ms, both closed; clear, abort, separate",
        )
    elif fault == "latch_stall":
        e = Expect(
            "safed",
            ["FAULT_LATCH_STALL"],
            why=("latent until the release; " if not late else "")
            + "release budget spent, one retry stalls again: hold soft-docked",
        )
    elif fault == "actuator_jam":
        if phase in ("approach", "reception"):
            e = Expect(
                "aborted",
                ["FAULT_PLANE_TIMEOUT"],
                why="latent until HARD_DOCK: plane timeout at 0 mm; clear, separate",
            )
        else:
            e = Expect(
                "safed",
                ["FAULT_PLANE_TIMEOUT"],
                why="plane cannot move either way: timeouts, one recovery, hold, valves closed",
            )
    elif fault == "overpressure":
        e = Expect(
            "aborted",
            ["FAULT_OVERPRESSURE"],
            extra={"coils_off_within_s_of_fault": 0.05},
            why="trip at 2600 kPa, coils off; clear once below, abort, separate",
        )
    elif fault == "serial_unplugged":
        e = Expect(
            "aborted",
            ["FAULT_HOST_LINK_LOSS"],
            why="host port gone: MCU link timeout 1 s, safes; the port back, re-handshake, clear, separate",
        )
    elif fault == "nav_hang":
        e = Expect(
            "aborted",
            ["FAULT_HOST_LINK_LOSS"],
            why="no heartbeat or update from the hung cycle: MCU link timeout, safes; "
            "the loop back, re-handshake, clear, separate",
        )
    elif fault == "camera_unplugged":
        e = Expect(
            "completed",
            [],
            why=(
                "free flight: hold 3 s on no frame, then on"
                if phase == "approach"
                else "docked: navigation not needed; the mission goes on"
            ),
        )
    elif fault == "slow_inference":
        e = Expect(
            "completed",
            [],
            why="cycles every 300 ms on 300 ms old frames: stale, held, never acted on; "
            "heartbeats still within the link timeout; on time again after 3 s",
        )
    elif fault == "watchdog_reset":
        e = Expect(
            "aborted",
            ["FAULT_WATCHDOG_RESET"],
            extra={"reset_cause": "RESET_WATCHDOG"},
            why="reset after 100 ms, outputs off, FAULT; host re-handshakes, clears, separates",
        )
    elif fault == "latch_wire_break":
        e = Expect(
            "safed",
            ["FAULT_LATCH_SENSOR"],
            why=(
                "latent until the latches engage; "
                if phase == "approach"
                else "the pair reads 'not engaged' at once (valves closed, FAULT_LATCH_LOST "
                "where engaged was required); "
            )
            + "neither contact for 100 ms: FAULT_LATCH_SENSOR, not clearable: hold",
        )
    elif fault == "adc_glitch":
        e = Expect(
            "completed",
            [],
            extra={"tv_min_kpa": 595},
            why="one bad conversion is skipped (last good value held): nominal",
        )
    elif fault == "adc_glitch_run":
        e = Expect(
            "aborted",
            ["FAULT_PRESSURE_SENSOR_RANGE"],
            why="a run of bad samples lasting 10 ms is a range fault; the sensor is back: "
            "clear, abort, separate",
        )
    elif fault == "replay":
        e = Expect(
            "completed",
            [],
            extra={"max_replays_executed": 0, "min_replays": 1, "tv_min_kpa": 595},
            why="recorded ARM/START resent every 0.25 s to the end: refused as stale "
            "(or answered from the duplicate cache): none runs again",
        )
    elif fault == "param_attack":
        e = Expect(
            "completed",
            [],
            why="every ParamSet refused (locked while active, out of bounds "
            "in IDLE/FAULT): the mission goes on unchanged",
        )
    elif fault == "valve_slow_close":
        if phase == "transferring":
            e = Expect(
                "aborted",
                ["FAULT_VALVE_MISMATCH"],
                why="host ABORT while filling: plane held mated while the valves close (300 ms "
                "> valve_mismatch_ms): FAULT, plane held; clear once closed, abort, separate",
            )
        elif phase == "reception":
            e = Expect("aborted", [], why="valves closed: the host's ABORT safes at once; no second try")
        elif phase == "unmating":
            e = Expect("completed", [], why="valves closed: ABORT re-latches soft-docked, separation goes on")
        else:
            e = Expect(
                "aborted",
                ["FAULT_VALVE_MISMATCH"],
                why="valves closed: ABORT safes at once; the retried fill's valves close slower "
                "than valve_mismatch_ms: FAULT with the plane held mated, nothing vented",
            )
    elif fault in NEW_MODES:
        e = _new_mode_expectation(fault, phase)
    else:
        raise ValueError(f"no expectation for fault {fault!r}")
    if e.final_state is None:
        e.final_state = _final(e.outcome)
    return e


# the FMEA's new modes (issue 59 item 5): one list, the injector's (oibar_hil.rig.faults.NEW_MODES)


def _new_mode_expectation(fault: str, phase: str) -> Expect:
    """Issue 59 item 5: each new failure mode of the FMEA (firmware/fmea.toml) in each phase.
    Nothing vents in any of them (FUEL_LOST_MAX_KG), and G-LATCH holds in all."""
    if fault == "plane_retracted_wire_break":
        if phase == "unmating":
            return Expect(
                "completed",
                [],
                why="the wire breaks while the plane retracts: the end counts only once the position "
                "sensor agrees (D9), so the latch waits for the real end; separation goes on",
            )
        return Expect(
            "safed",
            ["FAULT_PLANE_POSITION"],
            why=("latent until the plane reaches its extended switch; " if phase != "hard_docked" else "")
            + "both end switches read actuated: FAULT_PLANE_POSITION, valves closed, not clearable "
            "while implausible: hold mated, the latch never released",
        )
    if fault == "home_wire_break":
        return Expect(
            "safed",
            ["FAULT_LATCH_STALL"],
            why="latent until the latch homes after its release (plane retracted): the home switch "
            "reads 'home' from the start, the pull-off does not clear it (D7): stall, hold",
        )
    if fault == "switch_stuck":
        if phase in ("approach", "reception", "hard_docking"):
            return Expect(
                "aborted",
                ["FAULT_PLANE_TIMEOUT"],
                why="the extend never sees its switch: plane timeout; clear, the plane retracts, separate",
            )
        if phase == "unmating":
            return Expect("completed", [], why="the extended switch is not read once the plane leaves it")
        return Expect(
            "aborted",
            ["FAULT_PLANE_POSITION"],
            why="the plane no longer reads mated (switch and sensor disagree): valves closed "
            "(SAFETY_RULE_VALVES_NEED_PLANE_MATED); clear, abort, separate",
        )
    if fault == "plane_pos_adc_fail":
        return Expect(
            "safed",
            ["FAULT_PLANE_POSITION"],
            why="a run of failed conversions for 10 ms (D3): FAULT_PLANE_POSITION, nothing moves "
            "or opens on a stale number; not clearable while it fails: hold",
        )
    if fault == "backflow":
        if phase == "unmating":
            return Expect("completed", [], why="valves closed for good: the supply's level no longer matters")
        if phase == "approach":
            return Expect(
                "aborted",
                ["FAULT_PRESSURE_SENSOR_RATE"],
                why="the supply's fall read by the rate check on the rig's 20 ms coast exchanges "
                "(a faster fall than the fill allows): FAULT; clear, separate",
            )
        if phase in ("reception", "hard_docking"):
            return Expect(
                "aborted",
                [],
                why="the supply is below the target before the fill: START refused (D2, no head); "
                "the host gives up and separates",
            )
        return Expect(
            "aborted",
            ["FAULT_FILL_STALLED"],
            why="the supply falls below the target: the valves close at once "
            "(SAFETY_RULE_NO_BACKFLOW, D2); clear, abort, separate",
        )
    if fault == "mcu_reset":
        if phase == "approach":
            return Expect(
                "completed",
                [],
                why="a reset at home is no fault: the host re-handshakes and the mission goes on",
            )
        return Expect(
            "aborted",
            ["FAULT_RESET_AWAY_FROM_HOME"],
            why="outputs off at the reset (valves close by their springs); boots into FAULT with the "
            "mechanism away from home, parameters from the flash; host re-handshakes, clears, separates",
        )
    raise ValueError(fault)


def cell_scenario(fault: str, phase: str, exp: Expect, seed: int = 7) -> Scenario:
    ph = next(p for p in PHASES if p.key == phase)
    spec = {"type": fault, "at_state": ph.at_state, "after_s": ph.after_s, **FAULT_ARGS[fault]}
    expect = {
        "outcome": exp.outcome,
        "final_state": exp.final_state,
        "faults": exp.faults,
        "fuel_lost_max_kg": FUEL_LOST_MAX_KG,
        **exp.extra,
    }
    return Scenario.from_dict(
        {
            "name": f"matrix_{fault}@{phase}",
            "description": f"{FAULT_TITLES[fault]} during {ph.title} ({ph.note}): {exp.why}",
            "seed": seed,
            "start": {"range_m": 1.2, "lateral_m": [0.02, -0.01], "misalignment_deg": [1.0, -0.5]},
            "mission": {"target_kpa": 600, "arm_range_m": 2.0, "retreat_to_m": 0.5},
            "rig": {"max_time_s": MAX_SIM_TIME_S, "flash_image": fault == "mcu_reset"},
            "faults": [spec],
            "expect": expect,
        }
    )


@dataclass
class CellResult:
    fault: str
    phase: str
    status: str  # pass | FAIL | n.a.
    reason: str = ""  # n.a. reason or the failed checks
    outcome: str = ""
    final_state: str = ""
    faults_seen: list[str] = field(default_factory=list)
    detect_s: float | None = None  # first FAULT state after the injection
    valves_closed_s: float | None = None  # both valves sensed closed after the injection
    valves_open_at_injection: bool = False
    fuel_lost_kg: float = 0.0
    sim_time_s: float = 0.0
    wall_time_s: float = 0.0
    checks: list[dict] = field(default_factory=list)
    expected: str = ""


def generic_checks(fault: str, result: Any) -> list[Check]:
    m = result.metrics
    inj = m["first_injection_s"]
    vc = m["valves_closed_after_injection_s"]
    open_at_inj = inj is not None and (vc is None or vc > 0.0)
    stuck_open = fault == "valve_stuck_open"
    checks = [
        Check(
            "G-INJECTED",
            "the phase was reached and the fault injected",
            inj is not None,
            "never" if inj is None else f"at {inj:.2f} s",
        )
    ]
    ended = result.outcome in ("completed", "aborted", "safed")
    sensed_ok = m["valves_closed_at_end"] or stuck_open
    checks.append(
        Check(
            "G-END",
            "ended completed/aborted/safed, not TRANSFERRING, coils off, valves closed "
            "(a stuck-open valve excepted)",
            ended and m["final_state"] != "STATE_TRANSFERRING" and m["coils_off_at_end"] and sensed_ok,
            f"{result.outcome} in {m['final_state']}, coils off {m['coils_off_at_end']}, "
            f"valves closed {m['valves_closed_at_end']}",
        )
    )
    bound = VALVES_CLOSED_BOUND_S[fault]
    if not open_at_inj:
        checks.append(
            Check(
                "G-VALVES",
                "valves open at the injection closed within the bound",
                None,
                "valves were closed at the injection",
            )
        )
    elif bound is None:
        checks.append(
            Check(
                "G-VALVES",
                "valves open at the injection closed within the bound",
                None,
                f"no bound for {fault} (closed after {'never' if vc is None else f'{vc:.3f} s'})",
            )
        )
    else:
        checks.append(
            Check(
                "G-VALVES",
                f"valves open at the injection sensed closed within {bound} s",
                vc is not None and vc <= bound,
                "never" if vc is None else f"{vc:.3f} s",
            )
        )
    out_mm = m.get("latch_released_plane_out_mm", 0.0)
    checks.append(
        Check(
            "G-LATCH",
            f"the latch cam never at its release position with the plane beyond {LATCH_PLANE_MAX_MM} mm",
            out_mm <= LATCH_PLANE_MAX_MM,
            "never" if out_mm == 0.0 else f"released with the plane at {out_mm:.1f} mm",
        )
    )
    want = set(result.scenario.expect.get("faults", []))
    events, flags = set(m["faults_reported_to_host"]), set(m["faults_in_host_telemetry"])
    checks.append(
        Check(
            "G-REPORTED",
            "every expected fault reached the host (EVT_FAULT or telemetry)",
            (want <= events | flags) if want else None,
            f"events: {', '.join(sorted(events)) or 'none'}; telemetry: {', '.join(sorted(flags)) or 'none'}",
        )
    )
    if fault == "param_attack":
        attacks = [(label, verdict) for _, label, verdict in result.requests if label.startswith("ATTACK ")]
        accepted = [label for label, verdict in attacks if not verdict.startswith("refused")]
        names = {label.split()[1].split("=")[0] for label, _ in attacks}
        bounded = {
            label.split()[1].split("=")[0]
            for label, verdict in attacks
            if verdict == "refused (NACK_PARAM_OUT_OF_BOUNDS)"
        }
        want = set(FAULT_ARGS["param_attack"]["values"])
        checks.append(
            Check(
                "G-PARAMS",
                "every attempt to loosen a protection refused; each refused by its bounds once "
                "parameters may change (IDLE/FAULT)",
                not accepted and names == want and bounded == want,
                f"{len(attacks)} attempts, not refused: {', '.join(accepted) or 'none'}; "
                f"not tried in a settable state: {', '.join(sorted(want - bounded)) or 'none'}",
            )
        )
    return checks


def run_cell(fault: str, phase: str, mcu_path: str | None = None) -> CellResult:
    """Run one cell (in this process) and check it."""
    from oibar_hil.rig.checks import evaluate
    from oibar_hil.rig.runner import Rig

    exp = expectation(fault, phase)
    if isinstance(exp, str):
        return CellResult(fault, phase, "n.a.", reason=exp)
    sc = cell_scenario(fault, phase, exp)
    expected = f"{exp.outcome}" + (
        f", {'+'.join(f.replace('FAULT_', '') for f in exp.faults)}" if exp.faults else ""
    )
    try:
        result = Rig(sc, mcu_path=Path(mcu_path) if mcu_path else None).run()
    except Exception as exc:  # a lockstep error or a crash of the rig is a failed cell
        return CellResult(
            fault, phase, "FAIL", reason=f"run raised {type(exc).__name__}: {exc}", expected=expected
        )
    result.checks = evaluate(result) + generic_checks(fault, result)
    m = result.metrics
    inj, ff = m["first_injection_s"], m["first_fault_s"]
    vc = m["valves_closed_after_injection_s"]
    failed = [f"{c.id} ({c.measured})" for c in result.checks if c.ok is False]
    return CellResult(
        fault,
        phase,
        "pass" if not failed else "FAIL",
        reason="; ".join(failed),
        outcome=result.outcome,
        final_state=m["final_state"],
        faults_seen=m["faults_seen"],
        detect_s=(ff - inj) if (ff is not None and inj is not None and ff >= inj) else None,
        valves_closed_s=vc,
        valves_open_at_injection=inj is not None and (vc is None or vc > 0.0),
        fuel_lost_kg=m["fuel_lost_kg"],
        sim_time_s=result.sim_time_s,
        wall_time_s=result.wall_time_s,
        checks=[asdict(c) for c in result.checks],
        expected=expected,
    )


def all_cells() -> list[tuple[str, str]]:
    return [(f, p) for f in FAULT_TYPES for p in PHASE_KEYS]


def run_matrix(
    cells: list[tuple[str, str]] | None = None,
    *,
    jobs: int = 1,
    progress: bool = True,
    mcu_path: str | None = None,
) -> list[CellResult]:
    cells = cells or all_cells()
    bar = None
    if progress:
        from oibar.progress import Progress

        bar = Progress("fault matrix", total=len(cells), unit="cell")
    results: dict[tuple[str, str], CellResult] = {}

    def done(r: CellResult) -> None:
        results[(r.fault, r.phase)] = r
        if bar is not None:
            bar.set_postfix_str(f"{r.fault}@{r.phase}: {r.status}")
            bar.update(1)
            if r.status == "FAIL":
                bar.write(f"FAIL {r.fault}@{r.phase}: {r.reason}")

    if jobs <= 1:
        for f, p in cells:
            done(run_cell(f, p, mcu_path))
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            futs = [pool.submit(run_cell, f, p, mcu_path) for f, p in cells]
            for fut in as_completed(futs):
                done(fut.result())
    if bar is not None:
        bar.close()
    return [results[c] for c in cells]


# -- the table ----------------------------------------------------------------------------


def _cell_text(r: CellResult) -> str:
    if r.status == "n.a.":
        return "n.a.¹"
    short = {"completed": "compl.", "aborted": "aborted", "safed": "safed"}.get(r.outcome, r.outcome or "-")
    parts = [f"**{r.status}**" if r.status == "FAIL" else r.status, short]
    if r.detect_s is not None:
        parts.append(f"F {r.detect_s:.2f} s")
    if r.valves_open_at_injection:
        parts.append("V " + ("never" if r.valves_closed_s is None else f"{r.valves_closed_s:.2f} s"))
    return " · ".join(parts)


def markdown(results: list[CellResult], wall_s: float | None = None) -> str:
    by = {(r.fault, r.phase): r for r in results}
    n_pass = sum(r.status == "pass" for r in results)
    n_fail = sum(r.status == "FAIL" for r in results)
    n_na = sum(r.status == "n.a." for r in results)
    lines = [
        BEGIN,
        "",
        f"**{n_pass} pass, {n_fail} fail, {n_na} not applicable** of {len(results)} cells "
        f"({len(FAULT_TYPES)} faults x {len(PHASES)} phases)"
        + (f"; the whole matrix ran in {wall_s:.0f} s wall." if wall_s is not None else "."),
        "",
        "Cell: verdict · outcome · **F** time from the injection to the MCU entering FAULT "
        "(when it did) · **V** time from the injection until both valves were sensed closed "
        "(only where they were open at the injection). Simulated seconds.",
        "",
        "| fault \\ phase | " + " | ".join(p.title for p in PHASES) + " |",
        "| --- | " + " | ".join("---" for _ in PHASES) + " |",
    ]
    for f in FAULT_TYPES:
        row = [_cell_text(by[(f, p)]) if (f, p) in by else "not run" for p in PHASE_KEYS]
        lines.append(f"| {FAULT_TITLES[f]} | " + " | ".join(row) + " |")
    lines += [
        "",
        "Injection points (the rig's `at_state` trigger, seconds after the MCU first enters it):",
        "",
    ]
    lines += [f"- **{p.title}**: `{p.at_state}` + {p.after_s:g} s: {p.note}" for p in PHASES]
    lines += [
        "",
        "Expected outcome per cell (`hil/oibar_hil/rig/matrix.py`, `expectation()`):",
        "",
        "| fault | phase | expected | why |",
        "| --- | --- | --- | --- |",
    ]
    for f in FAULT_TYPES:
        for p in PHASE_KEYS:
            e = expectation(f, p)
            if isinstance(e, str):
                lines.append(f"| {f} | {p} | n.a. | ¹ {e} |")
            else:
                faults = ", ".join(x.replace("FAULT_", "") for x in e.faults) or "no fault"
                lines.append(f"| {f} | {p} | {e.outcome} ({faults}) | {e.why} |")
    fails = [r for r in results if r.status == "FAIL"]
    lines += ["", "Failed cells:" if fails else "No failed cell.", ""]
    for r in fails:
        lines.append(
            f"- `{r.fault}@{r.phase}`: expected {r.expected}; got {r.outcome} in "
            f"{r.final_state}, faults {', '.join(r.faults_seen) or 'none'}, fuel lost "
            f"{r.fuel_lost_kg * 1000:.1f} g; failed {r.reason}"
        )
    lines += ["", END]
    return "\n".join(lines)


def write_doc(section: str, path: Path = DOC_PATH, begin: str = BEGIN, end: str = END) -> None:
    """Replace the marked section of docs/reliability.md (the rest of the page is kept)."""
    text = path.read_text(encoding="utf-8")
    i, j = text.find(begin), text.find(end)
    if i < 0 or j < 0:
        raise ValueError(f"{path}: markers {begin} / {end} not found")
    path.write_text(text[:i] + section + text[j + len(end) :], encoding="utf-8")


def _parse_only(items: list[str]) -> list[tuple[str, str]]:
    cells = []
    for item in items:
        fault, _, phase = item.partition("@")
        if fault not in FAULT_TYPES or (phase and phase not in PHASE_KEYS):
            raise SystemExit(f"unknown cell {item!r}: faults {FAULT_TYPES}, phases {PHASE_KEYS}")
        cells += [(fault, p) for p in ([phase] if phase else PHASE_KEYS)]
    return cells


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_hil.rig.matrix", description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", "-j", type=int, default=1)
    ap.add_argument("--doc", type=Path, default=None, help="write the table into this page's markers")
    ap.add_argument("--json", type=Path, default=None, help="write every cell's checks here")
    ap.add_argument("--only", nargs="*", default=[], help="FAULT or FAULT@PHASE (default: all)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    cells = _parse_only(args.only) if args.only else None
    t0 = time.perf_counter()
    results = run_matrix(cells, jobs=args.jobs, progress=not args.no_progress)
    wall = time.perf_counter() - t0
    table = markdown(results, wall)
    print(table.replace(BEGIN, "").replace(END, "").strip())
    if args.json:
        import json

        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps([asdict(r) for r in results], indent=1, default=str))
    if args.doc:
        write_doc(table, args.doc)
        print(f"\ntable written to {args.doc}")
    return 1 if any(r.status == "FAIL" for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
