"""What a frame's search cost: PoseEstimate.crops (the crops read through the keypoint networks
for that frame, its latency's driver) and KeypointPoseEstimator.last_crops (which stage of the
search read them, oibar.nav.pose.search.STAGES). docs/benchmarks.md's cold-frame tables are made
of these counts, so they are checked against the network's own batches here."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from oibar.nav.pose.search import COLD_CROP_BUDGET, STAGES

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "models" / "oibarnet.onnx"
GOLDEN = ROOT / "tests" / "golden" / "pose"
SEARCH_ONLY = {"steps", "turn", "zoom", "scan", "upright", "zoom_out"}  # never on a well-tracked frame


@pytest.fixture(scope="module")
def frame_3m() -> np.ndarray:
    assert json.loads((GOLDEN / "golden.json").read_text())["model"] == MODEL.name
    return np.asarray(Image.open(GOLDEN / "cold_3m.png").convert("RGB"))


def _counting_estimator(finder: bool = True):
    """The shipped estimator at the flight setting (its fixture finder closed with `finder`
    False), and the rows of every batch its keypoint networks were given (an independent count:
    onnxruntime's inputs)."""
    from oibar.nav.pose import PoseEstimator

    est = PoseEstimator(MODEL, threads=1, finder=finder)
    rows: list[int] = []
    sessions = [est.reader.session] + ([est.reader.far_session] if est.reader.far_session else [])
    for s in sessions:
        run = s.run

        def counting(names, feed, run=run):
            rows.append(len(next(iter(feed.values()))))
            return run(names, feed)

        s.run = counting
    return est, rows


@pytest.mark.parametrize("finder", [True, False])
def test_a_cold_frame_counts_every_crop_by_the_stage_that_read_it(frame_3m, finder):
    est, rows = _counting_estimator(finder)
    e = est.estimate(frame_3m, 2.0)
    assert e.crops == sum(rows) > 0
    assert sum(est.last_crops.values()) == e.crops
    assert set(est.last_crops) <= set(STAGES)
    # nothing placed a window: the finder's crop (when the file's finder is open) or else the
    # direct model's window and SEARCH_STEPS came first, and the fit found was checked upside down
    assert "placed" not in est.last_crops and "upright" in est.last_crops
    first = "found" if finder else "steps"
    assert est.last_crops[first] >= 1 and not {"found", "steps"} - {first} & set(est.last_crops)


def test_a_tracked_frame_reads_only_the_window_its_prediction_places(frame_3m):
    est, rows = _counting_estimator()
    first = est.estimate(frame_3m, 2.0)
    rows.clear()
    e = est.estimate(frame_3m, 2.1, prior=(first.R_cam_target, first.T_cam_target_m))
    assert e.crops == sum(rows) == sum(est.last_crops.values())
    assert est.last_crops.get("placed", 0) >= 1
    assert not set(est.last_crops) & SEARCH_ONLY
    assert e.crops <= 6  # the placed window and one refining window, each read at most 3 ways


def test_the_cold_budget_counts_the_steps_and_a_carried_search_skips_them():
    """A frame without the fixture (dark noise): SEARCH_STEPS, the turn stage, then the cold
    search up to the budget with the steps counted in; the next frame goes on with the cold
    search alone, again within the budget."""
    est, rows = _counting_estimator()
    noise = np.random.default_rng(3).integers(0, 60, (480, 744, 3), dtype=np.uint8)
    budgeted = ("steps", "zoom", "scan")
    e = est.estimate(noise, 1.0)
    assert "searching" in e.flags and e.crops == sum(rows)
    assert {"steps", "turn"} <= set(est.last_crops)
    assert sum(est.last_crops.get(k, 0) for k in budgeted) <= COLD_CROP_BUDGET
    e = est.estimate(noise, 1.1)
    assert "steps" not in est.last_crops and "turn" not in est.last_crops
    assert 0 < sum(est.last_crops.get(k, 0) for k in budgeted) <= COLD_CROP_BUDGET
    assert sum(est.last_crops.values()) == e.crops


def test_a_blank_frame_reads_no_crop():
    est, rows = _counting_estimator()
    e = est.estimate(np.zeros((480, 744, 3), np.uint8), 1.0)
    assert "blank_frame" in e.flags
    assert e.crops == 0 and est.last_crops == {} and rows == []
