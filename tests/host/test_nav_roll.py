"""Rolled views (oibar.nav.pose: reader.window_for's upright windows, roll.UPRIGHT_TWIN and
TURN_STEPS_DEG). The shipped network was trained on unrolled views only and reads a fixture
turned by more than ~20 deg in its crop as unrolled. Rolling the camera about its boresight is
exact in the image: a frame turned about the principal point is the same scene seen by the camera
rolled by that angle, so the pose read from it must be the first pose turned with it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from oibar.geometry.rotations import rotation_angle_deg, rotvec_to_matrix
from oibar.nav.keypoints import image_roll_rad, project, window_around

ROOT = Path(__file__).resolve().parents[2]
MODEL = ROOT / "models" / "oibarnet.onnx"
GOLDEN = ROOT / "tests" / "golden" / "pose"
K = np.array([[583.3333, 0, 372.0], [0, 583.3333, 240.0], [0, 0, 1]])
RECT = np.array([[-0.25, -0.18, 0], [0.25, -0.18, 0], [0.25, 0.18, 0], [-0.25, 0.18, 0]])


def _Rz(angle_rad: float) -> np.ndarray:
    return rotvec_to_matrix(np.array([0.0, 0.0, angle_rad]))


def _rolled_frame(frame: np.ndarray, angle_deg: float) -> np.ndarray:
    """The frame the camera would see rolled by angle_deg about its boresight (+z): pixels turned
    about the principal point, from +u towards +v; what was outside the frame reads black."""
    import cv2

    if angle_deg % 360 == 180:
        return np.ascontiguousarray(frame[::-1, ::-1])  # exact: the principal point is the centre
    a = np.radians(angle_deg)
    c = np.array([K[0, 2] - 0.5, K[1, 2] - 0.5])  # OpenCV counts from pixel centres
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    M = np.hstack([rot, (c - rot @ c)[:, None]])
    h, w = frame.shape[:2]
    return cv2.warpAffine(frame, M, (w, h), flags=cv2.INTER_LINEAR, borderValue=(0, 0, 0))


def test_a_turned_window_frames_the_points_in_its_own_axes():
    """A rectangle turned by 40 deg: the window turned by -40 deg has the side of the unturned
    rectangle's window (not of its larger frame-axis box) and shows it centred and upright."""
    R, T = np.eye(3), np.array([0.1, -0.05, 4.0])
    upright = window_around(project(K, RECT, R, T), 128, 1.25)
    turned_uv = project(K, RECT, _Rz(np.radians(40)), _Rz(np.radians(40)) @ T)
    axis_box = window_around(turned_uv, 128, 1.25)
    win = window_around(turned_uv, 128, 1.25, angle_rad=np.radians(-40))
    assert win.side_px == pytest.approx(upright.side_px, rel=1e-6)
    assert axis_box.side_px > 1.2 * upright.side_px
    crop = win.to_crop(turned_uv)
    assert np.allclose(crop.mean(0), 64.0, atol=1e-6)
    top_edge = crop[1] - crop[0]  # top-left -> top-right corner: along +u, as unrolled
    assert top_edge[0] > 0 and abs(top_edge[1]) < 1e-6 * top_edge[0]


@pytest.mark.parametrize("roll_deg", [0.0, 30.0, -75.0, 150.0, 180.0])
def test_the_image_roll_is_the_camera_roll_about_its_boresight(roll_deg):
    R = rotvec_to_matrix(np.radians([2.0, -3.0, 0.0]))
    T = np.array([0.0, 0.0, 5.0])  # on the boresight: the roll shows undistorted
    got = np.degrees(image_roll_rad(K, _Rz(np.radians(roll_deg)) @ R, _Rz(np.radians(roll_deg)) @ T))
    assert abs((got - roll_deg + 180.0) % 360.0 - 180.0) < 0.5
    assert np.isnan(image_roll_rad(K, R, np.array([0.0, 0.0, -5.0])))  # behind the camera


@pytest.fixture(scope="module")
def frame_3m() -> np.ndarray:
    """Golden frame cold_3m: sequence 1's scene, the fixture 3 m ahead (tests/golden/pose)."""
    assert json.loads((GOLDEN / "golden.json").read_text())["model"] == MODEL.name
    return np.asarray(Image.open(GOLDEN / "cold_3m.png").convert("RGB"))


def _estimator(upright: bool = True):
    from oibar.nav.pose import PoseEstimator

    return PoseEstimator(MODEL, upright=upright, cold_crop_budget=None)


def _windows_read(est) -> list:
    """The windows the estimator reads through read_crop from now on (appended as read)."""
    seen: list = []
    read_crop = est.reader.read_crop

    def recording(image, win, refining=False):
        seen.append(win)
        return read_crop(image, win, refining)

    est.reader.read_crop = recording
    return seen


@pytest.fixture(scope="module")
def unrolled(frame_3m):
    e = _estimator().estimate(frame_3m, 0.0)
    assert "pnp_failed" not in e.flags and e.confidence > 0.5
    return e.R_cam_target, e.T_cam_target_m


@pytest.mark.parametrize("roll_deg", [180.0, 90.0, -60.0, 135.0])
def test_a_rolled_view_reads_the_pose_rolled_with_it(frame_3m, unrolled, roll_deg):
    """Cold (each frame alone): the frame rolled by 90-180 deg reads the unrolled frame's pose
    rolled with it, to 1 % of range and 1.5 deg. Without upright windows (the network as it reads
    any window) the same frames read 60-180 deg off: this is the test of the rule."""
    R0, T0 = unrolled
    Rz = _Rz(np.radians(roll_deg))
    frame = _rolled_frame(frame_3m, roll_deg)
    e = _estimator().estimate(frame, 0.0)
    assert np.linalg.norm(e.T_cam_target_m - Rz @ T0) < 0.01 * np.linalg.norm(T0), e.flags
    assert rotation_angle_deg(e.R_cam_target.T @ Rz @ R0) < 1.5, e.flags
    off = _estimator(upright=False).estimate(frame, 0.0)
    assert rotation_angle_deg(off.R_cam_target.T @ Rz @ R0) > 30.0


def test_a_rolled_track_keeps_its_windows_upright(frame_3m, unrolled):
    """Tracking: the next frame placed by the first answer is read in a window turned upright
    (a well-placed one: the placed pass alone), and reads the same pose."""
    R0, T0 = unrolled
    Rz = _Rz(np.radians(120.0))
    frame = _rolled_frame(frame_3m, 120.0)
    est = _estimator()
    first = est.estimate(frame, 0.0)
    seen = _windows_read(est)
    second = est.estimate(frame, 0.1, prior=(first.R_cam_target, first.T_cam_target_m))
    assert seen and all(abs(np.degrees(w.angle_rad) + 120.0) < 3.0 for w in seen)
    assert np.linalg.norm(second.T_cam_target_m - Rz @ T0) < 0.01 * np.linalg.norm(T0)
    assert rotation_angle_deg(second.R_cam_target.T @ Rz @ R0) < 1.5


def test_an_unrolled_view_reads_unturned_windows(frame_3m):
    """Below reader.UPRIGHT_FROM_DEG nothing is turned: what was measured on unrolled scenes holds."""
    est = _estimator()
    seen = _windows_read(est)
    e = est.estimate(frame_3m, 0.0)
    est.estimate(frame_3m, 0.1, prior=(e.R_cam_target, e.T_cam_target_m))
    assert seen and all(w.angle_rad == 0.0 for w in seen)


def _fit_of_a_rolled_fixture(est, roll_deg: float, any_turn: bool):
    """Fusion.fit on the exact keypoints of a fixture 3 m ahead, rolled by roll_deg, read in a
    window that is not turned to it, with the attitude head and the direct model reading it
    upright (as they read every view): (the fit, the truth R, T)."""
    from oibar.nav.keypoints import CropWindow

    R0 = rotvec_to_matrix(np.radians([2.0, -1.5, 0.0]))
    T0 = np.array([0.05, -0.03, 3.0])
    Rz = _Rz(np.radians(roll_deg))
    R, T = Rz @ R0, Rz @ T0
    uv = project(K, est.reader.points_m, R, T)
    base = window_around(uv, est.reader.out_px, 1.25)
    win = CropWindow(base.center_px, base.side_px, base.out_px, 0.0)
    est.fusion.keypoints_any_turn = any_turn
    return est.fusion.fit(uv, win, R0, R0, 3.0, est.fusion.table), R, T


@pytest.mark.parametrize("roll_deg", [90.0, 180.0, -60.0])
def test_keypoints_that_read_any_turn_fit_a_rolled_fixture_without_the_upright_prior(roll_deg):
    """oibar.keypoints_any_turn (fusion.PRIOR_MAX_TURN_DEG): where the keypoints show the fixture
    turned in its window, the fit is PnP alone and lands on the truth; with the head's and the
    direct model's upright prior (the flag off, as every file before it) the same keypoints give
    a fit pulled off the truth or none: this is the test of the rule."""
    est = _estimator()
    assert est.fusion.table and est.fusion.table.get("sigma_prior_deg") is not None
    r, R, T = _fit_of_a_rolled_fixture(est, roll_deg, any_turn=True)
    assert r.ok and r.no_prior is None  # PnP alone: nothing for a filter to compare it with
    assert rotation_angle_deg(r.R_cam_target.T @ R) < 0.05
    assert np.linalg.norm(r.T_cam_target_m - T) < 1e-3
    off, _, _ = _fit_of_a_rolled_fixture(est, roll_deg, any_turn=False)
    assert not off.ok or rotation_angle_deg(off.R_cam_target.T @ R) > 5.0


def test_keypoints_that_read_any_turn_keep_the_prior_on_an_upright_fixture():
    """Within PRIOR_MAX_TURN_DEG the flag changes nothing: the same fit, bit for bit."""
    est = _estimator()
    on, _, _ = _fit_of_a_rolled_fixture(est, 20.0, any_turn=True)
    off, _, _ = _fit_of_a_rolled_fixture(est, 20.0, any_turn=False)
    assert on.ok and off.ok and on.no_prior is not None
    assert np.array_equal(on.R_cam_target, off.R_cam_target)
    assert np.array_equal(on.T_cam_target_m, off.T_cam_target_m)


def test_a_model_that_says_keypoints_any_turn_opens_with_it_and_a_malformed_value_is_refused(tmp_path):
    import shutil

    import onnx

    from oibar.nav.pose import ModelFileError, PoseEstimator, read_metadata

    for name in [MODEL.name, read_metadata(MODEL)["first_pass"], read_metadata(MODEL)["finder"]["file"]]:
        shutil.copy(MODEL.parent / name, tmp_path / name)
    path = tmp_path / MODEL.name
    assert PoseEstimator(path, warmup_runs=0).fusion.keypoints_any_turn is False  # absent: off
    for value, ok in (("true", True), ('"yes"', False), ("1", False)):
        m = onnx.load(str(path))
        kept = [p for p in m.metadata_props if p.key != "oibar.keypoints_any_turn"]
        del m.metadata_props[:]
        m.metadata_props.extend(kept)
        p = m.metadata_props.add()
        p.key, p.value = "oibar.keypoints_any_turn", value
        onnx.save(m, str(path))
        if ok:
            assert PoseEstimator(path, warmup_runs=0).fusion.keypoints_any_turn is True
        else:
            with pytest.raises(ModelFileError, match="keypoints_any_turn must be true or false"):
                PoseEstimator(path, warmup_runs=0)


def _weak_fit_of_a_rolled_fixture(est, roll_deg: float):
    """A weak fit (reprojection far above the strong bound) of a fixture 3 m ahead rolled by
    roll_deg, in the unturned window around its keypoints: ((fit, window), the fixture's R, T)."""
    from oibar.nav.keypoints import PnpResult

    R0 = rotvec_to_matrix(np.radians([2.0, -1.5, 0.0]))
    T0 = np.array([0.05, -0.03, 3.0])
    Rz = _Rz(np.radians(roll_deg))
    R, T = Rz @ R0, Rz @ T0
    win = window_around(project(est.reader.K_frame, est.reader.points_m, R, T), est.reader.out_px, 1.25)
    return (PnpResult(True, R, T, rms_px=20.0 * win.scale), win), R, T


@pytest.mark.parametrize("roll_deg, any_turn, reads", [
    (90.0, True, 1), (180.0, True, 1), (-60.0, True, 1),
    (10.0, True, 0),   # within UPRIGHT_FROM_DEG: the window would not turn
    (90.0, False, 0),  # a file without the flag searches as before
])  # fmt: skip
def test_a_weak_fit_of_a_turned_fixture_has_its_window_turned_upright_read_once(
    monkeypatch, roll_deg, any_turn, reads
):
    """search.WindowSearch._weak_turned_pass: keypoints that read any turn fit a turned fixture in
    a window not turned to it, but weakly; the window that fit turns upright is read (as the
    refining pass reads, one crop) and a strong fit there ends the search. Once per weak fit."""
    from oibar.nav.keypoints import PnpResult
    from oibar.nav.pose.fusion import turn_in_window_deg
    from oibar.nav.pose.search_state import FitKeeper

    est = _estimator()
    est.fusion.keypoints_any_turn = any_turn
    search = est.search
    weak, R, T = _weak_fit_of_a_rolled_fixture(est, roll_deg)
    strong = PnpResult(True, R, T, rms_px=0.0)
    seen = []

    def one_pass(image, win, R_direct, f, range_m, refining=False, reading=None):
        seen.append((win, refining, range_m))
        return strong, win

    monkeypatch.setattr(search, "_one_pass", one_pass)
    keep = FitKeeper(search._weak_rank)
    assert not keep.consider(*weak) and keep.weak is not None and keep.weak[0] is weak[0]
    frame = np.zeros((480, 744, 3), np.uint8)
    read: list = []
    assert search._weak_turned_pass(frame, keep, R, None, read) == reads
    assert len(seen) == reads and search.last_crops.get("weak_turned", 0) == 0  # the stub reads no crop
    if not reads:
        assert keep.best is None
        return
    ((win, refining, range_m),) = seen
    assert refining and range_m == pytest.approx(np.linalg.norm(T))
    assert turn_in_window_deg(est.reader.K_frame, R, T, win) < 1.0  # the fixture upright in it
    assert turn_in_window_deg(est.reader.K_frame, R, T, weak[1]) > 15.0
    assert keep.best == (strong, win)
    # the same weak fit is not read again
    keep.best = None
    assert search._weak_turned_pass(frame, keep, R, None, read) == 0 and len(seen) == 1
