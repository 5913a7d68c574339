"""The navigation cycle's latency, frame to command, on this machine (`make bench`, issue 8).

The real daemon (scheduler, camera thread, navigator with the given model, filter, guidance,
vehicle sink, flight log without frames) runs at 10 Hz on a camera that delivers frames in real time: frames
from a synthetic sequence when one is given (the pose changes, so the filter and guidance do real
work), otherwise a fixed noise frame. The MCU side is a stub that is always up and answers
instantly, so the figure is the companion computer's own time; the serial link's round trip is
measured separately (bench, link section).
"""

from __future__ import annotations

import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np

from oibar import pb
from oibar.link.core import Request


class _InstantLink:
    """Always up, IDLE, accepts everything at once: the MCU is not what is measured here."""

    def __init__(self) -> None:
        tm = pb.Telemetry()
        tm.state = pb.STATE_IDLE
        self._tm = tm
        self.navs = 0
        self._lock = threading.Lock()

    link_alive = True

    @property
    def telemetry(self) -> pb.Telemetry:
        return self._tm

    def next_event(self, timeout_s: float | None = None) -> pb.Event | None:
        return None

    def send_nav_update(self, nav: pb.NavUpdate) -> bool:
        with self._lock:
            self.navs += 1
        return True

    def heartbeat(self, *, force: bool = False) -> bool:
        return True

    def submit_command(self, opcode: int, target_pressure_kpa: float | None = None) -> Request:
        ack = pb.Ack(accepted=True, reason=pb.NACK_NONE, state=pb.STATE_IDLE)
        return Request("command", pb.Packet(), done=True, response=ack, response_kind="ack")

    def submit_param_set(self, param_id: int, value: float) -> Request:
        raise RuntimeError("not used")


def _frames(frames_dir: str | Path | None, n: int) -> list[np.ndarray]:
    from PIL import Image

    if frames_dir is not None and Path(frames_dir).is_dir():
        files = sorted(Path(frames_dir).glob("*.jpg")) + sorted(Path(frames_dir).glob("*.png"))
        if files:
            pick = np.linspace(0, len(files) - 1, min(n, len(files))).astype(int)
            return [np.asarray(Image.open(files[i]).convert("RGB")) for i in pick]
    rng = np.random.default_rng(0)
    return [rng.integers(0, 255, (480, 744, 3), dtype=np.uint8)]


def nav_cycle_latency(
    model_path: str | Path,
    cycles: int = 600,
    frames_dir: str | Path | None = None,
    threads: int = 2,
    rate_hz: float = 10.0,
) -> dict[str, Any]:
    """-> dict(median_ms, p99_ms, max_ms, cycles, missed_deadlines, cycle_ms_median, cycle_ms_p99,
    frames_used, source). Runs ``cycles / rate_hz`` seconds of wall time."""
    from oibar.camera import CallableSource
    from oibar.nav.daemon import DaemonParams, NavDaemon, load_navigator
    from oibar.nav.flightlog import FlightLog
    from oibar.nav.guidance import Guidance, MissionParams

    if frames_dir is None:
        cand = Path(__file__).resolve().parents[3] / "data" / "synthetic" / "seq01" / "frames"
        frames_dir = cand if cand.is_dir() else None
    frames = _frames(frames_dir, 300)
    k = {"i": 0}

    def render(t_s: float) -> np.ndarray:
        img = frames[k["i"] % len(frames)]
        k["i"] += 1
        return img

    nav = load_navigator(model_path, threads=threads)
    with tempfile.TemporaryDirectory() as tmp:
        log = FlightLog(Path(tmp) / "flight.mcap", frames=False)  # what `oibar nav` writes by default
        d = NavDaemon(
            nav,
            Guidance(MissionParams(nav_lost_abort_s=1e9)),
            CallableSource(render, rate_hz=rate_hz * 1.5, name="bench frames"),
            link=_InstantLink(),
            log=log,
            params=DaemonParams(rate_hz=rate_hz),
        )
        s = d.run(max_cycles=cycles)
    return {
        "median_ms": s["frame_to_command_ms_median"],
        "p99_ms": s["frame_to_command_ms_p99"],
        "max_ms": s["frame_to_command_ms_max"],
        "cycles": s["cycles"],
        "missed_deadlines": s["missed_deadlines"],
        "cycle_ms_median": s["cycle_ms_median"],
        "cycle_ms_p99": s["cycle_ms_p99"],
        "frames_used": s["frames_used"],
        "source": f"{len(frames)} frames from {frames_dir}" if frames_dir else "one random frame",
    }


if __name__ == "__main__":
    import argparse
    import json

    ap = argparse.ArgumentParser(description="navigation cycle latency, frame to command")
    ap.add_argument("model", type=Path)
    ap.add_argument("--cycles", type=int, default=100)
    a = ap.parse_args()
    print(json.dumps(nav_cycle_latency(a.model, a.cycles), indent=1))
