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
