"""The attitude head's crop gain (oibar.nav.error_models.HeadCropGainModel, the export's
``oibar.fusion.head_crop_gain``): the window's bearing in the crop's frame, the model's checks and
inverse, and the fusion giving the head's reading back before it is the fit's prior."""

from __future__ import annotations

import numpy as np
import pytest

from oibar.geometry.rotations import matrix_to_rotvec, rotation_angle_deg, rotvec_to_matrix
from oibar.nav.error_models import HeadCropGainModel
from oibar.nav.keypoints import (
    CropWindow,
    R_crop_cam,
    attitude_from_crop,
    attitude_in_crop_deg,
    bearing_in_crop_deg,
)
from oibar.nav.pose.model_file import ModelFileError

K = np.array([[583.3333, 0, 372.0], [0, 583.3333, 240.0], [0, 0, 1]])
POINTS = np.array([[-0.25, -0.18, 0], [0.25, -0.18, 0], [0.25, 0.18, 0], [-0.25, 0.18, 0], [0, 0, 0.18]])
R_REF = rotvec_to_matrix(np.radians([180.0, 0.0, 0.0]))  # a head's reference: the fixture faced
TABLE = {"range_edges_m": [0.0, 2.0, 100.0], "gain": [0.6, 0.8], "bearing_leak": [-0.15, -0.05]}


def test_the_bearing_is_the_turn_from_the_boresight_to_the_window_centre_in_the_crops_frame():
    centre = CropWindow((K[0, 2], K[1, 2]), 100.0, 128)
    assert np.allclose(bearing_in_crop_deg(centre, K), 0.0)
    right = CropWindow((K[0, 2] + 200.0, K[1, 2]), 100.0, 128)
    b = bearing_in_crop_deg(right, K)
    # a window to the right: a turn about the camera's y axis by atan(200 / f)
    assert b[0] == pytest.approx(0.0, abs=1e-12) and b[2] == pytest.approx(0.0, abs=1e-12)
    assert b[1] == pytest.approx(np.degrees(np.arctan(200.0 / K[0, 0])))
    # it is the crop camera's own turn: R_crop_cam maps the window's ray onto the crop's boresight
    for win in (right, CropWindow((100.0, 420.0), 80.0, 128, angle_rad=0.7)):
        ray = np.linalg.solve(K, np.array([*win.center_px, 1.0]))
        assert np.allclose(R_crop_cam(win, K) @ (ray / np.linalg.norm(ray)), [0.0, 0.0, 1.0])
        # the same turn, seen from the crop's (rolled) frame
        rv = np.radians(bearing_in_crop_deg(win, K))
        roll = rotvec_to_matrix(rv) @ R_crop_cam(win, K)  # the bearing undone in the crop: its roll alone
        assert np.allclose(matrix_to_rotvec(roll)[:2], 0.0, atol=1e-12)
        assert np.degrees(np.linalg.norm(rv)) == pytest.approx(
            np.degrees(np.arccos(ray[2] / np.linalg.norm(ray)))
        )


def test_the_model_inverts_gain_and_leak_per_range_bin():
    m = HeadCropGainModel(TABLE)
    rng = np.random.default_rng(0)
    for range_m, (g, k) in ((0.7, (0.6, -0.15)), (5.0, (0.8, -0.05)), (150.0, (0.8, -0.05))):
        true, bearing = rng.normal(0, 3, 2), rng.normal(0, 4, 2)
        head = g * true + k * bearing
        assert np.allclose(m.correct(head, bearing, range_m), true)


@pytest.mark.parametrize(
    "change, match",
    [
        ({"gain": [0.6]}, "gain must have 2 entries"),
        ({"gain": [0.3, 0.8]}, "gain must be within 0.4-2.0"),
        ({"gain": [float("nan"), 0.8]}, "gain must be within"),
        ({"bearing_leak": [0.6, 0.0]}, "bearing_leak must be within -0.5-0.5"),
        ({"range_edges_m": [0.0, 0.0, 100.0]}, "rising edges"),
    ],
)
def test_a_malformed_crop_gain_is_refused(change, match):
    with pytest.raises(ValueError, match=match):
        HeadCropGainModel({**TABLE, **change})


def _fusion(f, R_att_ref=R_REF):
    from oibar.nav.pose.fusion import Fusion

    return Fusion("m.onnx", {"fusion": f}, POINTS, K, 4.0, has_head=True, R_att_ref=R_att_ref)


def test_the_fusion_gives_the_heads_reading_back_in_its_crop_before_the_fit_leans_on_it():
    """A head that reads the crop's out-of-plane rotation at 0.6 and leaks -0.15 of the bearing
    (the model's own form): its answer off the truth by degrees, the corrected prior on it."""
    f = {"sigma_crop_px": 1.0, "sigma_prior_deg": 2.0, "attitude_prior": "head", "head_crop_gain": TABLE}
    fusion = _fusion(f)
    for centre, turn_deg in (((600.0, 120.0), [4.0, -3.0, 10.0]), ((150.0, 400.0), [-2.0, 5.0, -20.0])):
        win = CropWindow(centre, 90.0, 128, angle_rad=0.3)
        R_true = rotvec_to_matrix(np.radians(turn_deg)) @ R_REF
        true_c = attitude_in_crop_deg(win, K, R_true, R_REF)
        head_c = true_c.copy()
        head_c[:2] = 0.6 * true_c[:2] - 0.15 * bearing_in_crop_deg(win, K)[:2]
        R_head = attitude_from_crop(win, K, head_c, R_REF)
        assert rotation_angle_deg(R_head.T @ R_true) > 1.0
        assert rotation_angle_deg(fusion.head_prior(R_head, win, 1.0, f).T @ R_true) < 1e-6
        # the table's far bin is another correction; without a table the head is the prior as read
        assert rotation_angle_deg(fusion.head_prior(R_head, win, 5.0, f).T @ R_true) > 0.1
        plain = {k: v for k, v in f.items() if k != "head_crop_gain"}
        assert np.allclose(fusion.head_prior(R_head, win, 1.0, plain), R_head)


def test_a_fusion_with_a_crop_gain_it_cannot_read_is_refused():
    f = {"sigma_crop_px": 1.0, "sigma_prior_deg": 2.0, "attitude_prior": "head", "head_crop_gain": TABLE}
    with pytest.raises(ModelFileError, match="prior is not the attitude head"):
        _fusion({**f, "attitude_prior": "direct"})
    with pytest.raises(ModelFileError, match="one correction of the head, not two"):
        _fusion({**f, "head_gain": {"range_edges_m": [0.0, 100.0], "tilt_gain": [0.9]}})
    with pytest.raises(ModelFileError, match="no attitude head reference"):
        _fusion(f, R_att_ref=None)
    with pytest.raises(ModelFileError, match="head_crop_gain is malformed"):
        _fusion({**f, "head_crop_gain": {**TABLE, "gain": [0.1, 0.8]}})
