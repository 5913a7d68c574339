"""The flight log's ``oibar.log`` messages (oibar.nav.logschema) of one cycle, built from what the
navigator, its filter and guidance returned; and the helpers that turn their values into numbers
a message or JSON takes."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from oibar.nav import logschema


def vec(x: Any, n: int | None = None) -> list[float]:
    """``x`` as a flat list of floats; empty when ``n`` is given and the size is not ``n``."""
    a = np.asarray(x, dtype=float).ravel()
    if n is not None and a.size != n:
        return []
    return [float(v) for v in a]


def jsonable(x: Any) -> Any:
    """Numbers, lists and dicts for JSON: numpy types unwrapped, NaN/inf as null."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, (float, np.floating)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    return x


def is_pb(msg: Any, full_name: str) -> bool:
    """``msg`` is a protobuf message of type ``full_name`` (a test's stand-in is not)."""
    desc = getattr(msg, "DESCRIPTOR", None)
    return (
        desc is not None and getattr(desc, "full_name", "") == full_name and hasattr(msg, "SerializeToString")
    )


def cycle_message(c: Any) -> Any:
    """``oibar.log.Cycle`` of a cycle (``c``: oibar.nav.flightlog.CycleInputs): its times, frame,
    odometry, hold reason, link, timings and the mechanism requests' verdicts."""
    step = c.step
    cyc = logschema.new(
        "Cycle",
        cycle=c.cycle,
        t_s=float(c.t_s),
        has_frame=c.image is not None,
        frame_seq=int(c.frame_seq or 0),
        frame_t_s=float(c.frame_t_s) if c.frame_t_s is not None else 0.0,
        hold_reason=str(step.hold_reason or ""),
        link_up=bool(c.link_up),
        mcu_state=c.mcu_state,
        cycle_ms=float(c.cycle_ms),
        corrupt_frames=int(c.corrupt_frames),
        camera_error=c.camera_error,
    )
    if c.odometry is not None:
        cyc.odometry.CopyFrom(odometry_message(c.odometry, step.velocity_update))
    if getattr(c, "vehicle_attitude", None) is not None:
        cyc.vehicle_attitude.CopyFrom(vehicle_attitude_message(c.vehicle_attitude, step.attitude_check))
    for name, ms in step.timings_ms.items():
        cyc.timings.add(name=str(name), ms=float(ms))
    for r in c.results:
        cyc.request_results.add(
            label=str(r.request.label),
            accepted=bool(r.accepted),
            reason=str(r.reason),
            state=str(r.state),
        )
    return cyc


def estimate_message(cycle: int, step: Any) -> Any:
    """``oibar.log.PoseEstimate`` of a cycle's step (None without an estimate)."""
    e = step.estimate
    if e is None:
        return None
    m = logschema.new(
        "PoseEstimate",
        cycle=cycle,
        frame_t_s=float(step.frame_t_s) if step.frame_t_s is not None else float(e.t_s),
        frame_seq=int(step.frame_seq or 0),
        T_cam_target_m=vec(e.T_cam_target_m),
        q_cam_target_wxyz=vec(e.q_cam_target),
        confidence=float(e.confidence),
        camera_range_m=float(e.camera_range_m),
        ortho_defect=float(e.ortho_defect),
        flags=[str(f) for f in e.flags],
        latency_ms=float(e.latency_ms),
        crops=int(e.crops),
    )
    if e.T_meas_cam_target_m is not None and e.R_meas_cam_target is not None:
        m.T_meas_cam_target_m.extend(vec(e.T_meas_cam_target_m))
        m.R_meas_cam_target.extend(vec(e.R_meas_cam_target))
    return m


def filter_message(cycle: int, t_s: float, state: Any, step: Any, initialised: bool) -> Any:
    """``oibar.log.FilterState``: the filter's ``NavState`` at the cycle's time and the verdicts
    on what was fed to it."""
    m = logschema.new("FilterState", cycle=cycle, t_s=float(t_s), initialised=bool(initialised))
    if state is not None:
        m.valid = bool(state.valid)
        for name in (
            "r_D_m",
            "v_D_mps",
            "att_rad",
            "w_rad_s",
            "pos_sigma_m",
            "vel_sigma_mps",
            "att_sigma_deg",
        ):
            getattr(m, name).extend(vec(getattr(state, name)))
        m.since_update_s = float(state.since_update_s)
        m.range_m = float(state.range_m)
        m.closing_speed_mps = float(state.closing_speed_mps)
        m.lateral_m = float(state.lateral_m)
        m.misalignment_deg = float(state.misalignment_deg)
        m.T_cam_target_m.extend(vec(state.T_cam_target_m))
        m.q_cam_target_wxyz.extend(vec(state.q_cam_target))
    upd = step.update
    if upd is not None:
        m.update_reason = str(upd.reason)
        m.accepted = bool(upd.accepted)
        m.gated = bool(upd.gated)
        m.reinitialised = bool(getattr(upd, "reinitialised", False))
        m.nis_pos = float(upd.nis_pos)
        m.nis_att = float(upd.nis_att)
    if step.velocity_update is not None:
        m.velocity_reason = str(step.velocity_update.reason)
    m.hold_reason = str(step.hold_reason or "")
    return m


def _measurement(m: Any, value: Any, vec_field: str, sigma_field: str) -> Any:
    """A vehicle's ``(t_s, vector, sigma)`` into ``m`` (an Odometry or VehicleAttitude); what is
    not one goes into ``m.malformed`` as its repr, with no vector."""
    try:
        m.t_s = float(value[0])
        getattr(m, vec_field).extend(float(v) for v in value[1])
        setattr(m, sigma_field, float(value[2]))
    except (TypeError, ValueError, IndexError):
        m.malformed = repr(value)[:80]
        del getattr(m, vec_field)[:]
    return m


def odometry_message(odometry: Any, verdict: Any) -> Any:
    m = logschema.new("Odometry", reason=str(verdict.reason) if verdict is not None else "dropped")
    return _measurement(m, odometry, "v_D_mps", "sigma_mps")


def vehicle_attitude_message(attitude: Any, check: Any) -> Any:
    """``oibar.log.VehicleAttitude``: the vehicle's attitude as fed, and the check's verdict."""
    m = _measurement(
        logschema.new("VehicleAttitude", checked=check is not None), attitude, "att_rad", "sigma_rad"
    )
    if check is not None:
        m.disagreement_deg = float(check.disagreement_deg)
        m.limit_deg = float(check.limit_deg)
        m.replaced = bool(check.replaced)
    return m


def guidance_message(cycle: int, t_s: float, out: Any) -> Any:
    """``oibar.log.GuidanceCommand``: what guidance decided (``out``: its GuidanceOutput)."""
    req = out.request
    g = logschema.new(
        "GuidanceCommand",
        cycle=cycle,
        t_s=float(t_s),
        phase=str(out.phase),
        v_sp_D_mps=vec(out.v_sp_D_mps),
        w_sp_rad_s=vec(out.w_sp_rad_s),
        nav_valid=bool(getattr(out.nav, "valid", False)),
    )
    if req is not None:
        g.request, g.request_kind = str(req.label), str(req.kind)
        g.opcode, g.target_kpa = int(req.opcode), float(req.target_kpa)
        g.param_id, g.param_value = int(req.param_id), float(req.value)
    return g
