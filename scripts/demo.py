#!/usr/bin/env python3
"""OIBAR demo: the nominal refuelling mission on the simulated HIL rig.

The real firmware (application + link), built for this machine as the simulated MCU, runs in
lockstep with a simulated approach and mechanism; the host talks to it over a pseudo-terminal on
simulated time. From 10 m: capture, soft dock, hard dock, fill to the target pressure, unmate,
release, separate, latch reset. Prints a summary table and the report's path.

A thin entry point: everything lives in ``oibar_hil.rig`` (``python -m oibar_hil.rig demo``).
``--peer`` (the link-only demo of earlier builds) is accepted and ignored.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
for sub in ("hil", "host"):
    if str(ROOT / sub) not in sys.path:
        sys.path.insert(0, str(ROOT / sub))

from oibar_hil.rig.cli import main  # noqa: E402


def _strip_legacy(argv: list[str]) -> list[str]:
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--peer":
            skip = True
        elif not a.startswith("--peer="):
            out.append(a)
    return out


if __name__ == "__main__":
    sys.exit(main([*_strip_legacy(sys.argv[1:]), "demo"]))
