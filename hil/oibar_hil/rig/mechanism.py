"""The docking-and-refuelling mechanism as physics: what the MCU's sensors see and what its
actuators do (SPEC section 2; numbers consistent with firmware/app/src/params.c).

Pieces, each a small model:
- probe and drogue: capture only inside the envelope (closing speed <= 50 mm/s, yaw/pitch
  misalignment <= 10 deg, probe inside the funnel mouth); otherwise the probe bounces off;
- the probe's spring-damper (absorbs the contact shock, gives the extraction pre-load);
- the soft-dock latches (spring-loaded, pop out past the cavity; a detent holds them) and the
  latch cam driven by the stepper (home switch; release position; detents when unpowered);
- the fluidic plane (lead-screw actuator, end switches, potentiometer; pins and connector mate
  over the last millimetres, with a mating force);
- the two valves (normally closed, stroke time, position switches);
- tanks and transfer line (isothermal ideal gas, orifice flow; self-sealing couplings);
- pressure transducers, plane potentiometer and probe load cell as ADC counts.

Fault knobs (set by :mod:`.faults`) sit on :class:`Mechanism` as plain attributes.
Every number is in :class:`MechanismParams`; "paper" marks the four from the paper, the
rest are assumptions (docs/hil.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from oibar_hil.rig.lockstep import ADC, DI, McuReply

R_N2_J_KG_K = 296.8  # the simulant gas is nitrogen, for kilograms in the report
T_GAS_K = 293.0


@dataclass
class MechanismParams:
    # capture envelope (paper)
    capture_max_speed_mps: float = 0.050
    capture_max_misalign_deg: float = 10.0
    funnel_mouth_radius_m: float = 0.10  # assumption: drogue mouth radius
    funnel_throat_depth_m: float = 0.05  # assumption: funnel centres the probe by here
    # probe in the drogue (assumptions)
    spring_engage_depth_m: float = 0.066  # probe spring-damper touches the drogue end
    latch_depth_m: float = 0.075  # latches pop out behind the cavity here
    latch_hold_margin_m: float = 0.002  # detent play once latched
    end_stop_depth_m: float = 0.095  # spring fully compressed
    spring_n_per_m: float = 600.0  # 5.4 N extraction pre-load at the latch point
    damper_n_s_per_m: float = 150.0  # about 0.25 of critical with the SV mass
    bounce_restitution: float = 0.3
    bounce_contact_s: float = 0.03
    bounce_impact_s: float = 0.05  # impulse spread for the force estimate
    # latch cam and stepper (assumptions consistent with params.c ids 15-19)
    latch_release_steps: int = 600  # latches retracted from here on
    latch_release_detent_steps: int = 650
    latch_end_stop_steps: int = 1500
    latch_home_stop_steps: int = -20  # mechanical stop behind the home switch
    latch_detent_rate_steps_s: float = 200.0
    # fluidic plane (assumptions consistent with params.c ids 10, 32)
    plane_travel_mm: float = 40.0
    plane_speed_mm_s: float = 10.0
    plane_switch_band_mm: float = 0.2
    plane_mm_per_count: float = 0.01221
    pins_engage_mm: float = 37.0  # alignment pins enter their tapered cavities
    connector_mate_mm: float = 39.5
    seal_made_mm: float = 38.5  # coupling seals hold from here to full travel
    mating_force_n: float = 20.0  # at full mate, through the probe load cell
    # valves (assumption, params.c id 20 comment)
    valve_stroke_s: float = 0.05
    # gas (assumptions): isothermal nitrogen simulant, self-sealing couplings
    sv_volume_l: float = 60.0
    tv_volume_l: float = 20.0
    line_volume_l: float = 2.0
    sv_initial_kpa: float = 2200.0
    tv_initial_kpa: float = 300.0
    line_initial_kpa: float = 1000.0  # residual of the previous transfer
    valve_conductance_l_s: float = 0.84  # flow = G * dp (kPa*L/s)
    leak_conductance_l_s: float = 0.5  # coupling half-open to space (fault paths only)
    # sensors (params.c ids 21-26, 33)
    press_zero_counts: float = 410.0
    press_kpa_per_count: float = 0.9158
    force_n_per_count: float = 0.05
    adc_noise_counts: float = 0.7


@dataclass
class Valve:
    cmd_open: bool = False
    open: bool = False
    moving_s: float = 0.0
    stuck: str | None = None  # None, "open", "closed"

    def step(self, dt_s: float, coil_on: bool, stroke_s: float) -> None:
        self.cmd_open = coil_on
        if self.stuck is not None:
            self.open = self.stuck == "open"
            self.moving_s = 0.0
            return
        if coil_on != self.open:
            self.moving_s += dt_s
            if self.moving_s >= stroke_s:
                self.open = coil_on
                self.moving_s = 0.0
        else:
            self.moving_s = 0.0


@dataclass
class SensorFault:
    stuck_counts: int | None = None  # frozen reading
    forced_counts: int | None = None  # out of range (open wire / short)


@dataclass
class Mechanism:
    p: MechanismParams
    rng: np.random.Generator
    # probe / latch
    captured: bool = False
    latched: bool = False
    bounce_left_s: float = 0.0
    impact_force_n: float = 0.0
    capture_record: dict | None = None
    capture_attempts: list = field(default_factory=list)
    latch_steps: float = 0.0
    latch_stall: bool = False
    # plane
    plane_mm: float = 0.0
    plane_jam: bool = False
    # valves and gas
    sv_valve: Valve = field(default_factory=Valve)
    tv_valve: Valve = field(default_factory=Valve)
    sv_kpa: float = 0.0
    tv_kpa: float = 0.0
    line_kpa: float = 0.0
    tank_offset_kpa: dict = field(default_factory=lambda: {"sv": 0.0, "tv": 0.0})
    fuel_lost_kpa_l: float = 0.0
    # forces
    spring_force_n: float = 0.0
    contact_force_n: float = 0.0
    # sensors
    sensor_faults: dict = field(
        default_factory=lambda: {"sv": SensorFault(), "tv": SensorFault(), "line": SensorFault()}
    )
    adc_fail_bits: int = 0
    # latch switch wiring (a changeover pair, common to ground): None, or the broken wire
    # "no" (engaged contact), "nc" (not-engaged contact) or "common"
    latch_wire_broken: str | None = None
    # pressure transducers: bad ADC samples still to come, per sensor (one per 1 ms exchange)
    adc_glitch_samples: dict = field(default_factory=lambda: {"sv": 0, "tv": 0, "line": 0})
    # digital inputs forced to a level whatever the mechanism does (issue 59 item 5): a broken
    # wire of a switch wired normally closed to ground reads "actuated" (docs/hardware.md,
    # Switch inputs), a stuck or welded switch reads its stuck level; by lockstep DI name
    di_forced: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.sv_kpa = self.p.sv_initial_kpa
        self.tv_kpa = self.p.tv_initial_kpa
        self.line_kpa = self.p.line_initial_kpa
        self._last_counts = {"sv": 0, "tv": 0, "line": 0}

    # -- derived facts ------------------------------------------------------------------

    @property
    def plane_extended(self) -> bool:
        return self.plane_mm >= self.p.plane_travel_mm - self.p.plane_switch_band_mm

    @property
    def plane_retracted(self) -> bool:
        return self.plane_mm <= self.p.plane_switch_band_mm

    @property
    def connector_mated(self) -> bool:
        return self.latched and self.plane_mm >= self.p.connector_mate_mm

    @property
    def coupling_mated(self) -> bool:
        return self.connector_mated

    @property
    def latch_home(self) -> bool:
        return self.latch_steps <= 0.0

    @property
    def latch_released(self) -> bool:
        return self.latch_steps >= self.p.latch_release_steps

    @property
    def adc_glitch_pending(self) -> bool:
        """A glitch is being played: the rig then runs 1 ms exchanges, one sample each."""
        return any(n > 0 for n in self.adc_glitch_samples.values())

    @property
    def contact(self) -> bool:
        return self.captured or self.bounce_left_s > 0.0

    def gas_kg(self, kpa_l: float) -> float:
        return kpa_l * 1000.0 * 1e-3 / (R_N2_J_KG_K * T_GAS_K)  # p[Pa]*V[m3]/(R T)

    @property
    def fuel_lost_kg(self) -> float:
        return self.gas_kg(self.fuel_lost_kpa_l)

    @property
    def tv_true_kpa(self) -> float:
        return self.tv_kpa + self.tank_offset_kpa["tv"]

    @property
    def sv_true_kpa(self) -> float:
        return self.sv_kpa + self.tank_offset_kpa["sv"]

    # -- probe and drogue ---------------------------------------------------------------

    def _entry(self, world, t_s: float) -> None:
        """The probe tip crosses the drogue mouth: capture or bounce (SPEC section 2)."""
        p = self.p
        rec = {
            "t_s": t_s,
            "closing_speed_mps": world.closing_speed_mps,
            "misalignment_deg": world.misalignment_deg,
            "lateral_m": world.lateral_m,
        }
        rec["captured"] = (
            rec["closing_speed_mps"] <= p.capture_max_speed_mps
            and rec["misalignment_deg"] <= p.capture_max_misalign_deg
            and rec["lateral_m"] <= p.funnel_mouth_radius_m
        )
        self.capture_attempts.append(rec)
        if rec["captured"]:
            self.captured = True
            if self.capture_record is None:
                self.capture_record = rec
            return
        # Outside the envelope: the probe glances off the funnel.
        v = world.s.v_D_mps
        dv = (1.0 + p.bounce_restitution) * max(0.0, -v[2])
        v[2] = p.bounce_restitution * max(0.0, -v[2])
        world.s.r_D_m[2] = 0.001
        self.bounce_left_s = p.bounce_contact_s
        self.impact_force_n = world.p.mass_kg * dv / p.bounce_impact_s

    def _probe_forces(self, world, dt_s: float, t_s: float) -> np.ndarray:
        p = self.p
        s = world.s
        depth = -s.r_D_m[2]
        f = np.zeros(3)
        if not self.captured:
            if depth >= 0.0 and self.bounce_left_s <= 0.0:
                self._entry(world, t_s)
                depth = -s.r_D_m[2]
            if not self.captured:
                self.spring_force_n = 0.0
                return f
        if depth < 0.0:  # pulled out of the drogue
            self.captured = False
            self.latched = False
            self.spring_force_n = 0.0
            return f
        # The funnel centres the probe and limits misalignment as it goes in.
        frac = min(1.0, depth / p.funnel_throat_depth_m)
        world.clamp_lateral(p.funnel_mouth_radius_m * (1.0 - frac) + 0.001)
        world.clamp_misalignment(np.radians(p.capture_max_misalign_deg * (1.0 - frac) + 0.5))
        # Spring-damper along the axis, pushing the probe back out (+z_D).
        x = depth - p.spring_engage_depth_m
        if x > 0.0:
            xdot = -s.v_D_mps[2]
            self.spring_force_n = max(0.0, p.spring_n_per_m * x + p.damper_n_s_per_m * xdot)
        else:
            self.spring_force_n = 0.0
        f[2] = self.spring_force_n
        # Latches: pop out past the cavity while the cam is home; released by the cam.
        if not self.latched and depth >= p.latch_depth_m and self.latch_steps < p.latch_release_steps / 2:
            self.latched = True
        if self.latched and self.latch_released:
            self.latched = False
        return f

    def _probe_limits(self, world) -> None:
        p = self.p
        s = world.s
        depth = -s.r_D_m[2]
        if self.captured and depth > p.end_stop_depth_m:
            s.r_D_m[2] = -p.end_stop_depth_m
            s.v_D_mps[2] = max(0.0, s.v_D_mps[2])
        if self.latched and depth < p.latch_depth_m - p.latch_hold_margin_m:
            s.r_D_m[2] = -(p.latch_depth_m - p.latch_hold_margin_m)  # the latch detent holds
            s.v_D_mps[2] = min(0.0, s.v_D_mps[2])

    # -- actuators ----------------------------------------------------------------------

    def _latch_cam(self, dt_s: float, out: McuReply) -> None:
        p = self.p
        if out.do("LATCH_ENABLE"):
            if not self.latch_stall:
                self.latch_steps += out.steps_fwd - out.steps_rev
        else:
            # Unpowered, the cam settles into its nearest detent (home or released).
            goal = (
                0.0 if self.latch_steps < p.latch_release_detent_steps / 2 else p.latch_release_detent_steps
            )
            d = goal - self.latch_steps
            step = p.latch_detent_rate_steps_s * dt_s
            self.latch_steps += float(np.clip(d, -step, step))
        self.latch_steps = float(np.clip(self.latch_steps, p.latch_home_stop_steps, p.latch_end_stop_steps))

    def _plane(self, dt_s: float, out: McuReply) -> None:
        p = self.p
        ext, ret = out.do("PLANE_EXTEND"), out.do("PLANE_RETRACT")
        if self.plane_jam or ext == ret:
            return
        v = p.plane_speed_mm_s if ext else -p.plane_speed_mm_s
        self.plane_mm = float(np.clip(self.plane_mm + v * dt_s, 0.0, p.plane_travel_mm))

    def _gas(self, dt_s: float) -> None:
        p = self.p
        G, G_leak = p.valve_conductance_l_s, p.leak_conductance_l_s
        q_sv = G * (self.sv_kpa - self.line_kpa) if self.sv_valve.open else 0.0
        q_tv = G * (self.line_kpa - self.tv_kpa) if (self.tv_valve.open and self.coupling_mated) else 0.0
        # A coupling half-mated (pins in, seals not made) with a valve open vents to space;
        # fully unmated couplings are self-sealing. Only fault paths get here.
        half_mated = self.latched and p.pins_engage_mm - 7.0 <= self.plane_mm < p.seal_made_mm
        leak_line = G_leak * max(0.0, self.line_kpa) if (half_mated and self.sv_valve.open) else 0.0
        leak_tv = G_leak * max(0.0, self.tv_kpa) if (half_mated and self.tv_valve.open) else 0.0
        # Explicit Euler is stable here: dt * G / V_line <= 0.02 * 0.84 / 2 << 1.
        self.sv_kpa -= q_sv * dt_s / p.sv_volume_l
        self.line_kpa += (q_sv - q_tv - leak_line) * dt_s / p.line_volume_l
        self.tv_kpa += (q_tv - leak_tv) * dt_s / p.tv_volume_l
        self.fuel_lost_kpa_l += (leak_line + leak_tv) * dt_s

    # -- one plant step -----------------------------------------------------------------

    def step(self, dt_s: float, t_s: float, out: McuReply, world) -> np.ndarray:
        """Advance the mechanism by ``dt_s`` with the MCU's outputs; return the axial force
        (in D) the probe puts on the SV."""
        p = self.p
        self.bounce_left_s = max(0.0, self.bounce_left_s - dt_s)
        if self.bounce_left_s <= 0.0:
            self.impact_force_n = 0.0
        self._latch_cam(dt_s, out)
        self._plane(dt_s, out)
        self.sv_valve.step(dt_s, out.do("SV_VALVE"), p.valve_stroke_s)
        self.tv_valve.step(dt_s, out.do("TV_VALVE"), p.valve_stroke_s)
        self._gas(dt_s)
        f = self._probe_forces(world, dt_s, t_s)
        mating = 0.0
        if self.latched and self.plane_mm > p.pins_engage_mm:
            span = p.plane_travel_mm - p.pins_engage_mm
            mating = p.mating_force_n * min(1.0, (self.plane_mm - p.pins_engage_mm) / span)
        self.contact_force_n = self.spring_force_n + mating + self.impact_force_n
        return f

    def after_motion(self, world) -> None:
        self._probe_limits(world)

    # -- sensors ------------------------------------------------------------------------

    def _press_counts(self, name: str, kpa: float) -> int:
        p = self.p
        fault = self.sensor_faults[name]
        if self.adc_glitch_samples[name] > 0:
            self.adc_glitch_samples[name] -= 1
            return 0  # one conversion reads like an open wire (EMI, a loose crimp)
        if fault.forced_counts is not None:
            return fault.forced_counts
        if fault.stuck_counts is not None:
            return fault.stuck_counts
        c = self.counts_of_kpa(kpa, noise_counts=self.rng.normal(0.0, p.adc_noise_counts))
        self._last_counts[name] = c
        return c

    def last_counts(self, name: str) -> int:
        return self._last_counts[name]

    def counts_of_kpa(self, kpa: float, noise_counts: float = 0.0) -> int:
        """The ADC counts a healthy pressure sensor gives for `kpa` (plus `noise_counts`)."""
        c = kpa / self.p.press_kpa_per_count + self.p.press_zero_counts + noise_counts
        return int(round(min(4095.0, max(0.0, c))))

    def di_bits(self) -> int:
        levels = {
            "CONTACT": self.contact,
            "LATCH_ENGAGED": self.latched and self.latch_wire_broken not in ("no", "common"),
            "LATCH_NOT_ENGAGED": not self.latched and self.latch_wire_broken not in ("nc", "common"),
            "LATCH_HOME": self.latch_home,
            "PLANE_EXTENDED": self.plane_extended,
            "PLANE_RETRACTED": self.plane_retracted,
            "CONNECTOR_MATED": self.connector_mated,
            "SV_VALVE_OPEN": self.sv_valve.open,
            "TV_VALVE_OPEN": self.tv_valve.open,
        }
        levels.update(self.di_forced)
        return sum(1 << DI.index(k) for k, v in levels.items() if v)

    def adc_counts(self) -> list[int]:
        p = self.p
        counts = {
            "SV_TANK": self._press_counts("sv", self.sv_true_kpa),
            "TV_TANK": self._press_counts("tv", self.tv_true_kpa),
            "LINE": self._press_counts("line", self.line_kpa),
            "PLANE_POS": int(round(self.plane_mm / p.plane_mm_per_count)),
            "CONTACT_FORCE": int(round(min(4095.0, self.contact_force_n / p.force_n_per_count))),
        }
        return [counts[name] for name in ADC]
