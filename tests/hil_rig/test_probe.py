"""The response probe's arithmetic (oibar_hil.rig.probe): slopes with their standard errors, and
the split of a timid answer into where the fixture is (bearing) and from where it is seen
(view). A fake camera and fake estimators stand in for the renderer and the network, so these
run without GL and say exactly what a slope means."""

from types import SimpleNamespace

import numpy as np
import pytest

from oibar.geometry.docking import camera_pose_from_docking
from oibar.geometry.rotations import matrix_to_quat, rotvec_to_matrix
from oibar.nav.pose import PoseEstimate
from oibar_hil.rig import probe as P


def test_a_slope_is_fitted_over_scenes_with_each_scenes_bias_removed():
    """Each scene is probed about its own point (the truth's mean differs) and the network has a
    bias of its own in each (here one that undoes the scene's mean): only the response counts."""
    rng = np.random.default_rng(1)
    pattern = np.array([[-1.0, 0], [1, 0], [0, -1], [0, 1], [0, 0]])
    centre = {"a": [3.0, -2.0], "b": [-4.0, 1.0], "c": [0.5, 0.5], "d": [8.0, 0.0]}
    scenes = np.repeat(list(centre), 5)
    truth = np.tile(pattern, (4, 1)) + np.array([centre[s] for s in scenes])
    est = 0.7 * np.tile(pattern, (4, 1)) + rng.normal(0, 0.01, truth.shape)  # the centres not seen
    slope, se = P.slope_fit(truth, est, scenes)
    assert slope == pytest.approx(0.7, abs=0.02)
    assert 0 < se < 0.02
    assert abs(float(np.polyfit(truth.ravel(), est.ravel(), 1)[0]) - 0.7) > 0.3  # a plain fit is fooled


def test_an_answer_that_ignores_the_offsets_has_slope_zero_and_no_variation_is_no_slope():
    truth = np.array([[-1.0, 0], [1, 0], [0, -1], [0, 1]])
    slope, _ = P.slope_fit(truth, np.zeros_like(truth), ["s"] * 4)
    assert slope == pytest.approx(0.0)
    slope, se = P.slope_fit(np.zeros((4, 2)), truth, ["s"] * 4)
    assert np.isnan(slope) and np.isnan(se)


class _Camera:
    """Renders nothing: remembers the pose it was asked for, as the rig camera labels a frame."""

    def __init__(self):
        self.last = None

    def render(self, r_D_m, att_rad):
        T, R = camera_pose_from_docking(r_D_m, att_rad)
        self.last = (T, R)
        return SimpleNamespace(image=np.zeros((4, 4, 3), np.uint8), T_cam_target_m=T, R_cam_target=R)


class _Estimator:
    """Answers the camera's truth, with the fixture's perspective (the view) read `view_gain`
    times its deviation from the on-axis, aligned view: the position (and so the bearing) exact."""

    def __init__(self, cam, view_gain=1.0):
        self.cam, self.view_gain = cam, view_gain

    def forget(self):
        pass

    def estimate(self, image, t_s):
        T, R = self.cam.last
        if self.view_gain != 1.0:
            rng = float(np.linalg.norm(T))
            T0, R0 = camera_pose_from_docking(np.array([0.0, 0.0, rng - 0.57]), np.zeros(3))
            v = -R.T @ T / rng
            v0 = -R0.T @ T0 / np.linalg.norm(T0)
            w = v0 + self.view_gain * (v - v0)
            w /= np.linalg.norm(w)
            axis = np.cross(v, w)  # the turn (fixture frame) that takes the true view to the timid one
            s = np.linalg.norm(axis)
            Q = rotvec_to_matrix(axis / s * np.arctan2(s, v @ w)) if s > 1e-12 else np.eye(3)
            R = R @ Q.T  # -R'^T T = Q v rng: seen from w, T untouched
        return PoseEstimate(T, matrix_to_quat(R), R, t_s, 1.0, 1.0, float(np.linalg.norm(T)), 0.0)


def _rows(view_gain):
    cam = _Camera()
    frames = P.probe_frames(_Estimator(cam, view_gain), [("s1", cam), ("s2", cam)], (3.0, 0.5))
    assert len(frames) == 2 * 2 * 18
    return {r["range_m"]: r for r in P.summarise(frames)}


def test_an_estimator_that_reads_the_truth_follows_everything():
    for r in _rows(1.0).values():
        for key in ("lateral_slope", "attitude_slope", "view_slope", "bearing_slope", "meas_lateral_slope"):
            assert r[key] == pytest.approx(1.0, abs=1e-6), (key, r)
        assert r["lateral_err_rms_m"] < 1e-9 and r["attitude_err_rms_deg"] < 1e-6


def test_a_timid_perspective_shows_as_the_view_slope_and_costs_the_lateral_slope_far_out():
    rows = _rows(0.6)
    for r in rows.values():
        assert r["bearing_slope"] == pytest.approx(1.0, abs=1e-3)  # the fixture is where it is
        assert r["view_slope"] == pytest.approx(0.6, abs=0.02)
    # at 3 m the lateral offset is read through the view (3.6 m lever arm to the camera), so it
    # loses most there; a turn hardly changes the view, so the attitude slope stays near 1
    assert rows[3.0]["lateral_slope"] < 0.8
    assert rows[3.0]["attitude_slope"] > 0.9


def test_scenes_are_named_or_the_whole_validation_set():
    from oibar_hil.rig.runner import REPO_ROOT

    names = [n for n, _ in P.scene_list("val", REPO_ROOT)]
    assert len(names) == 22 and names[0] == "va000"
    got = P.scene_list("va003, seq01", REPO_ROOT)
    assert [n for n, _ in got] == ["va003", "seq01"]
    assert got[0][1].endswith("models/scenes/val.json:va003")
    with pytest.raises(ValueError, match="no scene"):
        P.scene_list(" , ", REPO_ROOT)


def test_an_unknown_scene_is_a_clear_error_before_any_rendering(capsys):
    from oibar_hil.rig.runner import REPO_ROOT

    rc = P.main(["--model", str(REPO_ROOT / "models/oibarnet.onnx"), "--scenes", "va999"])
    assert rc == 2
    assert "unknown scene 'va999'" in capsys.readouterr().err
