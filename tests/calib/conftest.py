import json
import sys
import time
from pathlib import Path

import pytest

# hil/ is installed editable in .venv; make a bare `pytest tests/calib` work from a checkout too.
_HIL = Path(__file__).resolve().parents[2] / "hil"
if str(_HIL) not in sys.path:
    sys.path.insert(0, str(_HIL))


@pytest.fixture(scope="session")
def recording(tmp_path_factory, headless_gl):
    """One synthetic recording (200 rendered frames, 100 Hz mocap with 0.2 mm / 0.5 deg noise)
    shared by the end-to-end tests; rendering is most of the suite's time."""
    from oibar_hil.calib_synth import SynthConfig, write_recording

    out = tmp_path_factory.mktemp("calib_rec")
    t0 = time.monotonic()
    write_recording(out, SynthConfig())
    print(f"\nsynthetic recording rendered in {time.monotonic() - t0:.1f} s")
    return out


@pytest.fixture(scope="session")
def truth(recording):
    return json.loads((recording / "truth.json").read_text())
