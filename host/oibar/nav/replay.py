"""``oibar replay``: re-run pose estimation and the filter on a recorded cycle log.

The daemon's log (oibar.nav.cyclelog) names the frame of every cycle when it ran with
``--record-frames``. Replay feeds those frames, at their recorded times, with the vehicle's
recorded odometry, through a fresh Navigator (any model: compare two networks on the same
flight) and reports how the new estimates differ from the recorded ones. Guidance is not
re-run: its inputs (MCU telemetry, link state) were those of the flight and are in the log for
reading.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from oibar.geometry.rotations import angle_between_quats_deg
from oibar.nav.cyclelog import CycleLog, CycleLogError, read_log

if TYPE_CHECKING:
    from oibar.nav.core import Navigator


@dataclass
class ReplayResult:
    cycles: int = 0
    frames_replayed: int = 0
    frames_missing: int = 0
    holds_recorded: int = 0
    holds_replayed: int = 0
    dt_m: list[float] = field(default_factory=list)  # |t_new - t_recorded|
    dq_deg: list[float] = field(default_factory=list)
    model: str = ""

    def summary(self) -> dict[str, Any]:
        def stat(xs: list[float], f: Callable[[list[float]], Any]) -> float | None:
            return float(f(xs)) if xs else None

        return {
            "model": self.model,
            "cycles": self.cycles,
            "frames_replayed": self.frames_replayed,
            "frames_missing": self.frames_missing,
            "holds_recorded": self.holds_recorded,
            "holds_replayed": self.holds_replayed,
            "position_diff_m_mean": stat(self.dt_m, np.mean),
            "position_diff_m_max": stat(self.dt_m, np.max),
            "attitude_diff_deg_mean": stat(self.dq_deg, np.mean),
            "attitude_diff_deg_max": stat(self.dq_deg, np.max),
        }


def replay(
    log_path: str | Path,
    navigator: Navigator,
    out_path: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ReplayResult:
    from PIL import Image

    log_path = Path(log_path)
    records = list(read_log(log_path))
    cycles = [r for r in records if r.get("kind") == "cycle"]
    if not cycles:
        raise CycleLogError(f"{log_path}: no cycles recorded")
    if not any((r.get("frame") or {}).get("file") for r in cycles):
        raise CycleLogError(f"{log_path}: the log names no frames; record with `oibar nav --record-frames`")
    res = ReplayResult(model=str(getattr(navigator.estimator, "path", "")))
    out = CycleLog(out_path) if out_path else None
    try:
        for i, rec in enumerate(cycles):
            res.cycles += 1
            if rec.get("nav", {}).get("hold_reason"):
                res.holds_recorded += 1
            fr = rec.get("frame") or {}
            image = None
            if fr.get("file"):
                p = log_path.parent / fr["file"]
                try:
                    with Image.open(p) as im:
                        image = np.asarray(im.convert("RGB"))
                except OSError:
                    res.frames_missing += 1
            odo = rec.get("odometry") or {}
            odometry = (
                (odo["t_s"], np.asarray(odo["v_D_mps"], float), odo["sigma_mps"])
                if "v_D_mps" in odo
                else None
            )
            step = navigator.step(
                float(rec["t_s"]), image, frame_t_s=fr.get("t_s"), frame_seq=fr.get("seq"), odometry=odometry
            )
            if image is not None:
                res.frames_replayed += 1
            if step.hold_reason:
                res.holds_replayed += 1
            old = rec.get("estimate")
            if step.estimate is not None and old:
                res.dt_m.append(
                    float(np.linalg.norm(step.estimate.T_cam_target_m - np.asarray(old["T_cam_target_m"])))
                )
                res.dq_deg.append(angle_between_quats_deg(step.estimate.q_cam_target, old["q_cam_target"]))
            if out is not None:
                e = step.estimate
                out.write(
                    {
                        "kind": "replay",
                        "t_s": rec["t_s"],
                        "cycle": rec.get("cycle"),
                        "estimate": None
                        if e is None
                        else {
                            "T_cam_target_m": e.T_cam_target_m,
                            "q_cam_target": e.q_cam_target,
                            "confidence": e.confidence,
                        },
                        "recorded_estimate": old,
                        "hold_reason": step.hold_reason,
                        "r_D_m": step.solution.r_D_m if step.solution.valid else None,
                    }
                )
            if progress:
                progress(i + 1, len(cycles))
    finally:
        if out is not None:
            out.write({"kind": "footer", "summary": res.summary()})
            out.close()
    return res


def format_summary(res: ReplayResult) -> str:
    s = res.summary()
    lines = [
        f"model               {s['model']}",
        f"cycles              {s['cycles']}",
        f"frames replayed     {s['frames_replayed']} ({s['frames_missing']} missing)",
        f"hold cycles         recorded {s['holds_recorded']}, replayed {s['holds_replayed']}",
    ]
    if res.dt_m:
        lines += [
            f"position vs record  mean {s['position_diff_m_mean']:.4f} m, max {s['position_diff_m_max']:.4f} m",
            f"attitude vs record  mean {s['attitude_diff_deg_mean']:.3f} deg, "
            f"max {s['attitude_diff_deg_max']:.3f} deg",
        ]
    return "\n".join(lines)


def summary_json(res: ReplayResult) -> str:
    return json.dumps(res.summary(), indent=1)
