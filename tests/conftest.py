"""Fixtures shared by every suite."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# No oibar configuration file for the whole session (oibar.config's search: --config, then
# $OIBAR_CONFIG, then ~/.config/oibar/oibar.toml and /etc/oibar/oibar.toml): a developer's own
# file must not change what a test runs. Set in the environment, so the `oibar` processes the
# tests start inherit it; a test that reads a file names it (--config) or sets its own search.
os.environ["OIBAR_CONFIG"] = "none"


@pytest.fixture(scope="session")
def headless_gl() -> None:
    """Skip where this machine cannot make a headless OpenGL context (no EGL or Mesa driver).

    Only the context is checked here, so a test that then fails to build its renderer or camera
    (an unknown scene, a bad spec) fails instead of hiding behind the skip."""
    if str(ROOT / "hil") not in sys.path:
        sys.path.insert(0, str(ROOT / "hil"))
    from oibar_hil.render import create_context

    try:
        create_context().release()
    except RuntimeError as exc:
        pytest.skip(f"no headless OpenGL (EGL) here: {exc}")
