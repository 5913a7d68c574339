"""One campaign mission: a draw -> a rig Scenario and its navigation -> ``Rig.run()`` -> one row.

The scenario is the rig's own (oibar_hil.rig.scenario), run by the rig's runner; a drawn fault
is injected as the fault matrix injects it (``matrix.FAULT_ARGS``, its phase's ``at_state``
trigger) and judged by the matrix's expectation and generic checks. So a mission succeeds when:

- no fault drawn: the mission completed (captured, soft and hard docked, filled to the target
  within ``fill_tolerance_kpa`` of true pressure, separated), no MCU fault, nothing vented, and
  every requirement of checks.py held (capture envelope, contact forces, valves, safe end);
- a fault drawn: every check the fault matrix makes of that cell held (the expected outcome,
  fault codes and final state, the generic G-* checks, the requirements).

Navigation: ``truth`` is the world's pose with a modelled error (``NoisyTruthNav``: a constant
lateral bias and white noise growing with range, drawn per mission); ``cnn`` renders the camera
for the drawn scene (port, epoch, Sun, noise, blur, exposure) and runs the flight Navigator on
onnxruntime with one thread, as every mission of a campaign must take one core.
"""

from __future__ import annotations

import os
import resource
import socket
import time
import traceback
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np

from oibar.geometry.docking import R_D_cam_from_attitude, camera_pose_from_docking, misalignment_deg
from oibar.geometry.rotations import matrix_to_quat
from oibar.nav.guidance import NavSolution
from oibar_hil.campaign.dispersion import CampaignConfig, MissionDraw, draw_mission
from oibar_hil.rig.checks import evaluate
from oibar_hil.rig.matrix import FAULT_ARGS, FUEL_LOST_MAX_KG, PHASES, expectation, generic_checks
from oibar_hil.rig.mechanism import MechanismParams
from oibar_hil.rig.navigation import TruthNav
from oibar_hil.rig.scenario import Scenario

CAMERA_BEHIND_TIP_M = 0.57  # camera to probe tip along the axis (as the rig's nav metrics take it)
NAV_RANGE_SIGMA_FACTOR = 3.0  # a monocular fit's range error is several times its lateral one
NAV_VELOCITY_TAU_S = 2.0  # the filter's velocity: the position noise over about this window
ENV_THREADS = {  # one core per mission: the renderer (llvmpipe), BLAS/OpenMP, onnxruntime (threads=1)
    "LP_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}


class NoisyTruthNav(TruthNav):
    """Ground truth with a modelled navigation error: per cycle, lateral noise of 1-sigma
    ``floor + per_m * d`` (d: camera to drogue), range noise ``NAV_RANGE_SIGMA_FACTOR`` times
    that, attitude noise ``att_sigma_deg`` per axis, and a constant lateral bias. The rest of
    TruthNav (token frames, holding on stale frames) is unchanged."""

    def __init__(
        self,
        *,
        floor_m: float,
        per_m: float,
        att_sigma_deg: float,
        bias_xy_m: tuple[float, float],
        rng: np.random.Generator,
    ) -> None:
        super().__init__()
        self.floor_m = float(floor_m)
        self.per_m = float(per_m)
        self.att_sigma_rad = float(np.radians(att_sigma_deg))
        self.bias_m = np.array([bias_xy_m[0], bias_xy_m[1], 0.0])
        self.noise_rng = rng

    def solve(self, t_s: float, world: Any) -> NavSolution:
        s = world.s
        d_m = max(float(s.r_D_m[2]) + CAMERA_BEHIND_TIP_M, 0.3)
        sigma_m = self.floor_m + self.per_m * d_m
        n = self.noise_rng.normal(0.0, 1.0, 9)
        r = s.r_D_m + self.bias_m + sigma_m * np.array([n[0], n[1], NAV_RANGE_SIGMA_FACTOR * n[2]])
        v = s.v_D_mps + (sigma_m / NAV_VELOCITY_TAU_S) * n[3:6]
        att = s.att_rad + self.att_sigma_rad * n[6:9]
        T, R = camera_pose_from_docking(r, att)
        return NavSolution(
            valid=True,
            r_D_m=r,
            v_D_mps=v,
            att_rad=att,
            misalignment_deg=misalignment_deg(R_D_cam_from_attitude(att)),
            t_cam_target_m=T,
            q_cam_target=matrix_to_quat(R),
            confidence=1.0,
        )


def epoch_utc(epoch_day: float) -> str:
    from oibar_hil.orbit import DEFAULT_EPOCH_UTC, parse_utc

    return (parse_utc(DEFAULT_EPOCH_UTC) + timedelta(days=float(epoch_day))).isoformat()


def beta_angle_deg(epoch: str, sun_elevation_deg: float) -> float:
    """The Sun's angle above the orbit plane when the approach starts (the rendered camera's
    start: the first time after ``epoch`` at which the Sun has that in-plane elevation)."""
    from oibar_hil.orbit import DEFAULT_TLE, TargetOrbit, julian_date, parse_utc

    orbit = TargetOrbit(DEFAULT_TLE)
    start = orbit.time_for_sun_elevation(parse_utc(epoch), sun_elevation_deg)
    return orbit.state(julian_date(start)).beta_deg


def scene_of(draw: MissionDraw) -> Any:
    """The rendered camera's scene for a draw (cnn): port, epoch, Sun, sensor noise and blur."""
    from oibar_hil.dataset import SequenceSpec
    from oibar_hil.ports import PORTS

    v = draw.values
    port = int(v["approach_port"])
    return SequenceSpec(
        name=f"mission{draw.index:06d}",
        port=port,
        approach=PORTS[port].approach,
        sun_elevation_deg=float(v["sun_elevation_deg"]),
        background="iss",
        seed=1000 + port,  # the Perlin backdrop's seed (unused on the station's background)
        epoch_utc=epoch_utc(v["epoch_day"]),
        noise_sigma_dn=float(v["camera_noise_dn"]),
        blur_sigma_px=float(v["camera_blur_px"]),
    )


def expect_of(cfg: CampaignConfig, draw: MissionDraw) -> dict[str, Any]:
    """What the mission must show to count as a success (checks.py's ``expect`` keys)."""
    target = float(cfg.mission.get("target_kpa", 1200.0))
    fill_min = target - cfg.fill_tolerance_kpa
    if not draw.fault:
        return {
            "outcome": "completed",
            "final_state": "STATE_IDLE",
            "captured": True,
            "tv_min_kpa": fill_min,
            "fuel_lost_max_kg": FUEL_LOST_MAX_KG,
            "faults": [],
        }
    exp = expectation(draw.fault, draw.fault_phase)
    if isinstance(exp, str):  # draw_fault never picks such a cell
        raise ValueError(f"{draw.fault}@{draw.fault_phase} is not applicable: {exp}")
    out: dict[str, Any] = {
        "outcome": exp.outcome,
        "final_state": exp.final_state,
        "faults": exp.faults,
        "fuel_lost_max_kg": FUEL_LOST_MAX_KG,
        **exp.extra,
    }
    if "tv_min_kpa" in out:  # the matrix's figure is for its own 600 kPa target
        out["tv_min_kpa"] = fill_min
    return out


def build_scenario(cfg: CampaignConfig, draw: MissionDraw) -> Scenario:
    """The rig scenario of one draw (every dispersed input at its place: dispersion.INPUTS)."""
    v = draw.values
    mp = MechanismParams()
    faults = []
    if draw.fault:
        ph = next(p for p in PHASES if p.key == draw.fault_phase)
        faults.append(
            {"type": draw.fault, "at_state": ph.at_state, "after_s": ph.after_s, **FAULT_ARGS[draw.fault]}
        )
    what = f"{draw.fault} during {draw.fault_phase}" if draw.fault else "no fault"
    return Scenario.from_dict(
        {
            "name": f"{cfg.name}_m{draw.index:06d}",
            "description": f"campaign {cfg.name} (seed {cfg.seed}) mission {draw.index}: {what}",
            "seed": draw.rig_seed,
            "start": {
                "range_m": v["start_range_m"],
                "lateral_m": [v["start_lateral_x_m"], v["start_lateral_y_m"]],
                "misalignment_deg": [v["start_pitch_deg"], v["start_yaw_deg"]],
                "closing_speed_mps": v["start_closing_speed_mps"],
                "lateral_speed_mps": [v["start_lateral_speed_x_mps"], v["start_lateral_speed_y_mps"]],
                "roll_deg": v["start_roll_deg"],
                "rate_deg_s": [v["start_rate_x_deg_s"], v["start_rate_y_deg_s"], v["start_rate_z_deg_s"]],
            },
            "mission": dict(cfg.mission),
            "rig": {
                "max_time_s": cfg.max_time_s,
                "flash_image": draw.fault == "mcu_reset",  # as the matrix: the flash survives the reset
                "wire_ber": v["link_ber"],
            },
            "plant": {
                "adc_noise_counts": v["adc_noise_counts"],
                "press_zero_counts": mp.press_zero_counts + v["pressure_offset_counts"],
                "press_kpa_per_count": mp.press_kpa_per_count * (1.0 + v["pressure_gain_error_pct"] / 100.0),
                "force_n_per_count": mp.force_n_per_count * (1.0 + v["load_cell_gain_error_pct"] / 100.0),
                "valve_stroke_s": v["valve_stroke_s"],
            },
            "vehicle": {
                "mass_kg": v["chaser_mass_kg"],
                "ang_accel_max_rad_s2": v["chaser_ang_accel_max_rad_s2"],
                "thrust_max_n": v["thrust_max_n"],
                "accel_noise_mps2": v["thrust_noise_mps2"],
                "accel_bias_mps2": (
                    v["thrust_bias_x_mps2"],
                    v["thrust_bias_y_mps2"],
                    v["thrust_bias_z_mps2"],
                ),
                "velocity_tau_s": v["velocity_tau_s"],
                "odometry_sigma_mps": v["odometry_sigma_mps"],
                "odometry_bias_mps": v["odometry_bias_sigma_mps"],
            },
            "faults": faults,
            "expect": expect_of(cfg, draw),
        }
    )


def make_nav(cfg: CampaignConfig, draw: MissionDraw, model_path: str | None = None) -> Any:
    """The mission's navigation source (rig.navigation's, or the modelled-noise truth)."""
    v = draw.values
    if cfg.nav == "truth":
        return NoisyTruthNav(
            floor_m=v["nav_sigma_floor_m"],
            per_m=v["nav_sigma_per_m"],
            att_sigma_deg=v["nav_att_sigma_deg"],
            bias_xy_m=(v["nav_bias_x_m"], v["nav_bias_y_m"]),
            rng=np.random.default_rng(draw.nav_seed),
        )
    from oibar_hil.rig.navigation import CnnNav

    return CnnNav(
        model_path=model_path,
        scene=scene_of(draw),
        seed=draw.nav_seed,
        threads=1,
        camera_options={"exposure": v["camera_exposure"]},
    )


@dataclass
class MissionRun:
    """A finished mission: its row, and the rig's result for a replay's report (None on error)."""

    row: dict[str, Any]
    result: Any = None


def _cpu_s() -> float:
    """CPU seconds of this process and its finished children (the simulated MCU, once it has
    exited): the cost of a mission on a shared machine, where wall time says more about the load."""
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _abort_reason(notes: list[tuple[float, str]]) -> str:
    for _, text in notes:
        if text.startswith("mission aborted: "):
            return text[len("mission aborted: ") :]
    return ""


def run_mission(
    cfg: CampaignConfig,
    index: int,
    *,
    mcu_path: str | None = None,
    model_path: str | None = None,
    out_dir: Path | None = None,
) -> MissionRun:
    """Fly mission ``index`` in this process and judge it. A rig that raises is a failed
    mission (outcome "error"), recorded like any other, never an exception."""
    from oibar_hil.rig.runner import Rig

    for k, val in ENV_THREADS.items():
        os.environ.setdefault(k, val)
    wall0 = time.perf_counter()
    cpu0 = _cpu_s()
    draw = draw_mission(cfg, index)
    v = draw.values
    epoch = epoch_utc(v["epoch_day"])
    row: dict[str, Any] = {
        "index": index,
        "campaign": cfg.name,
        "campaign_seed": cfg.seed,
        "config_id": cfg.identity(),
        "nav": cfg.nav,
        "rig_seed": draw.rig_seed,
        "nav_seed": draw.nav_seed,
        "fault": draw.fault,
        "fault_phase": draw.fault_phase,
        "epoch_utc": epoch,
        "beta_deg": beta_angle_deg(epoch, v["sun_elevation_deg"]),
        **{f"in_{k}": val for k, val in v.items()},
    }
    result = None
    try:
        sc = build_scenario(cfg, draw)
        nav = make_nav(cfg, draw, model_path)
        rig = Rig(sc, mcu_path=Path(mcu_path) if mcu_path else None, out_dir=out_dir, nav=nav)
        result = rig.run()
        result.checks = evaluate(result)
        if draw.fault:
            result.checks += generic_checks(draw.fault, result)
        row.update(_outcome_columns(result, rig))
    except Exception as exc:  # noqa: BLE001 - a rig that raises is a failed mission, with its reason
        tb = traceback.format_exc(limit=3).strip().splitlines()
        row.update(
            outcome="error",
            success=False,
            failed_checks="",
            error=f"{type(exc).__name__}: {exc} | {' / '.join(tb[-3:])}"[:2000],
        )
    row["wall_time_s"] = time.perf_counter() - wall0
    row["cpu_time_s"] = _cpu_s() - cpu0
    row["worker"] = f"{socket.gethostname()}:{os.getpid()}"
    return MissionRun(complete_row(row), result)


def _outcome_columns(result: Any, rig: Any) -> dict[str, Any]:
    m = result.metrics
    cap = result.capture or {}
    mech = rig.mech
    tv0 = mech.p.tv_initial_kpa
    failed = [f"{c.id} ({c.measured})" for c in result.checks if c.ok is False]
    return {
        "outcome": result.outcome,
        "success": not failed,
        "failed_checks": "; ".join(failed),
        "abort_reason": _abort_reason(result.notes),
        "error": "",
        "final_state": m["final_state"],
        "captured": bool(m["captured"]),
        "capture_attempts": len(result.capture_attempts),
        "contact_t_s": cap.get("t_s"),
        "contact_lateral_m": cap.get("lateral_m"),
        "contact_closing_speed_mps": cap.get("closing_speed_mps"),
        "contact_misalignment_deg": cap.get("misalignment_deg"),
        "peak_force_n": m["max_force_n"],
        "peak_force_soft_n": m["max_force_soft_n"],
        "fuel_lost_kg": m["fuel_lost_kg"],
        "fuel_transferred_kg": mech.gas_kg((mech.tv_kpa - tv0) * mech.p.tv_volume_l),
        "tv_final_kpa": m["tv_final_kpa"],
        "faults_seen": ",".join(m["faults_seen"]),
        "faults_reported": ",".join(m["faults_reported_to_host"]),
        "mcu_resets": int(m["mcu_resets"]),
        "host_retransmissions": int(m["host_retransmissions"]),
        "crc_errors": int(m["host_rx_crc_errors"] + m["mcu_rx_crc_errors"]),
        "nav_hold_cycles": int(m.get("nav_hold_cycles", 0)),
        "nav_lateral_err_m_p95_below_5m": m.get("nav_lateral_err_m_p95_below_5m"),
        "nav_attitude_replaced": int(m.get("nav_attitude_replaced", 0)),
        "nav_att_check_deg_max": m.get("nav_att_check_deg_max"),
        "approach_off_axis_m_max_below_5m": m.get("approach_off_axis_m_max_below_5m"),
        "sim_time_s": result.sim_time_s,
        "rig_wall_s": result.wall_time_s,
    }


# Every column of a row, with its Parquet type ("in_*" columns come from dispersion.INPUTS).
OUTPUT_COLUMNS: dict[str, str] = {
    "index": "int64",
    "campaign": "string",
    "campaign_seed": "int64",
    "config_id": "string",
    "code_sha": "string",  # the short hash of the code that flew it (fingerprint.py; set by the driver)
    "nav": "string",
    "rig_seed": "int64",
    "nav_seed": "int64",
    "fault": "string",
    "fault_phase": "string",
    "epoch_utc": "string",
    "beta_deg": "float64",
    "outcome": "string",
    "success": "bool",
    "failed_checks": "string",
    "abort_reason": "string",
    "error": "string",
    "final_state": "string",
    "captured": "bool",
    "capture_attempts": "int64",
    "contact_t_s": "float64",
    "contact_lateral_m": "float64",
    "contact_closing_speed_mps": "float64",
    "contact_misalignment_deg": "float64",
    "peak_force_n": "float64",
    "peak_force_soft_n": "float64",
    "fuel_lost_kg": "float64",
    "fuel_transferred_kg": "float64",
    "tv_final_kpa": "float64",
    "faults_seen": "string",
    "faults_reported": "string",
    "mcu_resets": "int64",
    "host_retransmissions": "int64",
    "crc_errors": "int64",
    "nav_hold_cycles": "int64",
    "nav_lateral_err_m_p95_below_5m": "float64",
    # added after cnn_300 began (older tables read them as null): frames the navigator fused on
    # the vehicle's attitude (oibar.nav.integrity) and the check's largest disagreement (deg;
    # none with truth navigation), and the chaser's true path inside 5 m
    "nav_attitude_replaced": "int64",
    "nav_att_check_deg_max": "float64",
    "approach_off_axis_m_max_below_5m": "float64",
    "sim_time_s": "float64",
    "rig_wall_s": "float64",
    "wall_time_s": "float64",
    "cpu_time_s": "float64",
    "worker": "string",
}
# Not part of a mission's identity: they differ from one run of the same mission to the next.
VOLATILE_COLUMNS = ("rig_wall_s", "wall_time_s", "cpu_time_s", "worker")


def column_types() -> dict[str, str]:
    from oibar_hil.campaign.dispersion import INPUTS

    cols = dict(OUTPUT_COLUMNS)
    for name, idef in INPUTS.items():
        cols[f"in_{name}"] = "int64" if idef.integer else "float64"
    return cols


def complete_row(row: dict[str, Any]) -> dict[str, Any]:
    """Every column present (None where a mission has no value), typed as the table's schema."""
    out: dict[str, Any] = {}
    for col, kind in column_types().items():
        val = row.get(col)
        if val is None:
            out[col] = "" if kind == "string" else None  # a string column says "none" with ""
            continue
        if kind == "int64":
            out[col] = int(val)
        elif kind == "float64":
            out[col] = float(val)
        elif kind == "bool":
            out[col] = bool(val)
        else:
            out[col] = str(val)
    return out
