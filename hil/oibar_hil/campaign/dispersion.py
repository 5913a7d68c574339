"""The dispersion model: one TOML table of what varies from mission to mission, and the draws.

File format (hil/campaigns/default.toml is the documented example):

    inherit = "default.toml"        # optional: start from another file (relative), override below
    [campaign]  name, seed, missions, nav ("truth" | "cnn"), max_time_s (simulated, per mission)
    [mission]   oibar.nav.guidance.MissionParams, the same for every mission
    [success]   fill_tolerance_kpa: a fault-free mission must fill to target - this (true pressure)
    [faults]    probability (a mission draws one fault with it), phases (the fault matrix's
                phase keys a fault may start in), [faults.weights] (fault type -> relative weight)
    [inputs.NAME]  dist = "fixed" (value) | "uniform" (low, high) | "normal" (mean, sigma, low,
                high: truncated, redrawn until inside) | "loguniform" (low, high > 0) | "choice"
                (values, optional weights); note = "why this spread"

Every input NAME must be one of ``INPUTS`` (each is applied by mission.py at a stated place of
the rig); one absent from the file stays at its nominal value (the rig's default). The bounds
of a draw are the distribution's stated ``low``/``high`` (or its values), checked against what
the rig accepts (``InputDef.valid``).

Reproducibility: mission i of a campaign with seed s draws each input from its own stream,
``SeedSequence(s, spawn_key=(i, crc32(name)))``: the same (s, i) gives the same mission on any
machine, in any order, with any number of workers, and adding an input to the model leaves the
other inputs' draws unchanged.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import tomllib
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from oibar_hil.rig.faults import FAULT_TYPES
from oibar_hil.rig.matrix import PHASE_KEYS, expectation

NAVS = ("truth", "cnn")
DISTS = ("fixed", "uniform", "normal", "loguniform", "choice")
MAX_REDRAWS = 1000  # a truncated normal whose bounds hold almost none of its mass is a config error


class ConfigError(ValueError):
    """The campaign file is not a valid dispersion model (the message says where and why)."""


@dataclass(frozen=True)
class InputDef:
    """One input the rig can disperse: its unit, nominal value, valid range and where it lands."""

    unit: str
    nominal: float
    valid: tuple[float, float]  # what the rig accepts (inclusive)
    applies: str  # where mission.py puts it
    nav: str = "both"  # "both", or the one navigation mode in which it has an effect
    integer: bool = False


# What the rig can apply (mission.py does it); nominal = the rig's own default.
INPUTS: dict[str, InputDef] = {
    # initial relative pose and rates (StartCondition, frame D: +z out of the drogue)
    "start_range_m": InputDef("m", 10.0, (0.6, 12.0), "StartCondition.range_m"),
    "start_lateral_x_m": InputDef("m", 0.3, (-1.0, 1.0), "StartCondition.lateral_m[0]"),
    "start_lateral_y_m": InputDef("m", -0.2, (-1.0, 1.0), "StartCondition.lateral_m[1]"),
    "start_lateral_speed_x_mps": InputDef("m/s", 0.0, (-0.05, 0.05), "StartCondition.lateral_speed_mps[0]"),
    "start_lateral_speed_y_mps": InputDef("m/s", 0.0, (-0.05, 0.05), "StartCondition.lateral_speed_mps[1]"),
    "start_closing_speed_mps": InputDef("m/s", 0.0, (-0.05, 0.10), "StartCondition.closing_speed_mps"),
    "start_pitch_deg": InputDef("deg", 2.0, (-10.0, 10.0), "StartCondition.misalignment_deg[0]"),
    "start_yaw_deg": InputDef("deg", -1.5, (-10.0, 10.0), "StartCondition.misalignment_deg[1]"),
    "start_roll_deg": InputDef("deg", 0.0, (-20.0, 20.0), "StartCondition.roll_deg"),
    "start_rate_x_deg_s": InputDef("deg/s", 0.0, (-1.0, 1.0), "StartCondition.rate_deg_s[0]"),
    "start_rate_y_deg_s": InputDef("deg/s", 0.0, (-1.0, 1.0), "StartCondition.rate_deg_s[1]"),
    "start_rate_z_deg_s": InputDef("deg/s", 0.0, (-1.0, 1.0), "StartCondition.rate_deg_s[2]"),
    # approach port and Sun/Earth geometry: the rendered camera's scene (cnn only)
    "approach_port": InputDef("-", 1, (1, 6), "SequenceSpec.port (+ its approach axis)", "cnn", integer=True),
    "epoch_day": InputDef("day", 0.0, (0.0, 365.0), "SequenceSpec.epoch_utc = 2024-03-20 + days", "cnn"),
    "sun_elevation_deg": InputDef("deg", 37.0, (0.0, 359.9), "SequenceSpec.sun_elevation_deg", "cnn"),
    # chaser mass properties and its GNC (VehicleParams)
    "chaser_mass_kg": InputDef("kg", 150.0, (50.0, 500.0), "VehicleParams.mass_kg"),
    "chaser_ang_accel_max_rad_s2": InputDef(
        "rad/s^2", 0.02, (0.005, 0.1), "VehicleParams.ang_accel_max_rad_s2 (torque / inertia)"
    ),
    "thrust_max_n": InputDef("N", 20.0, (5.0, 50.0), "VehicleParams.thrust_max_n"),
    "thrust_noise_mps2": InputDef("m/s^2", 4e-4, (0.0, 2e-3), "VehicleParams.accel_noise_mps2"),
    "thrust_bias_x_mps2": InputDef("m/s^2", 0.0, (-1e-3, 1e-3), "VehicleParams.accel_bias_mps2[0]"),
    "thrust_bias_y_mps2": InputDef("m/s^2", 0.0, (-1e-3, 1e-3), "VehicleParams.accel_bias_mps2[1]"),
    "thrust_bias_z_mps2": InputDef("m/s^2", 0.0, (-1e-3, 1e-3), "VehicleParams.accel_bias_mps2[2]"),
    "velocity_tau_s": InputDef("s", 1.0, (0.3, 3.0), "VehicleParams.velocity_tau_s"),
    "odometry_sigma_mps": InputDef("m/s", 0.005, (0.0, 0.03), "VehicleParams.odometry_sigma_mps", "cnn"),
    "odometry_bias_sigma_mps": InputDef("m/s", 0.002, (0.0, 0.01), "VehicleParams.odometry_bias_mps", "cnn"),
    # the camera (RigCamera: SequenceSpec noise/blur, RenderSettings.exposure)
    "camera_noise_dn": InputDef("DN", 0.0, (0.0, 10.0), "SequenceSpec.noise_sigma_dn", "cnn"),
    "camera_blur_px": InputDef("px", 0.0, (0.0, 3.0), "SequenceSpec.blur_sigma_px", "cnn"),
    "camera_exposure": InputDef("-", 1.0, (0.3, 3.0), "RigCamera(exposure=)", "cnn"),
    # the modelled navigation error of truth navigation (mission.NoisyTruthNav)
    "nav_sigma_floor_m": InputDef("m", 0.002, (0.0, 0.05), "NoisyTruthNav lateral 1-sigma floor", "truth"),
    "nav_sigma_per_m": InputDef(
        "m/m", 0.004, (0.0, 0.05), "NoisyTruthNav lateral 1-sigma per m of camera distance", "truth"
    ),
    "nav_att_sigma_deg": InputDef("deg", 0.5, (0.0, 3.0), "NoisyTruthNav attitude 1-sigma", "truth"),
    "nav_bias_x_m": InputDef("m", 0.0, (-0.05, 0.05), "NoisyTruthNav constant lateral bias x", "truth"),
    "nav_bias_y_m": InputDef("m", 0.0, (-0.05, 0.05), "NoisyTruthNav constant lateral bias y", "truth"),
    # the link
    "link_ber": InputDef("1/bit", 0.0, (0.0, 1e-3), "RigSpec.wire_ber (both directions, from the start)"),
    # the MCU's sensors as the plant makes them (MechanismParams; the firmware keeps its calibration)
    "adc_noise_counts": InputDef("counts", 0.7, (0.0, 5.0), "MechanismParams.adc_noise_counts"),
    "pressure_offset_counts": InputDef(
        "counts", 0.0, (-20.0, 20.0), "MechanismParams.press_zero_counts = 410 + offset"
    ),
    "pressure_gain_error_pct": InputDef(
        "%", 0.0, (-5.0, 5.0), "MechanismParams.press_kpa_per_count x (1 + e/100)"
    ),
    "load_cell_gain_error_pct": InputDef(
        "%", 0.0, (-10.0, 10.0), "MechanismParams.force_n_per_count x (1 + e/100)"
    ),
    "valve_stroke_s": InputDef("s", 0.05, (0.01, 0.15), "MechanismParams.valve_stroke_s"),
}

# Asked for by issue 62 but not applied: the rig has no place for them yet (docs/campaign.md).
NOT_APPLIED = {
    "link latency": "the wire moves bytes once per lockstep exchange (10-20 ms); it has no delay line",
    "target mass and inertia": "the target is the fixed docking frame D (an infinite mass)",
    "chaser inertia tensor": "only its effect on the attitude loop, the angular acceleration limit",
    "beta angle (directly)": "the TLE is fixed; the epoch sets the beta angle, which is recorded",
    "camera mount and intrinsics": "the navigator and the camera share GEOMETRY and one PinholeCamera",
    "thruster failures": "a thruster out is not modelled (thrust limit, noise and a bias are)",
}


@dataclass(frozen=True)
class Dist:
    """One input's distribution, as the TOML states it."""

    kind: str
    value: float = 0.0
    low: float = 0.0
    high: float = 0.0
    mean: float = 0.0
    sigma: float = 0.0
    values: tuple[float, ...] = ()
    weights: tuple[float, ...] = ()
    note: str = ""

    @property
    def bounds(self) -> tuple[float, float]:
        """Every draw lies within these (inclusive)."""
        if self.kind == "fixed":
            return (self.value, self.value)
        if self.kind == "choice":
            return (min(self.values), max(self.values))
        return (self.low, self.high)

    @property
    def dispersed(self) -> bool:
        lo, hi = self.bounds
        return hi > lo

    def draw(self, rng: np.random.Generator) -> float:
        if self.kind == "fixed":
            return self.value
        if self.kind == "uniform":
            return float(rng.uniform(self.low, self.high))
        if self.kind == "loguniform":
            return float(math.exp(rng.uniform(math.log(self.low), math.log(self.high))))
        if self.kind == "normal":
            if self.sigma == 0.0:
                return self.mean
            for _ in range(MAX_REDRAWS):
                x = float(rng.normal(self.mean, self.sigma))
                if self.low <= x <= self.high:
                    return x
            raise ConfigError(f"normal({self.mean}, {self.sigma}) seldom falls in [{self.low}, {self.high}]")
        p = np.asarray(self.weights, dtype=float) if self.weights else None
        return float(self.values[int(rng.choice(len(self.values), p=None if p is None else p / p.sum()))])

    def to_dict(self) -> dict[str, Any]:
        keys = {
            "fixed": ("value",),
            "uniform": ("low", "high"),
            "loguniform": ("low", "high"),
            "normal": ("mean", "sigma", "low", "high"),
            "choice": ("values", "weights"),
        }[self.kind]
        out: dict[str, Any] = {"dist": self.kind}
        for k in keys:
            v = getattr(self, k)
            out[k] = list(v) if isinstance(v, tuple) else v
        if self.note:
            out["note"] = self.note
        return out


def _num(where: str, d: dict, key: str) -> float:
    if key not in d:
        raise ConfigError(f"{where}: missing '{key}'")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ConfigError(f"{where}: '{key}' must be a finite number, got {v!r}")
    return float(v)


def parse_dist(name: str, d: Any) -> Dist:
    """A TOML [inputs.NAME] table -> Dist, checked against the rig's valid range of NAME."""
    where = f"[inputs.{name}]"
    if name not in INPUTS:
        raise ConfigError(f"{where}: unknown input; known: {', '.join(INPUTS)}")
    if not isinstance(d, dict):
        raise ConfigError(f"{where}: must be a table with 'dist'")
    kind = d.get("dist")
    if kind not in DISTS:
        raise ConfigError(f"{where}: dist must be one of {', '.join(DISTS)}, got {kind!r}")
    allowed = {
        "fixed": {"value"},
        "uniform": {"low", "high"},
        "loguniform": {"low", "high"},
        "normal": {"mean", "sigma", "low", "high"},
        "choice": {"values", "weights"},
    }[kind] | {"dist", "note"}
    extra = set(d) - allowed
    if extra:
        raise ConfigError(f"{where}: keys {sorted(extra)} do not belong to dist = {kind!r}")
    note = str(d.get("note", ""))
    if kind == "fixed":
        dist = Dist(kind, value=_num(where, d, "value"), note=note)
    elif kind == "choice":
        values = d.get("values")
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{where}: 'values' must be a non-empty list")
        vals = tuple(_num(where, {"values": v}, "values") for v in values)
        weights = tuple(_num(where, {"weights": w}, "weights") for w in d.get("weights", []))
        if weights and (len(weights) != len(vals) or min(weights) < 0 or sum(weights) <= 0):
            raise ConfigError(f"{where}: 'weights' must be one non-negative number per value, not all 0")
        dist = Dist(kind, values=vals, weights=weights, note=note)
    else:
        low, high = _num(where, d, "low"), _num(where, d, "high")
        if not low <= high:
            raise ConfigError(f"{where}: low {low} > high {high}")
        if kind == "loguniform" and low <= 0:
            raise ConfigError(f"{where}: loguniform needs low > 0")
        if kind == "normal":
            sigma = _num(where, d, "sigma")
            if sigma < 0:
                raise ConfigError(f"{where}: sigma must be >= 0")
            mean = _num(where, d, "mean")
            if not low <= mean <= high:
                raise ConfigError(f"{where}: mean {mean} outside [low, high] = [{low}, {high}]")
            dist = Dist(kind, low=low, high=high, mean=mean, sigma=sigma, note=note)
        else:
            dist = Dist(kind, low=low, high=high, note=note)
    idef = INPUTS[name]
    lo, hi = dist.bounds
    vals = dist.values if kind == "choice" else (lo, hi) if kind != "fixed" else (dist.value,)
    if lo < idef.valid[0] or hi > idef.valid[1]:
        raise ConfigError(
            f"{where}: draws may reach [{lo:g}, {hi:g}] {idef.unit}, outside what the rig accepts "
            f"[{idef.valid[0]:g}, {idef.valid[1]:g}]"
        )
    if idef.integer and (kind not in ("fixed", "choice") or any(v != int(v) for v in vals)):
        raise ConfigError(f"{where}: an integer input takes dist = 'fixed' or 'choice' with whole numbers")
    return dist


@dataclass(frozen=True)
class CampaignConfig:
    name: str
    seed: int
    missions: int
    nav: str
    max_time_s: float
    mission: dict[str, Any]
    fill_tolerance_kpa: float
    fault_probability: float
    fault_phases: tuple[str, ...]
    fault_weights: dict[str, float]
    inputs: dict[str, Dist]
    source: str = ""

    def value_of(self, name: str, draws: dict[str, float]) -> float:
        """A drawn value, or the nominal one of an input the model does not disperse."""
        return draws[name] if name in draws else float(INPUTS[name].nominal)

    def to_dict(self) -> dict[str, Any]:
        return {
            "campaign": {
                "name": self.name,
                "seed": self.seed,
                "missions": self.missions,
                "nav": self.nav,
                "max_time_s": self.max_time_s,
            },
            "mission": dict(self.mission),
            "success": {"fill_tolerance_kpa": self.fill_tolerance_kpa},
            "faults": {
                "probability": self.fault_probability,
                "phases": list(self.fault_phases),
                "weights": dict(self.fault_weights),
            },
            "inputs": {k: v.to_dict() for k, v in self.inputs.items()},
            "source": self.source,
        }

    def identity(self) -> str:
        """What makes two campaigns the same missions: everything but the name, the count and
        the source file's path (a longer run of the same campaign extends it)."""
        d = self.to_dict()
        d["campaign"] = {k: v for k, v in d["campaign"].items() if k not in ("name", "missions")}
        d.pop("source")
        for spec in d["inputs"].values():
            spec.pop("note", None)
        text = json.dumps(d, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict) and k != "inputs":
            out[k] = _merge(out[k], v)
        elif k == "inputs" and isinstance(v, dict):
            merged = dict(out.get("inputs", {}))
            merged.update(v)  # an input's table replaces the base's whole (its dist may change)
            out[k] = merged
        else:
            out[k] = copy.deepcopy(v)
    return out


def read_toml(path: Path, _seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The file's tables, with ``inherit`` resolved (relative to the file)."""
    path = Path(path).resolve()
    if path in _seen:
        raise ConfigError(f"{path}: 'inherit' loops back to itself")
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"campaign file {path} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    base = data.pop("inherit", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise ConfigError(f"{path}: 'inherit' must be a file name")
    return _merge(read_toml(path.parent / base, (*_seen, path)), data)


def parse_config(data: dict[str, Any], source: str = "") -> CampaignConfig:
    """Validated tables -> CampaignConfig; ConfigError says what is wrong and where."""
    known = {"campaign", "mission", "success", "faults", "inputs", "source"}
    if set(data) - known:
        raise ConfigError(f"unknown tables {sorted(set(data) - known)}; known: {sorted(known - {'source'})}")
    c = data.get("campaign", {})
    extra = set(c) - {"name", "seed", "missions", "nav", "max_time_s"}
    if extra:
        raise ConfigError(f"[campaign]: unknown keys {sorted(extra)}")
    name = str(c.get("name", "campaign"))
    if not name or any(ch in name for ch in "/\\ ") or name.startswith("."):
        raise ConfigError(f"[campaign] name {name!r}: a folder name without spaces or slashes")
    seed = c.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"[campaign] seed must be a non-negative integer, got {seed!r}")
    missions = c.get("missions", 100)
    if isinstance(missions, bool) or not isinstance(missions, int) or missions < 1:
        raise ConfigError(f"[campaign] missions must be a positive integer, got {missions!r}")
    nav = c.get("nav", "truth")
    if nav not in NAVS:
        raise ConfigError(f"[campaign] nav must be one of {NAVS}, got {nav!r}")
    max_time_s = _num("[campaign]", {"max_time_s": c.get("max_time_s", 600.0)}, "max_time_s")
    if max_time_s <= 0:
        raise ConfigError("[campaign] max_time_s must be > 0")
    mission = dict(data.get("mission", {}))
    from oibar.nav.guidance import MissionParams

    try:
        MissionParams(**mission)
    except TypeError as exc:
        raise ConfigError(f"[mission]: {exc} (fields of oibar.nav.guidance.MissionParams)") from None
    s = data.get("success", {})
    if set(s) - {"fill_tolerance_kpa"}:
        raise ConfigError(f"[success]: unknown keys {sorted(set(s) - {'fill_tolerance_kpa'})}")
    tol = _num("[success]", {"fill_tolerance_kpa": s.get("fill_tolerance_kpa", 10.0)}, "fill_tolerance_kpa")
    f = data.get("faults", {})
    if set(f) - {"probability", "phases", "weights"}:
        raise ConfigError(f"[faults]: unknown keys {sorted(set(f) - {'probability', 'phases', 'weights'})}")
    prob = _num("[faults]", {"probability": f.get("probability", 0.0)}, "probability")
    if not 0.0 <= prob <= 1.0:
        raise ConfigError(f"[faults] probability must be in [0, 1], got {prob}")
    phases = tuple(f.get("phases", PHASE_KEYS))
    bad = [p for p in phases if p not in PHASE_KEYS]
    if bad or not phases:
        raise ConfigError(f"[faults] phases {bad or '[]'}: give some of {', '.join(PHASE_KEYS)}")
    weights_in = f.get("weights", {t: 1.0 for t in FAULT_TYPES})
    weights: dict[str, float] = {}
    for t, w in weights_in.items():
        if t not in FAULT_TYPES:
            raise ConfigError(f"[faults.weights] unknown fault type {t!r}; known: {', '.join(FAULT_TYPES)}")
        w = _num("[faults.weights]", {t: w}, t)
        if w < 0:
            raise ConfigError(f"[faults.weights] {t}: weight must be >= 0")
        if w > 0:
            weights[t] = w
    if prob > 0 and not weights:
        raise ConfigError("[faults] probability > 0 but no fault type has a weight > 0")
    for t in weights:
        if not any(not isinstance(expectation(t, p), str) for p in phases):
            raise ConfigError(f"[faults.weights] {t}: applicable in none of the phases {phases}")
    inputs_in = data.get("inputs", {})
    if not isinstance(inputs_in, dict):
        raise ConfigError("[inputs] must be a table of tables")
    inputs = {k: parse_dist(k, v) for k, v in inputs_in.items()}
    return CampaignConfig(
        name=name,
        seed=int(seed),
        missions=int(missions),
        nav=nav,
        max_time_s=max_time_s,
        mission=mission,
        fill_tolerance_kpa=tol,
        fault_probability=prob,
        fault_phases=phases,
        fault_weights=weights,
        inputs=inputs,
        source=source or str(data.get("source", "")),
    )


def config_from_dict(d: dict[str, Any]) -> CampaignConfig:
    """The inverse of ``CampaignConfig.to_dict`` (a campaign folder's stored config)."""
    d = copy.deepcopy(d)
    inputs = {}
    for k, v in d.get("inputs", {}).items():
        v = {kk: vv for kk, vv in v.items() if not (kk == "weights" and not vv)}
        inputs[k] = v
    d["inputs"] = inputs
    return parse_config(d, d.get("source", ""))


def load_config(path: str | Path) -> CampaignConfig:
    return parse_config(read_toml(Path(path)), str(path))


# -- the draws ------------------------------------------------------------------------------


def stream_rng(seed: int, index: int, stream: str) -> np.random.Generator:
    """Mission ``index``'s own generator for one named stream (an input, the faults, the rig)."""
    key = zlib.crc32(stream.encode("utf-8"))
    return np.random.default_rng(np.random.SeedSequence(entropy=int(seed), spawn_key=(int(index), key)))


@dataclass(frozen=True)
class MissionDraw:
    index: int
    values: dict[str, float]  # every input of INPUTS: drawn, or nominal where not dispersed
    fault: str  # "" = no fault
    fault_phase: str  # "" = no fault
    rig_seed: int  # the scenario's seed: world noise, wire, mechanism sensors
    nav_seed: int  # truth navigation's modelled noise; the camera's sensor noise
    dispersed: tuple[str, ...] = field(default=())


def draw_fault(cfg: CampaignConfig, index: int) -> tuple[str, str]:
    """(fault type, phase key) for the mission, or ("", "")."""
    if cfg.fault_probability <= 0.0:
        return "", ""
    rng = stream_rng(cfg.seed, index, "fault")
    if rng.random() >= cfg.fault_probability:
        return "", ""
    types = sorted(cfg.fault_weights)
    w = np.array([cfg.fault_weights[t] for t in types], dtype=float)
    fault = types[int(rng.choice(len(types), p=w / w.sum()))]
    phases = [p for p in cfg.fault_phases if not isinstance(expectation(fault, p), str)]
    return fault, phases[int(rng.integers(len(phases)))]


def draw_mission(cfg: CampaignConfig, index: int) -> MissionDraw:
    if index < 0:
        raise ValueError(f"mission index must be >= 0, got {index}")
    values: dict[str, float] = {}
    for name, idef in INPUTS.items():
        dist = cfg.inputs.get(name)
        v = dist.draw(stream_rng(cfg.seed, index, name)) if dist is not None else float(idef.nominal)
        values[name] = float(int(round(v))) if idef.integer else float(v)
    fault, phase = draw_fault(cfg, index)
    seeds = stream_rng(cfg.seed, index, "seeds").integers(0, 2**31 - 1, size=2)
    return MissionDraw(
        index=index,
        values=values,
        fault=fault,
        fault_phase=phase,
        rig_seed=int(seeds[0]),
        nav_seed=int(seeds[1]),
        dispersed=tuple(n for n, d in cfg.inputs.items() if d.dispersed),
    )
