"""Entry point:
python -m oibar_models.kp_train --config models/configs/keypoints/oibarnet_kp.yaml [section.key=value ...]

Re-running the same command resumes from runs/<name>/last.pt. Data-parallel:
torchrun --nproc_per_node N -m oibar_models.kp_train --config ...
"""

from __future__ import annotations

import argparse
import sys

from .config import ConfigError, parse_override
from .data import DatasetError
from .kp_engine import load_kp_config, train


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_models.kp_train", description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", required=True, help="YAML experiment config (models/configs/)")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("overrides", nargs="*", help="e.g. train.steps=100 data.train_root=/tmp/data")
    a = ap.parse_args(argv)
    try:
        cfg = load_kp_config(a.config, parse_override(a.overrides))
        best = train(cfg, progress=not a.no_progress)
    except (ConfigError, DatasetError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if best:
        print(f"best validation score {best.get('score', float('nan')):.4f} at step {best.get('step')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
