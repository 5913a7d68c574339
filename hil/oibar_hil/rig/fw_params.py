"""The firmware's parameter table, read from the simulated MCU itself.

Scenarios and fault injections name firmware parameters (``firmware_params: {nav_max_age_ms:
300}``); the link carries ids. The names, ids, units and bounds live in one place, the firmware's
table (firmware/app/src/params.c), and the simulated MCU built from it prints that table
(``oibar_sim_mcu --list-params``), so the rig never keeps a copy that could drift when a
parameter is added.
"""

from __future__ import annotations

import os
import subprocess
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[3]
DEFAULT_MCU = REPO_ROOT / "build" / "fw-host" / "port" / "sim" / "oibar_sim_mcu"


class FirmwareParamsError(RuntimeError):
    """The simulated MCU is missing or did not print a parameter table."""


class UnknownFirmwareParam(ValueError):
    """A name the firmware's parameter table does not have."""


@dataclass(frozen=True)
class FirmwareParam:
    id: int
    name: str
    unit: str
    default: float
    min: float
    max: float
    integer: bool


def default_mcu_path() -> Path:
    return Path(os.environ.get("OIBAR_SIM_MCU", DEFAULT_MCU))


def parse_table(text: str) -> dict[str, FirmwareParam]:
    """``--list-params``' lines (id, name, unit, default, min, max, integer; tab-separated) by name."""
    out: dict[str, FirmwareParam] = {}
    for n, line in enumerate(text.splitlines(), 1):
        f = line.split("\t")
        if len(f) != 7:
            raise FirmwareParamsError(
                f"parameter table line {n}: 7 tab-separated fields expected, got {line!r}"
            )
        try:
            p = FirmwareParam(int(f[0]), f[1], f[2], float(f[3]), float(f[4]), float(f[5]), f[6] == "1")
        except ValueError as exc:
            raise FirmwareParamsError(f"parameter table line {n}: {exc}") from exc
        if p.name in out or any(q.id == p.id for q in out.values()):
            raise FirmwareParamsError(f"parameter table line {n}: {p.name} (id {p.id}) listed twice")
        out[p.name] = p
    if not out:
        raise FirmwareParamsError("the simulated MCU printed an empty parameter table")
    return out


@lru_cache(maxsize=4)
def _table(path: str) -> dict[str, FirmwareParam]:
    if not Path(path).is_file():
        raise FirmwareParamsError(
            f"simulated MCU not built at {path} (run `make firmware-host`): the firmware's "
            "parameter names come from it"
        )
    try:
        res = subprocess.run([path, "--list-params"], capture_output=True, text=True, timeout=30, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise FirmwareParamsError(f"{path} --list-params: {exc}") from exc
    if res.returncode != 0:
        raise FirmwareParamsError(
            f"{path} --list-params exited {res.returncode}: {res.stderr.strip()[:200]} "
            "(an MCU built before the flag existed? run `make firmware-host`)"
        )
    return parse_table(res.stdout)


def firmware_params(mcu_path: str | Path | None = None) -> dict[str, FirmwareParam]:
    """The firmware's parameters by name, from the simulated MCU at `mcu_path` (default: the one
    `make firmware-host` builds, or $OIBAR_SIM_MCU). Read once per path."""
    return _table(str(Path(mcu_path) if mcu_path else default_mcu_path()))


def param_ids(names: dict[str, float] | list[str], mcu_path: str | Path | None = None) -> dict[str, int]:
    """The firmware's id of each name; a ValueError names the unknown ones and the known ones."""
    table = firmware_params(mcu_path)
    unknown = sorted(n for n in names if n not in table)
    if unknown:
        raise UnknownFirmwareParam(
            f"unknown firmware parameter(s) {unknown}; the firmware has {sorted(table)}"
        )
    return {n: table[n].id for n in names}
