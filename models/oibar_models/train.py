"""Entry point: python -m oibar_models.train --config models/configs/X.yaml [section.key=value ...]

Re-running the same command resumes from runs/<name>/last.pt after an interruption.
"""

from __future__ import annotations

import argparse
import sys

from .config import ConfigError, load_config, parse_override
from .data import DatasetError
from .engine import train


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_models.train", description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", required=True, help="YAML experiment config (models/configs/)")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("overrides", nargs="*", help="e.g. train.epochs=3 data.root=/tmp/data")
    a = ap.parse_args(argv)
    try:
        cfg = load_config(a.config, parse_override(a.overrides))
        train(cfg, progress=not a.no_progress)
    except (ConfigError, DatasetError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
