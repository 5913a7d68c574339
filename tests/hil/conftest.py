import sys
from pathlib import Path

import pytest

# The suite runs with PYTHONPATH=hil; make a bare `pytest tests/hil` work too.
_HIL = Path(__file__).resolve().parents[2] / "hil"
if str(_HIL) not in sys.path:
    sys.path.insert(0, str(_HIL))


@pytest.fixture(scope="session")
def gl_renderer(headless_gl):
    from oibar_hil.render import Renderer

    r = Renderer()
    yield r
    r.release()
