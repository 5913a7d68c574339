"""The navigation daemon's counters and cycle timings (NavDaemon.stats), and their summary for
the status line, the flight log's summary and ``oibar nav``'s last lines."""

from __future__ import annotations

import collections
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class DaemonStats:
    cycles: int = 0
    missed_deadlines: int = 0
    # cycle start -> end of work; capture -> setpoint sent (the newest DaemonParams.stats_window)
    cycle_ms: collections.deque[float] = field(default_factory=collections.deque)
    frame_to_command_ms: collections.deque[float] = field(default_factory=collections.deque)
    frames_used: int = 0
    camera_reopens: int = 0
    holds: int = 0
    odometry_errors: int = 0  # the vehicle's relative_velocity raised
    attitude_errors: int = 0  # the vehicle's relative_attitude raised
    attitude_replaced: int = 0  # frames fused with the vehicle's attitude (oibar.nav.integrity)
    corrupt_frames: int = 0  # frames the source could not decode: skipped

    def summary(self) -> dict[str, Any]:
        def pct(xs: collections.deque[float], q: float) -> float | None:
            return float(np.percentile(xs, q)) if xs else None

        return {
            "cycles": self.cycles,
            "missed_deadlines": self.missed_deadlines,
            "frames_used": self.frames_used,
            "camera_reopens": self.camera_reopens,
            "hold_cycles": self.holds,
            "odometry_errors": self.odometry_errors,
            "attitude_errors": self.attitude_errors,
            "attitude_replaced": self.attitude_replaced,
            "corrupt_frames": self.corrupt_frames,
            "cycle_ms_median": pct(self.cycle_ms, 50),
            "cycle_ms_p99": pct(self.cycle_ms, 99),
            "frame_to_command_ms_median": pct(self.frame_to_command_ms, 50),
            "frame_to_command_ms_p99": pct(self.frame_to_command_ms, 99),
            "frame_to_command_ms_max": max(self.frame_to_command_ms) if self.frame_to_command_ms else None,
        }
