"""STAND-IN mission controller for the rig: ground-truth guidance plus the mechanism command
sequence. The navigation-daemon issue replaces it with the real host daemon (camera, OibarNet,
filter, guidance); keep the interface so that swap is one line in the runner:

    output = controller.step(t_s, observation)   # -> ControllerOutput

``Observation`` carries the relative pose (here ground truth; later the navigation filter's
estimate), the latest MCU telemetry, new MCU events and the results of the commands this
controller asked for. ``ControllerOutput`` carries the relative-velocity setpoint for the
vehicle interface, a NavUpdate for the MCU, and at most one mechanism request (stop and wait).

Mission (SPEC section 2): approach in phases with closing-speed limits below the capture
envelope, hold at a gate until the MCU is armed and the alignment is good, push gently into the
drogue until the latches engage, then DOCK, HARD_DOCK, ARM_TRANSFER, START_TRANSFER(target),
wait for the fill, SEPARATE, back away. Abort paths: any FAULT -> try CLEAR_FAULT (the MCU then
safes through ABORTING) -> SEPARATE -> retreat; a fill that stops progressing -> ABORT; a
capture the MCU will not confirm -> ABORT. A fault that cannot be cleared -> hold ("safed").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from oibar import pb

MAX_CLEAR_ATTEMPTS = 3
MAX_RECOVERIES = 1          # after one recovered fault that recurs, leave it to the ground
CLEAR_RETRY_S = 2.0
SAFED_HOLD_S = 5.0
FILL_STALL_S = 5.0          # no TV pressure rise for this long while filling -> abort
FILL_STALL_MIN_RISE_KPA = 5.0
HOLD_GATE_RANGE_M = 0.5     # wait here until armed and aligned
GATE_MAX_LATERAL_M = 0.02
GATE_MAX_MISALIGN_DEG = 2.0
RETREAT_SPEED_MPS = 0.05
SEPARATION_BACKOFF_MPS = 0.03  # helps the spring-damper pre-load extract the probe
VALVES_CLOSED_BEFORE_SEPARATE_S = 0.5  # host-side guard: never unmate with a valve reading open
RECEPTION_PUSH_MPS = 0.05   # thrust demand after contact: ~7.5 N, enough to seat the latches

DOCKED_STATES = {"STATE_RECEPTION", "STATE_SOFT_DOCKED", "STATE_HARD_DOCKING", "STATE_HARD_DOCKED",
                 "STATE_TRANSFER_ARMED", "STATE_TRANSFERRING", "STATE_UNMATING",
                 "STATE_LATCH_RELEASE", "STATE_ABORTING", "STATE_FAULT"}


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
class Observation:
    t_s: float
    r_D_m: np.ndarray
    v_D_mps: np.ndarray
    att_rad: np.ndarray
    range_m: float
    closing_speed_mps: float
    misalignment_deg: float
    t_cam_target_m: np.ndarray
    q_cam_target: np.ndarray
    link_up: bool
    telemetry: Any
    events: list = field(default_factory=list)
    results: list[RequestResult] = field(default_factory=list)


@dataclass
class ControllerOutput:
    v_sp_D_mps: np.ndarray
    w_sp_rad_s: np.ndarray
    nav: Any
    request: MechRequest | None
    phase: str


def _name(enum: Any, value: int) -> str:
    return pb.enum_name(enum, value)


class StandInController:
    """Telemetry-driven: each step looks at the MCU's state and decides, so a restarted host
    (a new instance) picks the mission up where the MCU is."""

    def __init__(self, mission: Any, firmware_params: dict[int, float] | None = None) -> None:
        self.m = mission
        self.param_queue = [MechRequest("param_set", param_id=i, value=v, label=f"PARAM_SET {i}={v:g}")
                            for i, v in (firmware_params or {}).items()]
        self.awaiting: MechRequest | None = None
        self.finished = False
        self.outcome = "running"     # completed | aborted | safed | running
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
            if op == "CMD_DOCK" and not r.accepted and r.reason == "NACK_PRECONDITION_FAILED":
                self._abort_mission(t_s, "the MCU did not confirm the capture")
            if op == "CMD_CLEAR_FAULT" and r.accepted:
                self.recoveries += 1

    def _on_state(self, t_s: float, state: str, tm: Any) -> None:
        last = self._last_state
        if state == last:
            return
        self._last_state = state
        if state == "STATE_FAULT":
            self._abort_mission(t_s, f"MCU fault flags 0x{tm.fault_flags:x}")
            self.clear_attempts = 0
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
        return MechRequest("command", opcode=opcode, target_kpa=target_kpa,
                           label=_name(pb.CommandOpcode, opcode))

    def _next_request(self, t_s: float, obs: Observation, state: str, tm: Any) -> MechRequest | None:
        if self.param_queue and state in ("STATE_IDLE", "STATE_BOOT"):
            return self.param_queue.pop(0)
        done_docking = self.filled or self.mission_aborted
        if state == "STATE_IDLE":
            if not self.contacted and not self.mission_aborted and obs.range_m <= self.m.arm_range_m:
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
                self._abort_mission(t_s, f"fill not progressing (TV tank {tm.tv_tank_kpa:.0f} kPa "
                                         f"for {FILL_STALL_S:.0f} s)")
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

    def _guidance(self, obs: Observation, state: str, tm: Any) -> tuple[np.ndarray, np.ndarray, str]:
        r = obs.range_m
        lat = obs.r_D_m[:2]
        v_lat = np.clip(-0.3 * lat, -0.05, 0.05)
        w = np.clip(-0.5 * obs.att_rad, -np.radians(0.5), np.radians(0.5))
        contact = bool(tm.contact) if tm is not None else False
        if self.finished:
            return np.zeros(3), np.zeros(3), "HOLD"
        if state in ("STATE_SEPARATING", "STATE_LATCH_RESET") or (
                (self.contacted or self.mission_aborted) and state == "STATE_IDLE"):
            if contact or r < 0.0:
                return np.array([0.0, 0.0, SEPARATION_BACKOFF_MPS]), np.zeros(3), "RETREAT"
            vz = RETREAT_SPEED_MPS if r < self.m.retreat_to_m else 0.0
            return np.array([0.0, 0.0, vz]), w, "RETREAT"
        if state == "STATE_RECEPTION" and not (tm and tm.latch_engaged) and not self.mission_aborted:
            return np.array([0.0, 0.0, -RECEPTION_PUSH_MPS]), np.zeros(3), "SOFT_DOCK"
        if contact or state in DOCKED_STATES or self.mission_aborted:
            if not contact and r > 0.0 and state not in DOCKED_STATES:
                vz = RETREAT_SPEED_MPS if r < self.m.retreat_to_m else 0.0
                return np.array([0.0, 0.0, vz]), w, "RETREAT"
            return np.zeros(3), np.zeros(3), "HOLD"
        closing, phase = self._closing_speed_for(r)
        gate_ok = (state == "STATE_APPROACH_READY" and float(np.hypot(*lat)) <= GATE_MAX_LATERAL_M
                   and obs.misalignment_deg <= GATE_MAX_MISALIGN_DEG)
        if r <= HOLD_GATE_RANGE_M + 0.05 and not gate_ok:
            # Hold at the gate: a proportional brake onto the gate range.
            closing = float(np.clip(0.2 * (r - HOLD_GATE_RANGE_M), -0.02, closing))
            phase = "HOLD"
        return np.array([v_lat[0], v_lat[1], -closing]), w, phase

    def _nav(self, obs: Observation, phase: str) -> Any:
        self._frame_id += 1
        nav = pb.NavUpdate()
        nav.frame_id = self._frame_id
        nav.stamp_ms = int(obs.t_s * 1000.0) & 0xFFFFFFFF
        nav.t_cam_target_m.x, nav.t_cam_target_m.y, nav.t_cam_target_m.z = (
            float(v) for v in obs.t_cam_target_m)
        q = obs.q_cam_target
        nav.q_cam_target.w, nav.q_cam_target.x, nav.q_cam_target.y, nav.q_cam_target.z = (
            float(v) for v in q)
        nav.range_m = float(obs.range_m)
        nav.closing_speed_mps = float(obs.closing_speed_mps)
        nav.phase = pb.NavPhase.Value("NAV_PHASE_" + ("SOFT_DOCK" if phase == "SOFT_DOCK" else phase))
        nav.confidence = 1.0  # ground truth
        return nav

    # -- the interface ------------------------------------------------------------------

    def step(self, t_s: float, obs: Observation) -> ControllerOutput:
        tm = obs.telemetry
        state = _name(pb.State, tm.state) if tm is not None else "STATE_UNSPECIFIED"
        self._on_results(t_s, obs.results)
        for ev in obs.events:
            if ev.id == pb.EVT_FAULT:
                self._note(t_s, f"MCU event: fault {_name(pb.FaultCode, ev.fault)}")
        if tm is not None:
            self._on_state(t_s, state, tm)
        v_sp, w_sp, phase = self._guidance(obs, state, tm)
        request = None
        if not self.finished and obs.link_up and tm is not None and self.awaiting is None:
            request = self._next_request(t_s, obs, state, tm)
            self.awaiting = request
        self._check_finished(t_s, obs, state)
        return ControllerOutput(v_sp, w_sp, self._nav(obs, phase), request, phase)

    def _check_finished(self, t_s: float, obs: Observation, state: str) -> None:
        if self.finished:
            return
        if state == "STATE_IDLE" and (self.contacted or self.mission_aborted) \
                and obs.range_m >= self.m.retreat_to_m - 0.01:
            self.finished = True
            self.outcome = "completed" if self.filled and not self.mission_aborted else "aborted"
        elif self.gave_up_at is not None and t_s - self.gave_up_at >= SAFED_HOLD_S:
            self.finished = True
            self.outcome = "safed"
        if self.finished:
            self._note(t_s, f"mission {self.outcome}")
