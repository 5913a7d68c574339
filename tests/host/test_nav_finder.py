"""The fixture finder's place in the search (oibar.nav.pose.finder_place): one crop where it
sees the fixture, read before SEARCH_STEPS when it disagrees with the direct model's window. A
far cold frame whose direct window misses the fixture is the slow case it exists for (85-97
crops: docs/benchmarks.md); here the direct model is made to miss by 1 m at 8.5 m, as it does on
unseen far frames, and the finder is a stand-in that says what it is told."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from oibar.geometry.rotations import quat_to_matrix
from oibar.nav.keypoints import project
from oibar.nav.pose import ModelFileError, PoseEstimator
from oibar.nav.pose.finder import FinderAnswer
from oibar.nav.pose.finder_place import FINDER_MIN_SCORE

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "models" / "oibarnet.onnx"
GOLDEN = ROOT / "tests" / "golden" / "pose"
MISS_M = np.array([1.0, 0.0, 0.0])  # the direct model's error: ~1.6 window sides at 8.5 m


class StandIn:
    """A finder that answers `answer` (and counts its calls)."""

    def __init__(self, answer: FinderAnswer):
        self.answer, self.calls = answer, 0

    def find(self, image: np.ndarray) -> FinderAnswer:
        self.calls += 1
        return self.answer


@pytest.fixture(scope="module")
def far():
    """The golden 8.5 m cold frame and the box around its keypoints (from the golden pose)."""
    gold = json.loads((GOLDEN / "golden.json").read_text())
    assert gold["model"] == MODEL.name
    pose = next(p for p in gold["poses"] if p["frame"] == "cold_8m")
    img = np.asarray(Image.open(GOLDEN / "cold_8m.png").convert("RGB"))
    return img, np.array(pose["T_cam_target_m"]), quat_to_matrix(np.array(pose["q_cam_target"]))


def _estimator(miss: bool = True):
    est = PoseEstimator(MODEL, threads=1, finder=False)
    assert est.search.finder is None  # the shipped file's own finder closed: a stand-in takes its place
    if miss:
        first = est.first.estimate

        def missing(image, t_s=0.0):
            d = first(image, t_s)
            d.T_cam_target_m = d.T_cam_target_m + MISS_M
            return d

        est.first.estimate = missing
    return est


def _box(est, T, R) -> FinderAnswer:
    uv = project(est.reader.K_frame, est.reader.points_m, R, T)
    lo, hi = uv.min(0), uv.max(0)
    return FinderAnswer(tuple((lo + hi) / 2), float(np.max(hi - lo)), 0.9)


def test_a_finder_window_on_the_fixture_ends_a_far_cold_search_in_a_few_crops(far):
    img, T, R = far
    slow = _estimator()
    without = slow.estimate(img, 3.0)
    assert without.crops > 60 and {"zoom", "zoom_out"} <= set(slow.last_crops)  # the slow case
    est = _estimator()
    est.search.finder = StandIn(_box(est, T, R))
    e = est.estimate(img, 3.0)
    assert est.last_crops.get("found") == 1 and "steps" not in est.last_crops and "zoom" not in est.last_crops
    assert e.crops <= 6
    assert np.linalg.norm(e.T_cam_target_m - T) < 0.01 * np.linalg.norm(T)  # the same fixture, as well read
    assert np.linalg.norm(e.T_cam_target_m - without.T_cam_target_m) < 0.01 * np.linalg.norm(T)
    assert e.confidence > 0.5 and "searching" not in e.flags


def test_a_finder_window_on_nothing_costs_one_crop_and_changes_no_answer(far):
    img, T, R = far
    plain = _estimator()
    want = plain.estimate(img, 3.0)
    est = _estimator()
    box = _box(est, T, R)
    est.search.finder = StandIn(FinderAnswer((80.0, 400.0), box.side_px, 0.95))  # dark space
    e = est.estimate(img, 3.0)
    assert est.last_crops.get("found") == 1
    assert e.crops == want.crops + 1
    np.testing.assert_allclose(e.T_cam_target_m, want.T_cam_target_m, rtol=0, atol=1e-9)
    assert e.flags == want.flags


def test_the_finder_is_not_read_where_the_direct_window_is_or_when_unsure(far):
    img, T, R = far
    est = _estimator(miss=False)
    d = est.first.estimate(img, 3.0)
    base = est.reader.window_for(d.R_cam_target, d.T_cam_target_m, upright=False)
    # where the direct model's window is already (a tenth of its side off): SEARCH_STEPS' first crop
    near = (base.center_px[0] + 0.1 * base.side_px, base.center_px[1])
    est.search.finder = StandIn(FinderAnswer(near, base.side_px / est.reader.margin, 0.9))
    est.estimate(img, 3.0)
    assert est.search.finder.calls == 1 and "found" not in est.last_crops
    est = _estimator()
    box = _box(est, T, R)
    est.search.finder = StandIn(FinderAnswer(box.center_px, box.side_px, FINDER_MIN_SCORE * 0.9))
    e = est.estimate(img, 3.0)
    assert "found" not in est.last_crops and e.crops > 60


def test_a_tracked_frame_never_asks_the_finder(far):
    img, T, R = far
    est = _estimator(miss=False)
    est.search.finder = StandIn(FinderAnswer((80.0, 400.0), 40.0, 0.95))
    first = est.estimate(img, 3.0)
    calls = est.search.finder.calls
    est.estimate(img, 3.1, prior=(first.R_cam_target, first.T_cam_target_m))
    assert est.search.finder.calls == calls and "found" not in est.last_crops


def test_a_model_naming_a_missing_or_foreign_finder_is_refused(tmp_path):
    from oibar_models.kp_export import retag

    for f in MODEL.parent.glob("oibarnet*.onnx"):
        shutil.copy(f, tmp_path / f.name)
    with pytest.raises(ValueError, match="fixture finder 'nothing.onnx' must be a file name lying beside"):
        retag(tmp_path / MODEL.name, tmp_path / MODEL.name, {"finder": {"file": "nothing.onnx"}})
    # a file that is not a finder (the direct model) is refused when the estimator opens it
    with pytest.raises(ModelFileError, match="not a fixture finder"):
        retag(tmp_path / MODEL.name, tmp_path / MODEL.name, {"finder": {"file": "oibarnet_lite.onnx"}})
    assert (tmp_path / MODEL.name).read_bytes() == MODEL.read_bytes()  # unchanged
    assert PoseEstimator(tmp_path / MODEL.name, threads=1, warmup_runs=0).search.finder is not None
