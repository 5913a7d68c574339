"""Soak (issue 11): the short mission looped on ONE simulated-MCU process and ONE host link
session for an hour (or more) of simulated time, watching memory and deadlines.

    python -m oibar_hil.rig.soak [--sim-s 3600] [--doc docs/reliability.md] [--tracemalloc]

Each loop is the nominal short mission (hil/scenarios/nominal_short.yaml: from 1.2 m, capture,
soft and hard dock, fill 300 -> 600 kPa, unmate, separate, back off). Between missions the
rig's ``between_missions`` hook records the mission, samples memory, then turns the plant
around for the next one without touching the MCU or the link: the tanks are brought back to
their initial pressures slowly (300 kPa/s, inside the firmware's rate check: "the next target
vehicle, the supply topped up"), and a fresh world (the SV back at 1.2 m) and guidance
controller are installed. The firmware never restarts, so whatever it leaks accumulates.

Measured:
- memory: RSS of the simulated MCU (``/proc/<pid>/status``), RSS of this Python process,
  ``sys.getallocatedblocks()`` and the number of gc-tracked objects, at every mission end
  (optionally tracemalloc's traced size); growth after a warm-up, and the trend;
- deadlines: MCU resets (a missed watchdog kick resets it), host and MCU link losses
  (missed heartbeats), the lockstep contract (any broken frame or lost step pulse raises),
  valve coil time outside TRANSFERRING, fuel lost, and that every mission completed.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import os
import sys
import time
import tracemalloc
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from oibar_hil.rig.checks import capture_in_envelope
from oibar_hil.rig.runner import REPO_ROOT, Rig
from oibar_hil.rig.scenario import load_scenario
from oibar_hil.rig.world import VehicleParams, World, WorldState

BASE_SCENARIO = REPO_ROOT / "hil" / "scenarios" / "nominal_short.yaml"
DOC_PATH = REPO_ROOT / "docs" / "reliability.md"
BEGIN, END = "<!-- soak:begin -->", "<!-- soak:end -->"


def markers(nav: str) -> tuple[str, str]:
    """The page section a soak writes: one for ground truth, one for the CNN in the loop."""
    return (BEGIN, END) if nav == "truth" else (f"<!-- soak-{nav}:begin -->", f"<!-- soak-{nav}:end -->")


TURNAROUND_KPA_S = 300.0  # tank pressure change between missions (firmware rate limit 2000)
NAV_HIST_MAX_MS = 250.0
WARMUP_MISSIONS = 2  # memory growth is measured from the end of this mission on


def _malloc_trim() -> None:
    """Hand glibc's free heap pages back to the OS before reading our own RSS.

    Without it the host RSS follows the allocator's high-water mark and per-thread arenas,
    not the memory in use: on a loaded 2-core CI runner that alone read +2.2 MB over five
    missions with a flat Python heap."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: RSS stays the allocator's view
        pass


def rss_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise RuntimeError(f"no VmRSS for pid {pid}")


@dataclass
class MemSample:
    mission: int
    sim_s: float
    wall_s: float
    mcu_rss_kb: int
    host_rss_kb: int
    py_blocks: int
    gc_objects: int
    traced_kb: float | None


@dataclass
class MissionRecord:
    index: int
    start_s: float
    end_s: float
    outcome: str
    capture_ok: bool
    max_force_n: float
    max_force_soft_n: float
    tv_final_kpa: float


@dataclass
class SoakResult:
    sim_s: float
    wall_s: float
    missions: list[MissionRecord]
    memory: list[MemSample]
    totals: dict[str, Any] = field(default_factory=dict)
    checks: list[tuple[str, bool, str]] = field(default_factory=list)
    nav: str = "truth"

    @property
    def passed(self) -> bool:
        return all(ok for _, ok, _ in self.checks)

    def growth(self, key: str) -> float:
        """Growth of a memory figure from the end of the warm-up to the last sample."""
        ref = self._ref()
        return float(getattr(self.memory[-1], key) - getattr(ref, key))

    def slope_per_hour(self, key: str) -> float:
        """Least-squares trend after the warm-up, per simulated hour."""
        pts = [s for s in self.memory if s.mission >= self._ref().mission]
        if len(pts) < 3:
            return 0.0
        t = np.array([s.sim_s for s in pts]) / 3600.0
        y = np.array([getattr(s, key) for s in pts], dtype=float)
        return float(np.polyfit(t, y, 1)[0])

    def _ref(self) -> MemSample:
        after = [s for s in self.memory if s.mission >= WARMUP_MISSIONS]
        return after[0] if after else self.memory[0]


class Soak:
    def __init__(
        self,
        sim_s: float,
        *,
        mcu_path: Path | None = None,
        progress: bool = False,
        use_tracemalloc: bool = False,
        nav: str | Any = "truth",  # as Rig's: a name, or a navigation object
        nav_options: dict | None = None,
    ) -> None:
        self.nav = nav
        self.nav_options = nav_options
        self.nav_hist = np.zeros(int(NAV_HIST_MAX_MS / 0.25), dtype=np.int64)
        self.nav_max_ms = 0.0
        self.nav_over_period = 0
        self.sim_s = sim_s
        self.sc = load_scenario(BASE_SCENARIO)
        self.sc.name = "soak"
        self.sc.rig.max_time_s = sim_s + 600.0  # the last mission may finish past sim_s
        self.sc.rig.record_period_s = 0.5  # the recorder is cleared every mission anyway
        self.mcu_path = mcu_path
        self.progress = progress
        self.use_tracemalloc = use_tracemalloc
        self.missions: list[MissionRecord] = []
        self.memory: list[MemSample] = []
        self._mission_start = 0.0
        self._turning = False
        self._last_t = 0.0
        self._wall0 = 0.0

    def _nav_totals(self) -> dict[str, Any]:
        n = int(self.nav_hist.sum())
        if n == 0:
            return {}
        cdf = np.cumsum(self.nav_hist) / n
        width = NAV_HIST_MAX_MS / self.nav_hist.size

        def pct(q):
            return float((np.searchsorted(cdf, q) + 1) * width)

        return {
            "nav_cycles": n,
            "nav_ms_median": pct(0.5),
            "nav_ms_p99": pct(0.99),
            "nav_ms_max": self.nav_max_ms,
            "nav_over_100ms": self.nav_over_period,
        }

    def _sample(self, rig: Rig) -> None:
        assert rig.mcu is not None  # sampled between missions of a running rig
        gc.collect()
        _malloc_trim()
        self.memory.append(
            MemSample(
                mission=len(self.missions),
                sim_s=rig.t_s,
                wall_s=time.perf_counter() - self._wall0,
                mcu_rss_kb=rss_kb(rig.mcu.proc.pid),
                host_rss_kb=rss_kb(os.getpid()),
                py_blocks=sys.getallocatedblocks(),
                gc_objects=len(gc.get_objects()),
                traced_kb=tracemalloc.get_traced_memory()[0] / 1024 if self.use_tracemalloc else None,
            )
        )

    def _end_mission(self, rig: Rig) -> None:
        m, mech, cap = rig.metrics, rig.mech, rig.mech.capture_record
        self.missions.append(
            MissionRecord(
                index=len(self.missions),
                start_s=self._mission_start,
                end_s=rig.t_s,
                outcome=rig.controller.outcome,
                capture_ok=capture_in_envelope(cap),
                max_force_n=m["max_force_n"],
                max_force_soft_n=m["max_force_soft_n"],
                tv_final_kpa=mech.tv_true_kpa,
            )
        )
        # Navigator time per cycle into a fixed histogram (0.25 ms bins): the soak keeps no
        # per-cycle list, so its own bookkeeping cannot look like a leak.
        ms = [r["nav_ms"] for r in rig.nav_log if "nav_ms" in r]
        if ms:
            self.nav_hist += np.histogram(
                np.clip(ms, 0, NAV_HIST_MAX_MS - 1e-6), bins=self.nav_hist.size, range=(0.0, NAV_HIST_MAX_MS)
            )[0]
            self.nav_max_ms = max(self.nav_max_ms, max(ms))
            self.nav_over_period += sum(1 for x in ms if x > 100.0)
        # What a long-running host would rotate: the per-mission recorder and logs.
        for v in rig.samples.values():
            v.clear()
        for log in (rig.states, rig.requests_log, rig.events_log, rig.notes, rig.nav_log):
            log.clear()
        m["max_force_n"] = m["max_force_soft_n"] = 0.0
        mech.capture_record = None
        mech.capture_attempts.clear()
        self._sample(rig)

    def between_missions(self, rig: Rig) -> bool:
        dt = rig.t_s - self._last_t
        self._last_t = rig.t_s
        if not self._turning:
            self._turning = True
            self._end_mission(rig)
            return rig.controller.outcome == "completed" and rig.t_s < self.sim_s
        # Turnaround: tanks back to their initial pressures, slowly.
        mech, p = rig.mech, rig.mech.p
        step = TURNAROUND_KPA_S * max(dt, 0.0)
        done = True
        for name, goal in (
            ("sv_kpa", p.sv_initial_kpa),
            ("tv_kpa", p.tv_initial_kpa),
            ("line_kpa", p.line_initial_kpa),
        ):
            v = getattr(mech, name)
            setattr(mech, name, v + float(np.clip(goal - v, -step, step)))
            done &= abs(goal - getattr(mech, name)) < 1e-9
        if not done:
            return True
        # The next approach: the SV back at the start, a fresh controller (its NavUpdate
        # frame ids continue: the same host session keeps talking to the same MCU).
        st = self.sc.start
        rig.world = World(
            VehicleParams(**self.sc.vehicle),
            WorldState(
                r_D_m=np.array([st.lateral_m[0], st.lateral_m[1], st.range_m], dtype=float),
                v_D_mps=np.array([0.0, 0.0, -st.closing_speed_mps]),
                att_rad=np.radians([st.misalignment_deg[0], st.misalignment_deg[1], 0.0]),
            ),
            rig.rng,
        )
        rig.nav.reset()
        old = rig.controller
        rig.controller = rig.controller_factory()
        rig.controller._frame_id = old._frame_id
        self._turning = False
        self._mission_start = rig.t_s
        return True

    def run(self) -> SoakResult:
        if self.use_tracemalloc:
            tracemalloc.start()
        rig = Rig(
            self.sc,
            mcu_path=self.mcu_path,
            progress=self.progress,
            nav=self.nav,
            nav_options=self.nav_options,
            between_missions=self.between_missions,
        )
        self._wall0 = time.perf_counter()
        result = rig.run()
        wall = time.perf_counter() - self._wall0
        if not self._turning:  # stopped by max_time_s in the middle of a mission
            self._end_mission(rig)
        if self.use_tracemalloc:
            tracemalloc.stop()
        m = result.metrics
        soak = SoakResult(
            rig.t_s,
            wall,
            self.missions,
            self.memory,
            totals={
                "exchanges": m["exchanges"],
                "exchanges_1ms": m["exchanges_1ms"],
                "lockstep_frames": m["lockstep_frames"],
                "mcu_resets": m["mcu_resets"],
                "mcu_link_losses": m["mcu_link_losses"],
                "host_link_losses": m["host_link_losses"],
                "host_retransmissions": m["host_retransmissions"],
                "crc_errors": m["host_rx_crc_errors"] + m["mcu_rx_crc_errors"],
                "valve_violation_ms": m["valve_violation_ms"],
                "faults_seen": m["faults_seen"],
                "fuel_lost_kg": m["fuel_lost_kg"],
                "steps_total": m["steps_total"],
                "watchdog_kicks": m["watchdog_kicks"],
                **self._nav_totals(),
            },
            nav=self.nav,
        )
        soak.checks = base_checks(soak)
        return soak


def base_checks(s: SoakResult) -> list[tuple[str, bool, str]]:
    t = s.totals
    n = len(s.missions)
    done = sum(r.outcome == "completed" for r in s.missions)
    return [
        ("every mission completed", done == n and n > 0, f"{done}/{n}"),
        (
            "every capture in the envelope, force < 30 N soft / < 60 N",
            all(r.capture_ok and r.max_force_soft_n < 30.0 and r.max_force_n < 60.0 for r in s.missions),
            f"max {max((r.max_force_n for r in s.missions), default=0):.1f} N",
        ),
        ("no MCU reset (no missed watchdog kick)", t["mcu_resets"] == 0, str(t["mcu_resets"])),
        (
            "no link loss either side (no missed heartbeat)",
            t["mcu_link_losses"] == 0 and t["host_link_losses"] == 0,
            f"MCU {t['mcu_link_losses']}, host {t['host_link_losses']}",
        ),
        ("no fault raised", not t["faults_seen"], ", ".join(t["faults_seen"]) or "none"),
        ("no valve coil outside TRANSFERRING", t["valve_violation_ms"] == 0, f"{t['valve_violation_ms']} ms"),
        ("no fuel lost", t["fuel_lost_kg"] <= 1e-9, f"{t['fuel_lost_kg'] * 1000:.2f} g"),
        (
            "lockstep: every frame in order, step pulses accounted",
            True,
            f"{t['lockstep_frames']} frames, {t['steps_total']} step pulses",
        ),
    ] + (
        [
            (
                "navigator within the 100 ms period every cycle",
                t["nav_over_100ms"] == 0,
                f"max {t['nav_ms_max']:.1f} ms over {t['nav_cycles']:,} cycles",
            )
        ]
        if "nav_cycles" in t
        else []
    )


def memory_checks(
    s: SoakResult, *, mcu_kb: float, host_kb: float, py_blocks: float
) -> list[tuple[str, bool, str]]:
    g_mcu, g_host, g_blk = s.growth("mcu_rss_kb"), s.growth("host_rss_kb"), s.growth("py_blocks")
    return [
        (f"simulated MCU RSS growth after warm-up <= {mcu_kb:g} kB", g_mcu <= mcu_kb, f"{g_mcu:+.0f} kB"),
        (f"host Python RSS growth after warm-up <= {host_kb:g} kB", g_host <= host_kb, f"{g_host:+.0f} kB"),
        (
            f"Python allocated blocks growth after warm-up <= {py_blocks:g}",
            g_blk <= py_blocks,
            f"{g_blk:+.0f}",
        ),
    ]


def markdown(s: SoakResult) -> str:
    t = s.totals
    mem0 = s._ref()
    last = s.memory[-1]
    first = s.memory[0]

    def row(label: str, key: str, unit: str) -> str:
        return (
            f"| {label} | {getattr(first, key):,} | {getattr(mem0, key):,} | {getattr(last, key):,} | "
            f"{s.growth(key):+,.0f} {unit} | {s.slope_per_hour(key):+,.0f} {unit}/h |"
        )

    begin, end = markers(s.nav)
    nav_text = (
        "navigation: the CNN in the loop (rendered camera, OibarNet, filter; navigator time per cycle "
        f"median {t.get('nav_ms_median', float('nan')):.1f} ms, "
        f"p99 {t.get('nav_ms_p99', float('nan')):.1f} ms, "
        f"max {t.get('nav_ms_max', float('nan')):.1f} ms over {t.get('nav_cycles', 0):,} cycles; "
        f"{t.get('nav_over_100ms', 0)} over the 100 ms period)"
        if s.nav == "cnn"
        else "navigation: ground truth"
    )
    lines = [
        begin,
        "",
        f"**{s.sim_s / 3600:.2f} h simulated** ({s.sim_s:,.0f} s) in {s.wall_s:,.0f} s wall "
        f"({s.sim_s / s.wall_s:.0f}x real time): **{len(s.missions)} missions** back to back on one "
        f"simulated-MCU process and one host link session, {t['exchanges']:,} lockstep exchanges "
        f"({t['exchanges_1ms']:,} of 1 ms), {t['steps_total']:,} latch step pulses, "
        f"{t['watchdog_kicks']:,} watchdog kicks; {nav_text}.",
        "",
        f"Memory, sampled at every mission end (after `gc.collect()`); growth from the end of "
        f"mission {WARMUP_MISSIONS} (warm-up) to the last sample, and the least-squares trend "
        f"over the same span:",
        "",
        "| figure | first mission | after warm-up | end | growth | trend |",
        "| --- | --- | --- | --- | --- | --- |",
        row("simulated MCU RSS [kB]", "mcu_rss_kb", "kB"),
        row("host Python RSS [kB]", "host_rss_kb", "kB"),
        row("Python allocated blocks", "py_blocks", ""),
        row("gc-tracked objects", "gc_objects", ""),
    ]
    if last.traced_kb is not None:
        lines.append(
            f"| tracemalloc traced [kB] | {first.traced_kb:,.0f} | {mem0.traced_kb:,.0f} | "
            f"{last.traced_kb:,.0f} | {s.growth('traced_kb'):+,.0f} kB | "
            f"{s.slope_per_hour('traced_kb'):+,.0f} kB/h |"
        )
    lines += ["", "| check | verdict | measured |", "| --- | --- | --- |"]
    lines += [f"| {name} | {'pass' if ok else '**FAIL**'} | {meas} |" for name, ok, meas in s.checks]
    lines += [
        "",
        f"Host retransmissions: {t['host_retransmissions']}; CRC errors: {t['crc_errors']}.",
        "",
        end,
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from oibar_hil.rig.matrix import write_doc

    ap = argparse.ArgumentParser(prog="python -m oibar_hil.rig.soak", description=__doc__.splitlines()[0])
    ap.add_argument("--sim-s", type=float, default=3600.0, help="simulated seconds (default one hour)")
    ap.add_argument("--tracemalloc", action="store_true", help="also trace Python allocations (slower)")
    ap.add_argument("--doc", type=Path, default=None, help="write the figures into this page's markers")
    ap.add_argument("--max-mcu-growth-kb", type=float, default=256.0)
    ap.add_argument("--max-host-growth-kb", type=float, default=4096.0)
    ap.add_argument("--max-py-blocks-growth", type=float, default=5000.0)
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument(
        "--nav",
        choices=("truth", "cnn"),
        default="truth",
        help="navigation source (cnn: the rendered camera through the shipped model)",
    )
    ap.add_argument("--model", type=Path, default=None, help="ONNX model for --nav cnn")
    args = ap.parse_args(argv)
    s = Soak(
        args.sim_s,
        progress=not args.no_progress,
        use_tracemalloc=args.tracemalloc,
        nav=args.nav,
        nav_options={"model_path": args.model} if args.nav == "cnn" else None,
    ).run()
    s.checks += memory_checks(
        s, mcu_kb=args.max_mcu_growth_kb, host_kb=args.max_host_growth_kb, py_blocks=args.max_py_blocks_growth
    )
    text = markdown(s)
    begin, end = markers(args.nav)
    print(text.replace(begin, "").replace(end, "").strip())
    if args.doc:
        write_doc(text, args.doc, begin, end)
        print(f"\nfigures written to {args.doc}")
    json_path = REPO_ROOT / "build" / "soak" / "soak.json"
    json_path.parent.mkdir(parents=True, exist_ok=True)
    import json

    json_path.write_text(
        json.dumps(
            {
                "sim_s": s.sim_s,
                "wall_s": s.wall_s,
                "totals": s.totals,
                "checks": s.checks,
                "missions": [asdict(r) for r in s.missions],
                "memory": [asdict(r) for r in s.memory],
            },
            indent=1,
            default=str,
        )
    )
    return 0 if s.passed else 1


if __name__ == "__main__":
    sys.exit(main())
