"""Capture-envelope study: what the MCU is told at contact, with the CNN in the loop.

    python -m oibar_hil.rig.capture_study [--runs 30] [--seed0 100] [--no-odometry] [--json FILE]
    python -m oibar_hil.rig.capture_study --soak-s 2200 [--no-odometry] [--json FILE]

Independent runs: the short nominal mission (hil/scenarios/nominal_short.yaml, the soak's: from
1.2 m) with the rendered camera, the shipped model and the filter, once per seed (the seed drives
the world's actuator noise, the wire and the camera's sensor noise). ``--soak-s``: the CNN soak
itself (oibar_hil.rig.soak: missions back to back on one MCU, one session, one navigator) for
that many simulated seconds, continuing past a failed mission. Either way, for every mission:
the closing speed in the last NavUpdate before the probe reached the drogue (what the MCU records
the capture against, <= 50 mm/s) beside the true one, the MCU's answer to DOCK, the outcome and,
for a mission that did not complete, guidance's notes. ``--no-odometry`` leaves the vehicle's
own velocity measurement out of the filter (camera only, as before it was fused).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from oibar_hil.rig.checks import REQ_CAPTURE_MAX_SPEED_MPS
from oibar_hil.rig.navigation import CnnNav
from oibar_hil.rig.runner import REPO_ROOT, Rig
from oibar_hil.rig.scenario import load_scenario

SCENARIO = REPO_ROOT / "hil" / "scenarios" / "nominal_short.yaml"
ENVELOPE_MPS = REQ_CAPTURE_MAX_SPEED_MPS  # the MCU's PARAM_CAPTURE_MAX_CLOSING_SPEED_MM_S default


class RecordingNav:
    """CnnNav, recording per cycle the closing speed it reports (the NavUpdate's: guidance copies
    it) beside the truth, per world (the soak installs a fresh world every mission)."""

    name = "cnn"

    def __init__(self, **kw: Any) -> None:
        self.inner = CnnNav(**kw)
        self.cycles: list[tuple[int, float, float, float, float]] = []  # (world id, t, nav, true, range)

    @property
    def last_timings_ms(self) -> dict:
        return self.inner.last_timings_ms

    def reset(self) -> None:
        self.inner.reset()

    world_of: Any = None  # set by the rig: () -> World

    def frame(self, t_s: float, world: Any):
        return self.inner.frame(t_s, world)

    @property
    def navigator(self) -> RecordingNav:
        return self

    def step(self, t_s: float, image: Any, **kw: Any):
        """The daemon's navigator call, recorded beside the truth."""
        step = self.inner.navigator.step(t_s, image, **kw)
        world = self.world_of()
        sol = step.solution
        self.cycles.append((id(world), t_s, sol.closing_speed_mps, world.closing_speed_mps, world.range_m))
        return step

    def at_contact(self, world_id: int) -> tuple[float, float] | None:
        """(nav, true) closing speed of the last cycle before the probe tip reached the drogue."""
        rows = [c for c in self.cycles if c[0] == world_id]
        for prev, row in zip(rows, rows[1:], strict=False):
            if row[4] <= 0.0:
                return prev[2], prev[3]
        return None

    def error_before_contact(self, world_id: int, window_s: float = 10.0) -> float:
        """RMS of (nav - true) closing speed over the last window_s before contact."""
        rows = [c for c in self.cycles if c[0] == world_id]
        t_c = next((r[1] for r in rows if r[4] <= 0.0), None)
        if t_c is None:
            return float("nan")
        err = [r[2] - r[3] for r in rows if t_c - window_s <= r[1] < t_c]
        return float(np.sqrt(np.mean(np.square(err)))) if err else float("nan")

    def close(self) -> None:
        self.inner.close()


def _mission_row(nav: RecordingNav, world: Any, outcome: str, requests: list, notes: list, **extra) -> dict:
    contact = nav.at_contact(id(world))
    return {
        **extra,
        "outcome": outcome,
        "nav_closing_mps": contact[0] if contact else None,
        "true_closing_mps": contact[1] if contact else None,
        "dock": [res for _, label, res in requests if label == "CMD_DOCK"],
        "notes": [text for _, text in notes] if outcome != "completed" else [],
        "closing_err_last10s_rms_mps": nav.error_before_contact(id(world)),
    }


def run_one(
    seed: int, *, odometry: bool = True, scenario: Path = SCENARIO, mcu_path: Path | None = None
) -> dict:
    sc = load_scenario(scenario)
    sc.seed = seed
    sc.name = f"{sc.name}_s{seed}"
    if not odometry:
        sc.vehicle = {**sc.vehicle, "odometry": False}
    nav = RecordingNav(seed=seed)
    rig = Rig(sc, mcu_path=mcu_path, nav=nav)
    world = rig.world
    r = rig.run()
    return _mission_row(nav, world, r.outcome, r.requests, r.notes, seed=seed, wall_s=r.wall_time_s)


def run_soak(sim_s: float, *, odometry: bool = True) -> list[dict]:
    from oibar_hil.rig.soak import Soak

    rows: list[dict] = []

    class Recorder(Soak):
        def between_missions(self, rig: Rig) -> bool:
            if not self._turning:  # the mission just ended: read it before the soak clears it
                assert isinstance(self.nav, RecordingNav)  # set below, before run()
                notes = sorted(rig.notes + rig.controller.notes)
                rows.append(
                    _mission_row(
                        self.nav,
                        rig.world,
                        rig.controller.outcome,
                        rig.requests_log,
                        notes,
                        mission=len(rows) + 1,
                        t_s=rig.t_s,
                    )
                )
                print(_line(rows[-1]), flush=True)
                if rig.controller.outcome != "completed" and rig.t_s < self.sim_s:
                    self._end_mission(rig)  # carry on past a failed mission: we want the rate
                    self._turning = True
                    return True
            return super().between_missions(rig)

    soak = Recorder(sim_s)
    if not odometry:
        soak.sc.vehicle = {**soak.sc.vehicle, "odometry": False}
    soak.nav = RecordingNav()
    soak.run()
    return rows


def summarise(rows: list[dict]) -> dict:
    done = [row for row in rows if row["nav_closing_mps"] is not None]
    nav = np.array([row["nav_closing_mps"] for row in done])
    true = np.array([row["true_closing_mps"] for row in done])
    err = nav - true
    out = {
        "missions": len(rows),
        "completed": sum(row["outcome"] == "completed" for row in rows),
        "aborted": sum(row["outcome"] == "aborted" for row in rows),
        "true_in_envelope_at_contact": int(np.sum(true <= ENVELOPE_MPS)),
        "nav_over_envelope_at_contact": int(np.sum(nav > ENVELOPE_MPS)),
        "dock_refused": sum(any("PRECONDITION" in d for d in row["dock"]) for row in rows),
    }
    if err.size:
        out.update(
            {
                "nav_closing_err_at_contact_mm_s": {
                    "mean": 1e3 * float(np.mean(err)),
                    "rms": 1e3 * float(np.sqrt(np.mean(err**2))),
                    "max_abs": 1e3 * float(np.max(np.abs(err))),
                },
                "nav_closing_at_contact_mm_s": {
                    "min": 1e3 * float(nav.min()),
                    "median": 1e3 * float(np.median(nav)),
                    "max": 1e3 * float(nav.max()),
                },
                "true_closing_at_contact_mm_s": {
                    "min": 1e3 * float(true.min()),
                    "max": 1e3 * float(true.max()),
                },
                "closing_err_last10s_rms_mm_s_median": 1e3
                * float(np.nanmedian([row["closing_err_last10s_rms_mps"] for row in rows])),
            }
        )
    return out


def _line(row: dict) -> str:
    who = f"seed {row['seed']:4d}" if "seed" in row else f"mission {row['mission']:3d}"
    contact = (
        f"nav {row['nav_closing_mps'] * 1e3:5.1f} mm/s, true {row['true_closing_mps'] * 1e3:5.1f} mm/s"
        if row["nav_closing_mps"] is not None
        else "no contact"
    )
    text = (
        f"{who}: {row['outcome']:<9} at contact {contact}; DOCK {row['dock'] or '-'}; "
        f"last 10 s RMS {row['closing_err_last10s_rms_mps'] * 1e3:.1f} mm/s"
    )
    return "\n".join([text] + [f"      {n}" for n in row["notes"]])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m oibar_hil.rig.capture_study", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--runs", type=int, default=30)
    ap.add_argument("--seed0", type=int, default=100)
    ap.add_argument("--soak-s", type=float, default=None, help="run the CNN soak this long instead")
    ap.add_argument("--no-odometry", action="store_true", help="camera-only filter (no vehicle velocity)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    if args.soak_s is not None:
        rows = run_soak(args.soak_s, odometry=not args.no_odometry)
    else:
        rows = []
        for k in range(args.runs):
            rows.append(run_one(args.seed0 + k, odometry=not args.no_odometry))
            print(_line(rows[-1]), flush=True)
    summary = summarise(rows)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"rows": rows, "summary": summary}, indent=1, default=str))
    print(json.dumps(summary, indent=1))
    print(f"{time.perf_counter() - t0:.0f} s wall")
    return 0


if __name__ == "__main__":
    sys.exit(main())
