"""Fault injection by scenario: what each fault does to the plant, the wire or the host.

A scenario lists faults, each with a trigger (``at_s`` simulated seconds, or ``at_state``: the
first time the MCU enters that state, plus ``after_s``) and an optional ``duration_s`` (the
fault clears by itself afterwards; without it the fault stays). docs/hil.md lists every type
with the outcome the firmware and the host guidance should produce.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from oibar_hil.rig.lockstep import ADC

# Issue 59 item 5: the FMEA's new failure modes (firmware/fmea.toml), also the fault matrix's.
NEW_MODES = (
    "plane_retracted_wire_break",
    "home_wire_break",
    "switch_stuck",
    "plane_pos_adc_fail",
    "backflow",
    "mcu_reset",
)

FAULT_TYPES = (
    "link_loss",
    "bit_errors",
    "pressure_sensor_stuck",
    "pressure_sensor_range",
    "valve_stuck_open",
    "valve_stuck_closed",
    "latch_stall",
    "actuator_jam",
    "overpressure",
    "watchdog_reset",
    "host_crash",
    "latch_wire_break",
    "adc_glitch",
    "adc_glitch_run",
    "replay",
    # the host's own failures, through the real daemon cycle and link core (issue 17)
    "camera_unplugged",
    "serial_unplugged",
    "nav_hang",
    "slow_inference",
    # issue 16 (fw-app): abort with slow valves, host-side parameter attack
    "valve_slow_close",
    "param_attack",
    # issue 59 item 5: the FMEA's new failure modes (firmware/fmea.toml)
    *NEW_MODES,
)

# Lockstep DI names of the switches a fault may break or stick (hil/oibar_hil/rig/lockstep.py).
SWITCHES = {
    "contact": "CONTACT",
    "latch_home": "LATCH_HOME",
    "plane_extended": "PLANE_EXTENDED",
    "plane_retracted": "PLANE_RETRACTED",
    "connector": "CONNECTOR_MATED",
    "sv_valve": "SV_VALVE_OPEN",
    "tv_valve": "TV_VALVE_OPEN",
}


@dataclass
class FaultSpec:
    type: str
    at_s: float | None = None
    at_state: str | None = None
    after_s: float = 0.0
    duration_s: float | None = None
    args: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FaultSpec:
        d = dict(d)
        kind = d.pop("type")
        if kind not in FAULT_TYPES:
            raise ValueError(f"unknown fault type {kind!r}; known: {', '.join(FAULT_TYPES)}")
        spec = cls(
            kind,
            d.pop("at_s", None),
            d.pop("at_state", None),
            float(d.pop("after_s", 0.0)),
            d.pop("duration_s", None),
            d,
        )
        if spec.at_s is None and spec.at_state is None:
            spec.at_s = 0.0
        return spec


@dataclass
class ActiveFault:
    spec: FaultSpec
    start_s: float
    end_s: float | None
    state: dict[str, Any] = field(default_factory=dict)


class FaultInjector:
    """Arms, applies and removes the scenario's faults as simulated time goes by."""

    def __init__(self, specs: list[FaultSpec]) -> None:
        self.pending = list(specs)
        self.state_seen_at: dict[str, float] = {}
        self.active: list[ActiveFault] = []
        self.log: list[tuple[float, str]] = []  # (t_s, text) for the report
        self.first_injection_s: float | None = None

    def update(self, t_s: float, dt_s: float, mcu_state: str, rig: Any) -> None:
        self.state_seen_at.setdefault(mcu_state, t_s)
        for spec in list(self.pending):
            if spec.at_state is not None:
                seen = self.state_seen_at.get(spec.at_state)
                due = seen is not None and t_s >= seen + spec.after_s
            else:
                assert spec.at_s is not None  # FaultSpec.from_dict: a trigger, at_s or at_state
                due = t_s >= float(spec.at_s) + spec.after_s
            if due:
                self.pending.remove(spec)
                end = None if spec.duration_s is None else t_s + float(spec.duration_s)
                fault = ActiveFault(spec, t_s, end)
                self._apply(fault, rig, True)
                self.active.append(fault)
                if self.first_injection_s is None:
                    self.first_injection_s = t_s
                self.log.append((t_s, f"inject {spec.type} {spec.args or ''}".strip()))
        for fault in list(self.active):
            if fault.spec.type == "overpressure":
                self._overpressure(fault, t_s, dt_s, rig)
            if fault.spec.type == "backflow":
                self._backflow(fault, dt_s, rig)
            if fault.spec.type == "replay":
                self._replay(fault, t_s, rig)
            if fault.end_s is not None and t_s >= fault.end_s:
                self.active.remove(fault)
                self._apply(fault, rig, False)
                self.log.append((t_s, f"clear {fault.spec.type}"))

    # -- the faults ---------------------------------------------------------------------

    def _apply(self, fault: ActiveFault, rig: Any, on: bool) -> None:
        spec, mech, wire = fault.spec, rig.mech, rig.wire
        kind = spec.type
        if kind == "link_loss":
            wire.cut = on
        elif kind == "bit_errors":
            wire.ber = float(spec.args.get("ber", 1e-4)) if on else 0.0
        elif kind == "pressure_sensor_stuck":
            # frozen at its last reading, or (kpa: P) stuck at the reading of P kPa
            name = spec.args.get("sensor", "tv")
            s = mech.sensor_faults[name]
            at = mech.counts_of_kpa(float(spec.args["kpa"])) if "kpa" in spec.args else mech.last_counts(name)
            s.stuck_counts = at if on else None
        elif kind == "pressure_sensor_range":
            s = mech.sensor_faults[spec.args.get("sensor", "tv")]
            level = spec.args.get("level", "high")
            s.forced_counts = (4095 if level == "high" else 0) if on else None
        elif kind in ("valve_stuck_open", "valve_stuck_closed"):
            valve = mech.sv_valve if spec.args.get("valve", "sv") == "sv" else mech.tv_valve
            valve.stuck = ("open" if kind == "valve_stuck_open" else "closed") if on else None
        elif kind == "latch_stall":
            mech.latch_stall = on
        elif kind == "actuator_jam":
            mech.plane_jam = on
        elif kind == "overpressure":
            if not on:
                mech.tank_offset_kpa[spec.args.get("tank", "sv")] = 0.0
        elif kind == "watchdog_reset":
            if on:
                rig.request_hang()
        elif kind == "host_crash":
            rig.host_crash(on)
        elif kind == "latch_wire_break":
            # One wire of the latch switch's changeover pair: "no" (engaged contact, the
            # default), "nc" (not-engaged contact) or "common" (the ground return).
            mech.latch_wire_broken = spec.args.get("wire", "no") if on else None
        elif kind in ("adc_glitch", "adc_glitch_run"):
            # `samples` consecutive conversions of one transducer read 0 counts (open wire),
            # then the sensor is fine again: one sample must not trip, a run must.
            n = int(spec.args.get("samples", 1 if kind == "adc_glitch" else 20))
            mech.adc_glitch_samples[spec.args.get("sensor", "tv")] = n if on else 0
        elif kind == "camera_unplugged":
            rig.camera_unplugged(on)
        elif kind == "serial_unplugged":
            rig.serial_unplugged(on)
        elif kind == "nav_hang":
            rig.nav_hang(on)
        elif kind == "slow_inference":
            rig.slow_inference(float(spec.args.get("latency_s", 0.3)) if on else 0.0)
        elif kind == "param_attack":
            # The host tries to zero or loosen each protection (args: {name: value}).
            if on:
                rig.host_param_attack(dict(spec.args.get("values", {})))
        elif kind in ("plane_retracted_wire_break", "home_wire_break"):
            # Switches are wired normally closed to ground with a pull-up: a broken wire reads
            # "actuated" for good (docs/hardware.md, Switch inputs).
            name = "PLANE_RETRACTED" if kind == "plane_retracted_wire_break" else "LATCH_HOME"
            if on:
                mech.di_forced[name] = True
            else:
                mech.di_forced.pop(name, None)
        elif kind == "switch_stuck":
            # A switch stuck at one level (a broken lever: never actuated; welded: always).
            name = SWITCHES[spec.args.get("switch", "plane_extended")]
            if on:
                mech.di_forced[name] = bool(spec.args.get("level", False))
            else:
                mech.di_forced.pop(name, None)
        elif kind == "plane_pos_adc_fail":
            # Every conversion of the plane's position sensor fails (hal_adc_read false).
            bit = 1 << ADC.index("PLANE_POS")
            mech.adc_fail_bits = (mech.adc_fail_bits | bit) if on else (mech.adc_fail_bits & ~bit)
        elif kind == "backflow":
            pass  # the supply's fall is played step by step (_backflow)
        elif kind == "mcu_reset":
            # The MCU restarts (reset pin, brown-out): outputs off, RAM lost, flash kept.
            if on:
                rig.request_reset()
        elif kind == "valve_slow_close":
            # Both valves stroke in stroke_s (e.g. 300 ms, slower than valve_mismatch_ms), and
            # the host sends ABORT at the injection: the plane must wait for the valves.
            if on:
                fault.state["stroke_s"] = mech.p.valve_stroke_s
                mech.p.valve_stroke_s = float(spec.args.get("stroke_s", 0.3))
                if spec.args.get("host_abort", True):
                    rig.host_command("CMD_ABORT")
            else:
                mech.p.valve_stroke_s = fault.state.get("stroke_s", mech.p.valve_stroke_s)

    @staticmethod
    def _replay(fault: ActiveFault, t_s: float, rig: Any) -> None:
        """An attacker on the wire sends the host's recorded ARM_TRANSFER and START_TRANSFER
        frames again every ``period_s`` (once the host has sent them): before, during and
        after the transfer, so also after it stopped. None may reopen the valves."""
        st = fault.state
        if t_s >= st.get("next_s", t_s):
            rig.wire.replay()
            st["next_s"] = t_s + float(fault.spec.args.get("period_s", 0.25))

    @staticmethod
    def _backflow(fault: ActiveFault, dt_s: float, rig: Any) -> None:
        """The supply tank falls below the target tank (a leak on the supply side, upstream of
        the couplings; an emptied supply) at ``rate_kpa_s`` (a real tank, not a sensor jump) down
        to ``sv_kpa``: with the valves open gas would flow back from the target tank."""
        args = fault.spec.args
        mech = rig.mech
        floor = float(args.get("sv_kpa", 250.0))
        rate = float(args.get("rate_kpa_s", 400.0))
        mech.sv_kpa = max(min(mech.sv_kpa, floor), mech.sv_kpa - rate * dt_s)

    @staticmethod
    def _overpressure(fault: ActiveFault, t_s: float, dt_s: float, rig: Any) -> None:
        """A thermal transient in one tank: ramp up to ``peak_kpa``, hold, ramp back down."""
        args = fault.spec.args
        tank = args.get("tank", "sv")
        rate = float(args.get("rate_kpa_s", 300.0))
        hold_s = float(args.get("hold_s", 5.0))
        mech = rig.mech
        base = mech.sv_kpa if tank == "sv" else mech.tv_kpa
        off = mech.tank_offset_kpa[tank]
        st = fault.state
        if "peak_at" not in st:
            if base + off >= float(args.get("peak_kpa", 2700.0)):
                st["peak_at"] = t_s
            else:
                off += rate * dt_s
        elif t_s >= st["peak_at"] + hold_s:
            off = max(0.0, off - rate * dt_s)
        mech.tank_offset_kpa[tank] = off
