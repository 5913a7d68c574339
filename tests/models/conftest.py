"""Fixtures for the OibarNet tests (helpers in models_helpers.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
from models_helpers import write_sequence


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """Sequences 1 (test) and 2, 3 (train/val), 48 frames each."""
    root = tmp_path_factory.mktemp("tiny_dataset")
    for n in (1, 2, 3):
        write_sequence(root / f"seq{n:02d}", 48, seed=n)
    return root


# A module's own MLflow store (the builds' tests read back what their stages logged)
@pytest.fixture(scope="module")
def tracking(tmp_path_factory):
    store = f"sqlite:///{tmp_path_factory.mktemp('mlflow') / 'mlflow.db'}"
    mp = pytest.MonkeyPatch()
    mp.setenv("MLFLOW_TRACKING_URI", store)
    mp.setenv("OIBAR_TRACKING", "1")
    yield store
    mp.undo()
