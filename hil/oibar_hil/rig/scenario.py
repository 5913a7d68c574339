"""Scenario files (YAML, hil/scenarios/): the start condition, the mission, plant and firmware
parameter overrides, the faults to inject and the expected outcome. Format: docs/hil.md."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from oibar.nav.guidance import MissionParams as MissionSpec  # the host's mission parameters
from oibar_hil.rig.faults import FaultSpec

EXPECT_KEYS = {
    "outcome",
    "final_state",
    "faults",
    "valves_closed_within_s",
    "coils_off_within_s_of_fault",
    "fuel_lost_max_kg",
    "tv_min_kpa",
    "reset_cause",
    "min_crc_errors",
    "captured",
    "max_sim_time_s",
    "max_replays_executed",
    "min_replays",
}


@dataclass
class StartCondition:
    range_m: float = 10.0
    lateral_m: tuple[float, float] = (0.3, -0.2)
    misalignment_deg: tuple[float, float] = (2.0, -1.5)  # about camera x (pitch), y (yaw)
    closing_speed_mps: float = 0.0
    # Start rates (issue 62, the dispersion campaigns): lateral drift in D (x, y), the chaser's
    # roll about the docking axis and its body rates (camera x, y, z); all zero in the scenarios
    lateral_speed_mps: tuple[float, float] = (0.0, 0.0)
    roll_deg: float = 0.0
    rate_deg_s: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass
class RigSpec:
    max_time_s: float = 900.0
    exchange_ms: int = 10  # while the mechanism or the contact is active
    coast_exchange_ms: int = 20  # free flight far from the drogue, mechanism idle
    watchdog_ms: int | None = None  # None: the firmware's own, HAL_WATCHDOG_TIMEOUT_MS (250 ms, the board's)
    # The MCU's parameter flash kept in a file next to the run's logs (SimMcu flash_image): it
    # survives a reset of the MCU like the board's sectors 1 and 2 (fault mcu_reset)
    flash_image: bool = False
    guidance_period_s: float = 0.1  # navigation/guidance at 10 Hz (SPEC section 5)
    record_period_s: float = 0.05
    # A bit-error rate on the cable from the start (issue 62: a dispersed link, not a fault); the
    # bit_errors fault overrides it while injected
    wire_ber: float = 0.0


@dataclass
class Scenario:
    name: str
    description: str = ""
    seed: int = 1
    start: StartCondition = field(default_factory=StartCondition)
    mission: MissionSpec = field(default_factory=MissionSpec)
    rig: RigSpec = field(default_factory=RigSpec)
    plant: dict[str, Any] = field(default_factory=dict)
    vehicle: dict[str, Any] = field(default_factory=dict)
    firmware_params: dict[str, float] = field(default_factory=dict)
    faults: list[FaultSpec] = field(default_factory=list)
    expect: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    def param_names(self) -> list[str]:
        """Every firmware parameter the scenario names: its overrides and its param_attack
        values. The rig checks them against the table of the MCU it flies (runner.Rig), not the
        loader: a scenario is data, and which MCU flies it is chosen at run time."""
        named = list(self.firmware_params)
        for f in self.faults:
            if f.type == "param_attack":
                named += [n for n in f.args.get("values", {}) if n not in named]
        return named

    @classmethod
    def from_dict(cls, d: dict[str, Any], path: Path | None = None) -> Scenario:
        d = dict(d)
        unknown_expect = set(d.get("expect", {})) - EXPECT_KEYS
        if unknown_expect:
            raise ValueError(f"unknown expect keys {sorted(unknown_expect)}; known: {sorted(EXPECT_KEYS)}")
        start = d.get("start", {})
        return cls(
            name=d.get("name") or (path.stem if path else "scenario"),
            description=d.get("description", ""),
            seed=int(d.get("seed", 1)),
            start=StartCondition(
                range_m=float(start.get("range_m", 10.0)),
                lateral_m=tuple(start.get("lateral_m", (0.3, -0.2))),
                misalignment_deg=tuple(start.get("misalignment_deg", (2.0, -1.5))),
                closing_speed_mps=float(start.get("closing_speed_mps", 0.0)),
                lateral_speed_mps=tuple(start.get("lateral_speed_mps", (0.0, 0.0))),
                roll_deg=float(start.get("roll_deg", 0.0)),
                rate_deg_s=tuple(start.get("rate_deg_s", (0.0, 0.0, 0.0))),
            ),
            mission=MissionSpec(**d.get("mission", {})),
            rig=RigSpec(**d.get("rig", {})),
            plant=d.get("plant", {}),
            vehicle=d.get("vehicle", {}),
            firmware_params=d.get("firmware_params", {}),
            faults=[FaultSpec.from_dict(f) for f in d.get("faults", [])],
            expect=d.get("expect", {}),
            path=path,
        )


def load_scenario(path: str | Path) -> Scenario:
    """The scenario file at `path` (its parameter names are checked by the rig that flies it)."""
    path = Path(path)
    with open(path, encoding="utf-8") as f:
        data = yaml.safe_load(f) or {}
    return Scenario.from_dict(data, path)
