"""Guidance: which phase, what relative velocity to command, when to send which mechanism
command, when to hold or retreat (SPEC sections 2 and 5). It runs on the companion computer
inside the navigation daemon (oibar.nav.core) and, unchanged, in the HIL rig.

    output = guidance.step(t_s, observation)   # -> GuidanceOutput

``Observation`` carries the navigation solution (the filtered CNN estimate, or ground truth in
the rig's reference runs), the latest MCU telemetry, new MCU events and the results of the
commands this guidance asked for. ``GuidanceOutput`` carries the relative-velocity setpoint for
the vehicle interface, a NavUpdate for the MCU, and at most one mechanism request (stop and wait).

Mission: approach in phases with closing-speed limits below the capture envelope (50 mm/s,
10 deg), hold at a gate until the MCU is armed and the alignment is good, push gently into the
drogue until the latches engage, then DOCK, HARD_DOCK, ARM_TRANSFER, START_TRANSFER(target),
wait for the fill, SEPARATE, back away.

Hold and abort rules:
- navigation not trustworthy this cycle (no fresh frame, low confidence, gated outlier):
  hold (zero relative velocity) in free flight;
- navigation lost for ``nav_lost_abort_s``: abort the mission and back off blind along the
  docking axis for ``blind_retreat_s``, then hold;
- link down: no mechanism command is sent, and the vehicle holds in free flight;
- any MCU FAULT -> CLEAR_FAULT (the MCU safes through ABORTING) -> SEPARATE -> retreat; a fill
  that stops progressing -> ABORT; a capture the MCU will not confirm -> ABORT; a fault that
  cannot be cleared -> hold ("safed").
All numbers are assumptions, named below with their units.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from oibar import pb
from oibar.geometry.docking import lateral_offset_m
from oibar.link.protocols import Event, Telemetry

MAX_CLEAR_ATTEMPTS = 3
MAX_RECOVERIES = 1  # after one recovered fault that recurs, leave it to the ground
CLEAR_RETRY_S = 2.0
SAFED_HOLD_S = 5.0
FILL_STALL_S = 5.0  # no TV pressure rise for this long while filling -> abort
# A mechanism command the MCU keeps refusing for a reason that will not pass by itself (a
# precondition: a stuck switch, a supply below the target tank, a sensor out of its window) is
# sent again each cycle; after this many refusals in a row the mission is aborted, so the
# sequence goes on to its safe end (disarm, unmate, separate) instead of asking for ever.
MAX_REFUSALS = 20  # 2 s of cycles
LASTING_REFUSALS = frozenset({"NACK_PRECONDITION_FAILED", "NACK_PREARM_SENSOR", "NACK_PREARM_IMPLAUSIBLE"})
FILL_STALL_MIN_RISE_KPA = 5.0
HOLD_GATE_RANGE_M = 0.5  # wait here until armed and aligned
GATE_MAX_LATERAL_M = 0.02
# Held at the gate for a misalignment alone, the vehicle turns its boresight in (tilt only, the
# part beyond ATT_DEADBAND_DEG) even with steer_attitude off: the vehicle's attitude hold keeps
# the attitude it started with, and without this a start turned 5.6 deg held at the gate until
# the mission timed out (campaign truth_1000, mission 12, docs/campaign.md). Stationary at
# 0.5 m, where the network reads attitude best, and only beyond the deadband, the network's
# ~1 deg bias cannot turn the vehicle away as it did when steering on it all the way in.
GATE_TURN_GAIN_PER_S = 0.5
GATE_TURN_MAX_RAD_S = float(np.radians(0.5))
GATE_MAX_MISALIGN_DEG = 5.0  # half the 10 deg capture envelope: the CNN's attitude is good to ~2 deg
CORRIDOR_SLOPE = 0.10  # approach corridor half-width per metre of range (a 5.7 deg cone)
CORRIDOR_MIN_HALF_WIDTH_M = 0.05
RETREAT_SPEED_MPS = 0.05
SEPARATION_BACKOFF_MPS = 0.03  # helps the spring-damper pre-load extract the probe
VALVES_CLOSED_BEFORE_SEPARATE_S = 0.5  # host-side guard: never unmate with a valve reading open
ATT_DEADBAND_DEG = (
    4.0  # attitude errors below this are left to the vehicle's attitude hold (< the 5 deg gate)
)
RECEPTION_PUSH_MPS = 0.05  # thrust demand after contact: ~7.5 N, enough to seat the latches

FREE_FLIGHT_STATES = {"STATE_UNSPECIFIED", "STATE_BOOT", "STATE_IDLE", "STATE_APPROACH_READY"}
DOCKED_STATES = {
    "STATE_RECEPTION",
    "STATE_SOFT_DOCKED",
    "STATE_HARD_DOCKING",
    "STATE_HARD_DOCKED",
    "STATE_TRANSFER_ARMED",
    "STATE_TRANSFERRING",
    "STATE_UNMATING",
    "STATE_LATCH_RELEASE",
    "STATE_ABORTING",
    "STATE_FAULT",
}


@dataclass
class MechRequest:
    """One request for the MCU: a command or a parameter set."""

    kind: str  # "command" or "param_set"
    opcode: int = 0
    target_kpa: float = 0.0
    param_id: int = 0
    value: float = 0.0
    label: str = ""


@dataclass
class RequestResult:
    request: MechRequest
    accepted: bool
    reason: str  # NackReason name, or the link error
    state: str = ""


@dataclass
class MissionParams:
    target_kpa: float = 1200.0  # TV tank fill target
    arm_range_m: float = 2.0  # send APPROACH_ARM inside this range
    retreat_to_m: float = 2.0  # back off to here after separation or an abort
    final_closing_mps: float = 0.03  # closing speed into the drogue (capture envelope: 0.05)
    nav_lost_abort_s: float = 5.0  # no trustworthy navigation this long in free flight: abort
    blind_retreat_s: float = 10.0  # then back off along +z_D this long without navigation
    # Attitude rates from the navigation solution. Off: the vehicle's own GNC holds the relative
    # attitude (both vehicles hold their attitude from their own sensors, as automated dockings
    # do) and the camera gives position. The shipped network's attitude follows the truth only
    # partly (slope 0.5-0.7, 1.2-1.8 deg RMS on the rig probe): closing the loop on it turned the
    # vehicle from 2.5 to 10.4 deg in the 10 m mission and the probe bounced off the drogue.
    steer_attitude: bool = False
    # Held at the 0.5 m gate (not armed, off-centre or misaligned) this long: abort and back off.
    # Every wait is bounded; an MCU arms in well under a second and a misalignment is turned out
    # at the gate in about 10 s (GATE_TURN_MAX_RAD_S), so a minute means the gate will not open.
    gate_hold_max_s: float = 60.0


@dataclass
class NavSolution:
    """What guidance needs from navigation, in the docking frame D (oibar.geometry.docking)."""

    valid: bool
    r_D_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    v_D_mps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    att_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    misalignment_deg: float = 0.0
    t_cam_target_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    q_cam_target: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    confidence: float = 0.0
    hold_reason: str = ""  # non-empty: do not move on this solution (why)

    @property
    def range_m(self) -> float:
        return float(self.r_D_m[2])

    @property
    def closing_speed_mps(self) -> float:
        return float(-self.v_D_mps[2])

    @property
    def lateral_m(self) -> float:
        return lateral_offset_m(self.r_D_m)


@dataclass
class Observation:
    t_s: float
    nav: NavSolution
    link_up: bool
    telemetry: Telemetry | None  # the newest MCU telemetry (pb.Telemetry); None before the first
    events: list[Event] = field(default_factory=list)
    results: list[RequestResult] = field(default_factory=list)


@dataclass
class GuidanceOutput:
    v_sp_D_mps: np.ndarray
    w_sp_rad_s: np.ndarray
    nav: pb.NavUpdate
    request: MechRequest | None
    phase: str


def gate_turn_rad_s(att_rad: np.ndarray) -> np.ndarray:
    """The body rate that turns the boresight's tilt (the attitude error about the camera's x and
    y, not the roll about it) in, beyond ATT_DEADBAND_DEG only (GATE_TURN_*)."""
    tilt = np.array([att_rad[0], att_rad[1], 0.0], dtype=float)
    size = float(np.linalg.norm(tilt))
    excess = max(0.0, size - np.radians(ATT_DEADBAND_DEG))
    out: np.ndarray = np.clip(
        -GATE_TURN_GAIN_PER_S * tilt * (excess / max(size, 1e-12)), -GATE_TURN_MAX_RAD_S, GATE_TURN_MAX_RAD_S
    )
    return out


def corridor_half_width_m(range_m: float) -> float:
    """The approach corridor's half-width at a probe range: 10 % of the range (a 5.7 deg cone,
    comfortably wider than the network's lateral error, 1-3 % of range), never under the 5 cm
    near the drogue that its 10 cm funnel forgives."""
    return max(CORRIDOR_MIN_HALF_WIDTH_M, CORRIDOR_SLOPE * max(range_m, 0.0))


def _name(enum: Any, value: int) -> str:
    return pb.enum_name(enum, value)


class Guidance:
    """Telemetry-driven: each step looks at the MCU's state and decides, so a restarted host
    (a new instance) picks the mission up where the MCU is."""

    def __init__(
        self, mission: MissionParams | None = None, firmware_params: dict[int, float] | None = None
    ) -> None:
        self.m = mission or MissionParams()
        self.param_queue = [
            MechRequest("param_set", param_id=i, value=v, label=f"PARAM_SET {i}={v:g}")
            for i, v in (firmware_params or {}).items()
        ]
        self.awaiting: MechRequest | None = None
        self.finished = False
        self.outcome = "running"  # completed | aborted | safed | running
        self.notes: list[tuple[float, str]] = []
        self.mission_aborted = False
        self.filled = False
        self.contacted = False
        self.clear_attempts = 0
        self.recoveries = 0
        self.gave_up_at: float | None = None
        self._last_clear_s = -1e9
        self._last_state = ""
        self._fill_ref = (0.0, 0.0)
        self._frame_id = 0
        self._dock_sent = False
        self._valves_closed_since: float | None = None
        self._nav_bad_since: float | None = None
        self._blind_retreat_until: float | None = None
        self._gate_hold_since: float | None = None  # when the vehicle began holding at the gate
        self._refusals: tuple[str, int] = ("", 0)  # (command, refusals in a row)

    # -- bookkeeping --------------------------------------------------------------------

    def _note(self, t_s: float, text: str) -> None:
        self.notes.append((t_s, text))

    def _abort_mission(self, t_s: float, why: str) -> None:
        if not self.mission_aborted:
            self.mission_aborted = True
            self._note(t_s, f"mission aborted: {why}")

    def _on_results(self, t_s: float, results: list[RequestResult]) -> None:
        for r in results:
            if r.request is self.awaiting:
                self.awaiting = None
            if r.request.kind == "param_set":
                if not r.accepted:
                    self._note(t_s, f"{r.request.label} refused: {r.reason}")
                continue
            op = _name(pb.CommandOpcode, r.request.opcode)
            if op == "CMD_DOCK" and not r.accepted:
                if r.reason == "NACK_PRECONDITION_FAILED":
                    self._abort_mission(t_s, "the MCU did not confirm the capture")
                else:
                    # lost on the link (LinkDown, LinkTimeout) or refused for now: the capture
                    # is still good, so DOCK goes out again while the latches hold
                    self._dock_sent = False
            if op == "CMD_CLEAR_FAULT" and r.accepted:
                self.recoveries += 1
            if r.accepted or r.reason not in LASTING_REFUSALS:
                if self._refusals[0] == op:
                    self._refusals = ("", 0)
            else:
                n = self._refusals[1] + 1 if self._refusals[0] == op else 1
                self._refusals = (op, n)
                if n >= MAX_REFUSALS:
                    self._abort_mission(t_s, f"{op} refused {n} times in a row ({r.reason})")

    def _on_state(self, t_s: float, state: str, tm: Telemetry) -> None:
        last = self._last_state
        if state == last:
            return
        self._last_state = state
        if state == "STATE_FAULT":
            self._abort_mission(t_s, f"MCU fault flags 0x{tm.fault_flags:x}")
            self.clear_attempts = 0
        elif last == "STATE_FAULT" and self.gave_up_at is not None:
            # the last clear was accepted after all (its answer came after the third try): the
            # MCU is on its way to a safe end (since issue 59's D1 an unconfirmed capture lets the
            # probe go and homes the latch, which takes longer than the hold), so follow it
            self.gave_up_at = None
            self._note(t_s, f"fault cleared: {state}")
        if last == "STATE_TRANSFERRING" and state == "STATE_HARD_DOCKED":
            if tm.tv_tank_kpa >= 0.99 * self.m.target_kpa:
                self.filled = True
                self._note(t_s, f"fill complete: TV tank {tm.tv_tank_kpa:.0f} kPa")
            else:
                self._abort_mission(t_s, "transfer ended below the target")
        if state == "STATE_TRANSFERRING":
            self._fill_ref = (t_s, tm.tv_tank_kpa)
        if state == "STATE_RECEPTION":
            self.contacted = True
            self._dock_sent = False

    # -- mechanism sequence -------------------------------------------------------------

    def _cmd(self, opcode: int, target_kpa: float = 0.0) -> MechRequest:
        return MechRequest(
            "command", opcode=opcode, target_kpa=target_kpa, label=_name(pb.CommandOpcode, opcode)
        )

    def _next_request(self, t_s: float, obs: Observation, state: str, tm: Telemetry) -> MechRequest | None:
        if self.param_queue and state in ("STATE_IDLE", "STATE_BOOT"):
            return self.param_queue.pop(0)
        done_docking = self.filled or self.mission_aborted
        if state == "STATE_IDLE":
            if (
                not self.contacted
                and not self.mission_aborted
                and self._trusted(obs)
                and obs.nav.range_m <= self.m.arm_range_m
            ):
                return self._cmd(pb.CMD_APPROACH_ARM)
        elif state == "STATE_APPROACH_READY":
            if self.mission_aborted:
                return self._cmd(pb.CMD_ABORT)
        elif state == "STATE_RECEPTION":
            if self.mission_aborted:
                return self._cmd(pb.CMD_ABORT)
            if tm.latch_engaged and not self._dock_sent:
                self._dock_sent = True
                return self._cmd(pb.CMD_DOCK)
        elif state == "STATE_SOFT_DOCKED":
            return self._cmd(pb.CMD_SEPARATE if done_docking else pb.CMD_HARD_DOCK)
        elif state == "STATE_HARD_DOCKED":
            if not done_docking:
                return self._cmd(pb.CMD_ARM_TRANSFER)
            # The firmware accepts SEPARATE while a valve still reads open (its mismatch
            # check needs 200 ms); unmating then would vent through the couplings. Wait.
            if tm.sv_valve_open or tm.tv_valve_open or tm.sv_valve_cmd_open or tm.tv_valve_cmd_open:
                self._valves_closed_since = None
                return None
            if self._valves_closed_since is None:
                self._valves_closed_since = t_s
            if t_s - self._valves_closed_since >= VALVES_CLOSED_BEFORE_SEPARATE_S:
                return self._cmd(pb.CMD_SEPARATE)
        elif state == "STATE_TRANSFER_ARMED":
            if done_docking:
                return self._cmd(pb.CMD_DISARM_TRANSFER)
            return self._cmd(pb.CMD_START_TRANSFER, self.m.target_kpa)
        elif state == "STATE_TRANSFERRING":
            t0, p0 = self._fill_ref
            if tm.tv_tank_kpa >= p0 + FILL_STALL_MIN_RISE_KPA:
                self._fill_ref = (t_s, tm.tv_tank_kpa)
            elif t_s - t0 >= FILL_STALL_S:
                self._abort_mission(
                    t_s, f"fill not progressing (TV tank {tm.tv_tank_kpa:.0f} kPa for {FILL_STALL_S:.0f} s)"
                )
                return self._cmd(pb.CMD_ABORT)
        elif state == "STATE_FAULT":
            if self.recoveries > MAX_RECOVERIES or self.clear_attempts >= MAX_CLEAR_ATTEMPTS:
                if self.gave_up_at is None:
                    self.gave_up_at = t_s
                    self._note(t_s, "fault not recoverable from here: holding, valves closed")
                return None
            if t_s - self._last_clear_s >= CLEAR_RETRY_S:
                self._last_clear_s = t_s
                self.clear_attempts += 1
                return self._cmd(pb.CMD_CLEAR_FAULT)
        return None

    # -- guidance -----------------------------------------------------------------------

    def _closing_speed_for(self, range_m: float) -> tuple[float, str]:
        if range_m > 3.0:
            return 0.15, "FORCED_TRANSLATION"
        if range_m > 1.0:
            return 0.08, "FORCED_TRANSLATION"
        if range_m > 0.3:
            return 0.04, "ALIGNMENT"
        return self.m.final_closing_mps, "SOFT_DOCK"

    @staticmethod
    def _trusted(obs: Observation) -> bool:
        return bool(obs.nav.valid and not obs.nav.hold_reason)

    def _guidance(
        self, obs: Observation, state: str, tm: Telemetry | None
    ) -> tuple[np.ndarray, np.ndarray, str]:
        nav = obs.nav
        trusted = self._trusted(obs)
        r = nav.range_m
        lat = nav.r_D_m[:2]
        v_lat = np.clip(-0.3 * lat, -0.05, 0.05)
        # Attitude: only errors beyond a deadband are corrected; inside it the vehicle's own
        # attitude hold keeps it. A small fixture seen head-on shows a camera rotation almost
        # like a lateral shift, so the network's attitude carries a bias of about a degree
        # (docs/navigation.md); steering on that bias would turn the vehicle away for ever (in the
        # rig: 2 deg to 32 deg in 100 s). The deadband stays under the 5 deg hold gate, so a real
        # misalignment is still removed.
        att_err = np.asarray(nav.att_rad, dtype=float)
        excess = max(0.0, float(np.linalg.norm(att_err)) - np.radians(ATT_DEADBAND_DEG))
        att_cmd = att_err * (excess / max(float(np.linalg.norm(att_err)), 1e-12))
        w = (
            np.clip(-0.5 * att_cmd, -np.radians(0.5), np.radians(0.5))
            if self.m.steer_attitude
            else np.zeros(3)
        )
        contact = bool(tm.contact) if tm is not None else False
        hold = (np.zeros(3), np.zeros(3), "HOLD")
        if self.finished:
            return hold
        if (
            self._blind_retreat_until is not None
            and obs.t_s < self._blind_retreat_until
            and state not in DOCKED_STATES
        ):
            # Navigation lost: back off along the docking axis, the one direction that cannot
            # hit the target, without attitude commands.
            return np.array([0.0, 0.0, RETREAT_SPEED_MPS]), np.zeros(3), "RETREAT"
        if state in ("STATE_SEPARATING", "STATE_LATCH_RESET") or (
            (self.contacted or self.mission_aborted) and state == "STATE_IDLE"
        ):
            if contact or (trusted and r < 0.0):
                return np.array([0.0, 0.0, SEPARATION_BACKOFF_MPS]), np.zeros(3), "RETREAT"
            if not trusted:
                return hold
            vz = RETREAT_SPEED_MPS if r < self.m.retreat_to_m else 0.0
            return np.array([0.0, 0.0, vz]), w, "RETREAT"
        if state == "STATE_RECEPTION" and not (tm and tm.latch_engaged) and not self.mission_aborted:
            return np.array([0.0, 0.0, -RECEPTION_PUSH_MPS]), np.zeros(3), "SOFT_DOCK"
        if not trusted or not obs.link_up:
            # Free flight (or docked) on navigation we may not act on, or with the MCU out of
            # reach: hold. Docked, holding is what the mechanism needs anyway.
            return hold
        if contact or state in DOCKED_STATES or self.mission_aborted:
            if not contact and r > 0.0 and state not in DOCKED_STATES:
                vz = RETREAT_SPEED_MPS if r < self.m.retreat_to_m else 0.0
                return np.array([0.0, 0.0, vz]), w, "RETREAT"
            return np.zeros(3), np.zeros(3), "HOLD"
        closing, phase = self._closing_speed_for(r)
        # Approach corridor: a cone around the docking axis. Outside it the vehicle stops closing
        # and centres first; well outside it (twice the half-width) it backs off while centring.
        half_width = corridor_half_width_m(r)
        lateral = float(np.hypot(*lat))
        if lateral > 2.0 * half_width:
            return np.array([v_lat[0], v_lat[1], RETREAT_SPEED_MPS]), w, "RETREAT"
        if lateral > half_width:
            closing, phase = 0.0, "HOLD"
        gate_ok = (
            state == "STATE_APPROACH_READY"
            and float(np.hypot(*lat)) <= GATE_MAX_LATERAL_M
            and nav.misalignment_deg <= GATE_MAX_MISALIGN_DEG
        )
        if r <= HOLD_GATE_RANGE_M + 0.05 and not gate_ok:
            # Hold at the gate: a proportional brake onto the gate range.
            closing = float(np.clip(0.2 * (r - HOLD_GATE_RANGE_M), -0.02, closing))
            phase = "HOLD"
            self._hold_at_gate(obs.t_s, state, float(np.hypot(*lat)), nav.misalignment_deg)
            if nav.misalignment_deg > GATE_MAX_MISALIGN_DEG and not self.m.steer_attitude:
                w = gate_turn_rad_s(att_err)
        else:
            self._gate_hold_since = None
        return np.array([v_lat[0], v_lat[1], -closing]), w, phase

    def _hold_at_gate(self, t_s: float, state: str, lateral_m: float, misalignment_deg: float) -> None:
        """Count the time held at the gate; past gate_hold_max_s, abort the mission (the retreat
        follows) and say what kept the gate closed."""
        if self._gate_hold_since is None:
            self._gate_hold_since = t_s
            return
        if t_s - self._gate_hold_since < self.m.gate_hold_max_s:
            return
        why = [
            text
            for text, bad in (
                (f"MCU {state.removeprefix('STATE_')}, not APPROACH_READY", state != "STATE_APPROACH_READY"),
                (
                    f"lateral {lateral_m * 100:.0f} cm > {GATE_MAX_LATERAL_M * 100:.0f}",
                    lateral_m > GATE_MAX_LATERAL_M,
                ),
                (
                    f"misaligned {misalignment_deg:.1f} deg > {GATE_MAX_MISALIGN_DEG:.0f}",
                    misalignment_deg > GATE_MAX_MISALIGN_DEG,
                ),
            )
            if bad
        ]
        self._abort_mission(t_s, f"held at the gate for {self.m.gate_hold_max_s:.0f} s ({'; '.join(why)})")

    def _nav(self, obs: Observation, phase: str) -> pb.NavUpdate:
        """The NavUpdate for the MCU. ``valid`` says the filter has a solution (initialised, not
        diverged); an invalid one carries no pose, range, speed or confidence at all, so the
        defaults of an uninitialised filter never read as data. A valid solution on a cycle
        guidance holds (gated outlier, no new frame) goes out with this cycle's estimate
        confidence (0 without a frame): the MCU's capture check wants it above its parameter."""
        n = obs.nav
        self._frame_id += 1
        nav = pb.NavUpdate()
        nav.frame_id = self._frame_id
        nav.stamp_ms = int(obs.t_s * 1000.0) & 0xFFFFFFFF
        nav.phase = pb.NavPhase.Value("NAV_PHASE_" + ("SOFT_DOCK" if phase == "SOFT_DOCK" else phase))
        nav.valid = bool(n.valid)
        if not nav.valid:
            return nav
        nav.t_cam_target_m.x, nav.t_cam_target_m.y, nav.t_cam_target_m.z = (
            float(v) for v in n.t_cam_target_m
        )
        q = n.q_cam_target
        nav.q_cam_target.w, nav.q_cam_target.x, nav.q_cam_target.y, nav.q_cam_target.z = (float(v) for v in q)
        nav.range_m = float(n.range_m)
        nav.closing_speed_mps = float(n.closing_speed_mps)
        nav.confidence = float(n.confidence)
        return nav

    # -- the interface ------------------------------------------------------------------

    def _watch_navigation(self, t_s: float, obs: Observation, state: str, tm: Telemetry | None) -> None:
        """Navigation lost in free flight for too long: abort and back off blind."""
        free_flight = state in FREE_FLIGHT_STATES and not (tm is not None and tm.contact)
        if self._trusted(obs) or not free_flight:
            self._nav_bad_since = None
            return
        if self._nav_bad_since is None:
            self._nav_bad_since = t_s
            self._note(t_s, f"holding: navigation {obs.nav.hold_reason or 'invalid'}")
        if t_s - self._nav_bad_since >= self.m.nav_lost_abort_s and self._blind_retreat_until is None:
            self._abort_mission(
                t_s,
                f"navigation lost for {self.m.nav_lost_abort_s:.0f} s ({obs.nav.hold_reason or 'invalid'})",
            )
            self._blind_retreat_until = t_s + self.m.blind_retreat_s
        if self._blind_retreat_until is not None and t_s >= self._blind_retreat_until and not self.finished:
            self.finished = True
            self.outcome = "aborted"
            self._note(t_s, "blind retreat done, navigation still lost: holding; mission aborted")

    def step(self, t_s: float, obs: Observation) -> GuidanceOutput:
        tm = obs.telemetry
        state = _name(pb.State, tm.state) if tm is not None else "STATE_UNSPECIFIED"
        self._on_results(t_s, obs.results)
        for ev in obs.events:
            if ev.id == pb.EVT_FAULT:
                self._note(t_s, f"MCU event: fault {_name(pb.FaultCode, ev.fault)}")
        if tm is not None:
            self._on_state(t_s, state, tm)
        self._watch_navigation(t_s, obs, state, tm)
        v_sp, w_sp, phase = self._guidance(obs, state, tm)
        request = None
        if not self.finished and obs.link_up and tm is not None and self.awaiting is None:
            request = self._next_request(t_s, obs, state, tm)
            self.awaiting = request
        self._check_finished(t_s, obs, state)
        return GuidanceOutput(v_sp, w_sp, self._nav(obs, phase), request, phase)

    def _check_finished(self, t_s: float, obs: Observation, state: str) -> None:
        if self.finished:
            return
        if (
            state == "STATE_IDLE"
            and (self.contacted or self.mission_aborted)
            and self._trusted(obs)
            and obs.nav.range_m >= self.m.retreat_to_m - 0.01
        ):
            self.finished = True
            self.outcome = "completed" if self.filled and not self.mission_aborted else "aborted"
        elif self.gave_up_at is not None and t_s - self.gave_up_at >= SAFED_HOLD_S:
            self.finished = True
            self.outcome = "safed"
        if self.finished:
            self._note(t_s, f"mission {self.outcome}")
