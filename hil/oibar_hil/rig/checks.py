"""Pass/fail of each requirement and of the scenario's declared outcome.

Requirements (always checked, ground truth from the plant and the lockstep replies):
  REQ-CAPTURE   capture only inside the envelope: <= 50 mm/s, <= 10 deg (paper)
  REQ-FORCE-SOFT contact force < 30 N while soft-docking (paper)
  REQ-FORCE-HARD contact force < 60 N throughout (paper)
  REQ-VALVES    no valve coil energised outside STATE_TRANSFERRING (SPEC section 3)
  REQ-SAFE-END  both valve coils off at the end of the run
  REQ-LOCKSTEP  every exchange in order, step pulses accounted (the run would have stopped)
Expectations (from the scenario's ``expect``): EXP-<key>.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

# The capture envelope the requirement holds the run to (paper), whatever a scenario's plant or
# the MCU's parameters allow.
REQ_CAPTURE_MAX_SPEED_MPS = 0.050
REQ_CAPTURE_MAX_MISALIGN_DEG = 10.0


def capture_in_envelope(cap: dict | None) -> bool:
    """A capture record (MechanismPlant.capture_record) inside the required envelope."""
    return (
        cap is not None
        and cap["closing_speed_mps"] <= REQ_CAPTURE_MAX_SPEED_MPS
        and cap["misalignment_deg"] <= REQ_CAPTURE_MAX_MISALIGN_DEG
    )


@dataclass
class Check:
    id: str
    text: str
    ok: bool | None  # None: not applicable in this run
    measured: str


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


def evaluate(result: Any) -> list[Check]:
    m = result.metrics
    cap = result.capture
    checks = [
        Check(
            "REQ-CAPTURE",
            "capture only at closing speed <= 50 mm/s and misalignment <= 10 deg",
            None if cap is None else capture_in_envelope(cap),
            "no capture"
            if cap is None
            else f"{cap['closing_speed_mps'] * 1000:.1f} mm/s, {cap['misalignment_deg']:.2f} deg, "
            f"lateral {cap['lateral_m'] * 1000:.1f} mm",
        ),
        Check(
            "REQ-FORCE-SOFT",
            "contact force < 30 N while soft-docking",
            m["max_force_soft_n"] < 30.0,
            f"max {m['max_force_soft_n']:.1f} N",
        ),
        Check(
            "REQ-FORCE-HARD",
            "contact force < 60 N throughout",
            m["max_force_n"] < 60.0,
            f"max {m['max_force_n']:.1f} N",
        ),
        Check(
            "REQ-VALVES",
            "valve coils energised only in STATE_TRANSFERRING",
            m["valve_violation_ms"] == 0,
            f"{m['valve_violation_ms']} ms outside",
        ),
        Check(
            "REQ-SAFE-END",
            "valve coils off at the end (a stuck valve may still read open)",
            m["coils_off_at_end"],
            f"coils off {m['coils_off_at_end']}, sensed closed {m['valves_closed_at_end']}",
        ),
        Check(
            "REQ-LOCKSTEP",
            "lockstep frames in order, step pulses accounted",
            True,
            f"{m['lockstep_frames']} frames, {m['steps_total']} step pulses",
        ),
    ]
    exp = result.scenario.expect
    for key, want in exp.items():
        checks.append(_expectation(key, want, result))
    return checks


def _expectation(key: str, want: Any, result: Any) -> Check:
    m = result.metrics
    cid = f"EXP-{key}"
    if key == "outcome":
        return Check(cid, f"mission outcome {want}", result.outcome == want, result.outcome)
    if key == "final_state":
        return Check(cid, f"final MCU state {want}", m["final_state"] == want, m["final_state"])
    if key == "faults":
        want_set = set(want)
        seen = set(m["faults_seen"])
        ok = want_set <= seen if want_set else not seen
        return Check(
            cid, f"faults raised: {sorted(want_set) or 'none'}", ok, ", ".join(sorted(seen)) or "none"
        )
    if key == "valves_closed_within_s":
        v = m["valves_closed_after_injection_s"]
        return Check(
            cid,
            f"both valves closed within {want} s of the fault injection",
            v is not None and v <= float(want),
            "never" if v is None else f"{v:.3f} s",
        )
    if key == "coils_off_within_s_of_fault":
        v = m["coils_off_after_fault_s"]
        return Check(
            cid,
            f"valve coils off within {want} s of entering FAULT",
            v is not None and v <= float(want),
            "no FAULT" if v is None else f"{v:.3f} s",
        )
    if key == "fuel_lost_max_kg":
        return Check(
            cid,
            f"fuel lost <= {want} kg",
            m["fuel_lost_kg"] <= float(want) + 1e-9,
            f"{m['fuel_lost_kg']:.4f} kg",
        )
    if key == "tv_min_kpa":
        return Check(
            cid,
            f"target tank filled to >= {want} kPa",
            m["tv_final_kpa"] >= float(want),
            f"{m['tv_final_kpa']:.0f} kPa",
        )
    if key == "reset_cause":
        return Check(
            cid,
            f"MCU reported reset cause {want}",
            m["handshake_reset_cause"] == want,
            _fmt(m["handshake_reset_cause"]),
        )
    if key == "min_crc_errors":
        n = m["host_rx_crc_errors"] + m["mcu_rx_crc_errors"]
        return Check(cid, f"at least {want} CRC errors detected (host + MCU)", n >= int(want), str(n))
    if key == "captured":
        return Check(cid, f"probe captured: {want}", m["captured"] == bool(want), str(m["captured"]))
    if key == "max_replays_executed":
        n = m["wire"]["replays_executed"]
        return Check(
            cid,
            f"replayed ARM/START frames executed at most {want} times",
            n <= int(want),
            f"{n} executed, {m['wire']['replays_sent']} sent, {m['mcu_rx_stale']} refused stale",
        )
    if key == "min_replays":
        n = m["wire"]["replays_sent"]
        return Check(
            cid,
            f"at least {want} recorded ARM/START frames replayed",
            n >= int(want),
            f"{n} sent, {m['mcu_rx_stale']} refused stale",
        )
    if key == "max_sim_time_s":
        return Check(
            cid,
            f"mission over within {want} s (sim)",
            result.sim_time_s <= float(want),
            f"{result.sim_time_s:.1f} s",
        )
    return Check(cid, f"unknown expectation {key}", False, "-")
