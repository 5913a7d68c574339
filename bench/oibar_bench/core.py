"""The bench machinery: targets and gaps, statistics, the measurement registry, the run context.

A measurement is a function ``fn(ctx) -> Result`` registered with :func:`measurement`; its
rows are plain dicts whose keys are the table's columns (plus any extra raw values, which go
to the JSON output only). Every row that has a target carries ``target`` (a :class:`Target`)
and ``measured`` (the number compared with it); the writer adds the gap.
"""

from __future__ import annotations

import math
import os
import statistics
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
BUILD = ROOT / "build"

NOT_AVAILABLE = "not available yet"


# ----------------------------------------------------------------------------- targets
@dataclass(frozen=True)
class Target:
    """A requirement: ``op`` is ">=" (more is better) or "<=" (less is better)."""

    op: str
    value: float
    unit: str
    source: str = ""  # where the number comes from (issue, doc, build budget)

    def __post_init__(self) -> None:
        if self.op not in (">=", "<="):
            raise ValueError(f"target op must be '>=' or '<=', not {self.op!r}")

    def text(self) -> str:
        return f"{'≥' if self.op == '>=' else '≤'} {fmt(self.value)} {self.unit}".strip()

    def margin(self, measured: float) -> float:
        """Positive when the target is met (how much room is left), negative when missed."""
        return measured - self.value if self.op == ">=" else self.value - measured

    def met(self, measured: float) -> bool:
        return self.margin(measured) >= 0

    def gap(self, measured: float | None) -> str:
        if measured is None or (isinstance(measured, float) and math.isnan(measured)):
            return "-"
        m = self.margin(measured)
        verdict = "met" if m >= 0 else "**MISSED**"
        # A ratio reads better than a difference when the scales are far apart.
        ratio = ""
        if self.value > 0 and measured > 0:
            r = measured / self.value if self.op == ">=" else self.value / measured
            ratio = f", {fmt(r)}x"
        return f"{'+' if m >= 0 else '−'}{fmt(abs(m))} {self.unit}{ratio} ({verdict})".replace("  ", " ")

    def to_json(self) -> dict:
        return {"op": self.op, "value": self.value, "unit": self.unit, "source": self.source}


# ----------------------------------------------------------------------------- statistics
def summarize_ms(samples_ms: Iterable[float]) -> dict:
    """median, 99th percentile (linear interpolation), max and count of latency samples."""
    xs = sorted(float(x) for x in samples_ms)
    if not xs:
        raise ValueError("no samples to summarize")
    return {
        "runs": len(xs),
        "median_ms": statistics.median(xs),
        "p99_ms": percentile(xs, 99.0),
        "max_ms": xs[-1],
        "min_ms": xs[0],
        "mean_ms": statistics.fmean(xs),
    }


def percentile(sorted_xs: list[float], q: float) -> float:
    """q-th percentile of already sorted values, linear between neighbours (numpy's default)."""
    if not sorted_xs:
        raise ValueError("no samples")
    pos = (len(sorted_xs) - 1) * q / 100.0
    lo, hi = math.floor(pos), math.ceil(pos)
    return sorted_xs[lo] + (sorted_xs[hi] - sorted_xs[lo]) * (pos - lo)


def timed_runs(
    fn: Callable[[], Any], *, seconds: float, min_runs: int, max_runs: int, warmup: int = 2
) -> list[float]:
    """Call ``fn`` repeatedly; return each call's latency in ms. Stops at ``max_runs``, or once
    ``seconds`` have passed and at least ``min_runs`` calls were made (the time box)."""
    for _ in range(warmup):
        fn()
    lat_ms: list[float] = []
    t_end = time.perf_counter() + seconds
    while len(lat_ms) < max_runs and (len(lat_ms) < min_runs or time.perf_counter() < t_end):
        t0 = time.perf_counter()
        fn()
        lat_ms.append((time.perf_counter() - t0) * 1e3)
    return lat_ms


# ----------------------------------------------------------------------------- formatting
def fmt(x: Any) -> str:
    """Numbers for a table: thousands separators for integers, 3-4 significant digits."""
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return f"{x:,}"
    if isinstance(x, float):
        if math.isnan(x):
            return "-"
        if math.isinf(x):
            return "∞"
        a = abs(x)
        if a >= 1000:
            return f"{x:,.0f}"
        if a >= 100:
            return f"{x:.0f}"
        if a >= 10:
            return f"{x:.1f}"
        if a >= 1:
            return f"{x:.2f}"
        if a == 0:
            return "0"
        return f"{x:.3g}"
    return str(x)


# ----------------------------------------------------------------------------- registry
@dataclass
class Result:
    rows: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


@dataclass
class Measurement:
    key: str  # "section.name"
    title: str
    columns: list[tuple[str, str]]  # (row key, header)
    fn: Callable[[Context], Result]
    order: int

    @property
    def section(self) -> str:
        return self.key.split(".", 1)[0]


REGISTRY: list[Measurement] = []

# The page's sections, in order: id -> heading.
SECTIONS: dict[str, str] = {
    "pose": "1. Pose inference (onnxruntime CPU, single stream)",
    "nav": "2. Navigation cycle: frame to command sent",
    "hil": "3. HIL rig speed factor",
    "render": "4. Renderer and data-set throughput",
    "firmware": "5. Firmware: STM32F405 image size and step-interrupt cost",
    "link": "6. Host <-> MCU link",
}


def measurement(key: str, title: str, columns: list[tuple[str, str]]):
    """Register ``fn(ctx) -> Result`` under ``key`` ("<section>.<name>")."""
    section = key.split(".", 1)[0]
    if section not in SECTIONS:
        raise ValueError(f"measurement {key!r}: unknown section {section!r}; known: {list(SECTIONS)}")

    def deco(fn):
        if any(m.key == key for m in REGISTRY):
            raise ValueError(f"measurement {key!r} registered twice")
        REGISTRY.append(Measurement(key, title, columns, fn, len(REGISTRY)))
        return fn

    return deco


# ----------------------------------------------------------------------------- context
@dataclass
class Context:
    quick: bool
    tmp: Path  # scratch, removed after the run
    threads: int = 2  # intra-op threads for inference (the target's 2 cores)
    t_start: float = field(default_factory=time.monotonic)
    shared: dict = field(default_factory=dict)  # values one measurement leaves for another

    def progress(self, msg: str) -> None:
        el = time.monotonic() - self.t_start
        print(f"[bench {int(el) // 60:2d}m{int(el) % 60:02d}s] {msg}", flush=True)

    @property
    def build(self) -> Path:
        return BUILD

    @property
    def root(self) -> Path:
        return ROOT


def load_average() -> str:
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def python() -> str:
    return sys.executable
