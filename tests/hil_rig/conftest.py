import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
for p in (ROOT / "hil", ROOT / "host"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from oibar_hil.rig.runner import default_mcu_path  # noqa: E402


@pytest.fixture(scope="session")
def sim_mcu_path() -> Path:
    path = default_mcu_path()
    if not path.exists():
        pytest.skip(f"simulated MCU not built at {path} (run `make firmware-host`)")
    return path
