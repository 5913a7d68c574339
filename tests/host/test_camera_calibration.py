"""Any camera (issue 60, item 2): `oibar calibrate-camera`, the calibration files (OpenCV YAML and
ROS camera_info), the one remap to the network's canonical camera, and `oibar pose`."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from oibar.calib.io import read_intrinsics
from oibar.camera.calibrate import Board, calibrate
from oibar.camera.calibration import (
    CalibrationError,
    CameraCalibration,
    CanonicalRemap,
    canonical_camera,
    load_calibration,
    write_camera_info_yaml,
    write_opencv_yaml,
)
from oibar.cli import main
from oibar.geometry.camera import PinholeCamera
from oibar.geometry.rotations import rotation_angle_deg

GOLDEN = Path(__file__).resolve().parents[1] / "golden" / "pose"
# the other camera: 1280x800, f 900 px, k1 -0.25, k2 0.05 (OpenCV pixel convention)
OTHER = CameraCalibration(
    1280, 800, np.array([[900.0, 0, 639.5], [0, 900.0, 399.5], [0, 0, 1]]), np.array([-0.25, 0.05, 0, 0, 0])
)


def _rvec(rx_deg: float, ry_deg: float, rz_deg: float) -> np.ndarray:
    R = cv2.Rodrigues(np.radians([rx_deg, 0, 0]))[0] @ cv2.Rodrigues(np.radians([0, ry_deg, 0]))[0]
    return cv2.Rodrigues(R @ cv2.Rodrigues(np.radians([0, 0, rz_deg]))[0])[0]


def render_chessboard(
    cam: CameraCalibration, rvec: np.ndarray, tvec: np.ndarray, squares=(10, 7), square_m=0.03
) -> np.ndarray:
    """A chessboard of `squares` squares seen by `cam` (with its distortion): every square's
    outline (8 points a side, so edges bend as the lens bends them) through cv2.projectPoints,
    filled at 4x the resolution and averaged down (INTER_AREA), on a white sheet with a
    one-square margin, on a grey background."""
    ss = 4
    img = np.full((cam.height_px * ss, cam.width_px * ss), 90, np.uint8)
    t = np.linspace(0, 1, 9)[:-1]

    def poly(x0, y0, x1, y1):
        edge = [(x0 + (x1 - x0) * s, y0) for s in t] + [(x1, y0 + (y1 - y0) * s) for s in t]
        edge += [(x1 - (x1 - x0) * s, y1) for s in t] + [(x0, y1 - (y1 - y0) * s) for s in t]
        pts = np.array([(x, y, 0.0) for x, y in edge])
        uv = cv2.projectPoints(pts, rvec, tvec, cam.K, cam.dist)[0].reshape(-1, 2)
        # pixel centres on integers at both scales: u_ss = ss (u + 0.5) - 0.5; 1/16 px (shift 4)
        return np.round((ss * (uv + 0.5) - 0.5) * 16).astype(np.int32)

    sx, sy = squares
    cv2.fillPoly(
        img, [poly(-square_m, -square_m, (sx + 1) * square_m, (sy + 1) * square_m)], 245, cv2.LINE_8, 4
    )
    for i in range(sx):
        for j in range(sy):
            if (i + j) % 2 == 0:
                x0, y0 = i * square_m, j * square_m
                cv2.fillPoly(img, [poly(x0, y0, x0 + square_m, y0 + square_m)], 15, cv2.LINE_8, 4)
    return cv2.resize(img, (cam.width_px, cam.height_px), interpolation=cv2.INTER_AREA)


VIEWS = [
    ((0, 0, 0), (-0.15, -0.1, 0.55)),
    ((25, 0, 5), (-0.15, -0.1, 0.6)),
    ((-25, 0, -5), (-0.15, -0.1, 0.6)),
    ((0, 30, 0), (-0.1, -0.1, 0.6)),
    ((0, -30, 10), (-0.2, -0.1, 0.6)),
    ((15, 20, 0), (-0.35, -0.25, 0.65)),
    ((-15, -20, 0), (0.05, 0.03, 0.65)),
    ((10, -15, 0), (-0.35, 0.02, 0.6)),
    ((-10, 15, 0), (0.02, -0.25, 0.6)),
]


def _board_images(cam: CameraCalibration) -> list[tuple[str, np.ndarray]]:
    return [
        (f"view{k}", render_chessboard(cam, _rvec(*r), np.array(t, float))) for k, (r, t) in enumerate(VIEWS)
    ]


def _pixel_error(a: CameraCalibration, b: CameraCalibration) -> float:
    """The largest distance (px) between where the two cameras put the same rays, over the rays
    of the canonical camera's field of view (the part of the camera the network reads)."""
    pc = PinholeCamera()
    u, v = np.meshgrid(np.linspace(0, 744, 25), np.linspace(0, 480, 17))
    pts = np.stack([(u.ravel() - 372) / pc.fx_px, (v.ravel() - 240) / pc.fy_px, np.ones(u.size)], 1)
    pa = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), a.K, a.dist)[0].reshape(-1, 2)
    pb = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), b.K, b.dist)[0].reshape(-1, 2)
    return float(np.max(np.linalg.norm(pa - pb, axis=1)))


def test_a_rendered_chessboard_calibrates_back_to_its_camera():
    res = calibrate(_board_images(OTHER), Board((9, 6), 0.03))
    c = res.calibration
    assert len(res.views_used) == len(VIEWS) and res.rms_px < 0.2
    assert c.size_wh == (1280, 800)
    assert c.K[0, 0] == pytest.approx(900.0, rel=0.005) and c.K[1, 1] == pytest.approx(900.0, rel=0.005)
    assert c.K[0, 2] == pytest.approx(639.5, abs=2.0) and c.K[1, 2] == pytest.approx(399.5, abs=2.0)
    assert c.dist[0] == pytest.approx(-0.25, abs=0.01)
    # the same rays land within 2 px (of 900 px focal length: 0.13 deg) over the canonical view
    # (measured: 1.7 px at the corners, 0.9 px median; f 901.1 px)
    assert _pixel_error(OTHER, c) < 2.0


def test_calibrate_camera_command_writes_opencv_yaml(tmp_path, capsys):
    for name, im in _board_images(OTHER)[:5]:
        cv2.imwrite(str(tmp_path / f"{name}.png"), im)
    (tmp_path / "blank.png").write_bytes(
        cv2.imencode(".png", np.full((800, 1280), 128, np.uint8))[1].tobytes()
    )
    out, info = tmp_path / "cam.yaml", tmp_path / "cam_info.yaml"
    rc = main(
        [
            "calibrate-camera",
            str(tmp_path),
            "--chessboard",
            "9x6",
            "--square-mm",
            "30",
            "-o",
            str(out),
            "--camera-info",
            str(info),
        ]
    )
    text = capsys.readouterr()
    assert rc == 0, text.err
    assert "board found in 5 of 6 images" in text.out and "no board:" in text.out
    a, b = load_calibration(out), load_calibration(info)
    assert a.K[0, 0] == pytest.approx(900.0, rel=0.01)
    np.testing.assert_allclose(a.K, b.K, atol=1e-9)
    np.testing.assert_allclose(a.dist, b.dist, atol=1e-12)
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)  # OpenCV's own reader, OpenCV's own keys
    assert fs.getNode("camera_matrix").mat().shape == (3, 3) and fs.getNode("image_width").real() == 1280


def test_calibrate_camera_refuses_too_few_views_in_one_line(tmp_path, capsys):
    cv2.imwrite(str(tmp_path / "a.png"), np.full((100, 100), 128, np.uint8))
    rc = main(
        [
            "calibrate-camera",
            str(tmp_path / "a.png"),
            str(tmp_path / "missing.png"),
            "--chessboard",
            "9x6",
            "--square-mm",
            "30",
            "-o",
            str(tmp_path / "o.yaml"),
        ]
    )
    err = capsys.readouterr().err
    assert rc == 2 and "missing.png: cannot read the image" in err and "Traceback" not in err
    assert not (tmp_path / "o.yaml").exists()


@pytest.mark.skipif(not hasattr(cv2, "aruco"), reason="this OpenCV has no cv2.aruco")
def test_a_charuco_board_calibrates_back():
    board = Board((7, 5), 0.04, charuco=True, marker_m=0.03)
    sheet = board.charuco_board().generateImage((1600, 1200), marginSize=100)  # 200 px a square
    K = np.array([[800.0, 0, 399.5], [0, 800.0, 299.5], [0, 0, 1]])
    px_m = 0.04 / 200
    images = []
    A = np.array([[4.0, 0, 1.5], [0, 4.0, 1.5], [0, 0, 1]])  # pixel centres at 4x: u4 = 4 (u + 0.5) - 0.5
    for k, (r, t) in enumerate(VIEWS):
        R = cv2.Rodrigues(_rvec(*r))[0]
        # sheet pixel (centre convention) -> board metres (the board's corner is at the margin) -> image
        S = np.array([[px_m, 0, -100 * px_m + 0.5 * px_m], [0, px_m, -100 * px_m + 0.5 * px_m], [0, 0, 1]])
        H = A @ K @ np.column_stack([R[:, 0], R[:, 1], t]) @ S
        big = cv2.warpPerspective(sheet, H, (3200, 2400), flags=cv2.INTER_LINEAR, borderValue=90)
        images.append((f"c{k}", cv2.resize(big, (800, 600), interpolation=cv2.INTER_AREA)))
    c = calibrate(images, board).calibration
    # 24 corners a view and five free distortion terms: the principal point is the loosest
    # (measured: f 802.6 px, c (403.7, ...))
    assert c.K[0, 0] == pytest.approx(800.0, rel=0.01) and c.K[0, 2] == pytest.approx(399.5, abs=6.0)


# ------------------------------------------------------------------ calibration files
ROS_FILE = """\
image_width: 1280
image_height: 800
camera_name: other
camera_matrix:
  rows: 3
  cols: 3
  data: [900.0, 0.0, 639.5, 0.0, 900.0, 399.5, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.25, 0.05, 0.0, 0.0, 0.0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
projection_matrix:
  rows: 3
  cols: 4
  data: [900.0, 0.0, 639.5, 0.0, 0.0, 900.0, 399.5, 0.0, 0.0, 0.0, 1.0, 0.0]
"""
ROS_MESSAGE = """\
header:
  frame_id: camera
height: 800
width: 1280
distortion_model: "plumb_bob"
d: [-0.25, 0.05, 0.0, 0.0, 0.0]
k: [900.0, 0.0, 639.5, 0.0, 900.0, 399.5, 0.0, 0.0, 1.0]
"""


def test_opencv_yaml_and_ros_camera_info_load_the_same_camera(tmp_path):
    write_opencv_yaml(tmp_path / "cv.yaml", OTHER)
    write_camera_info_yaml(tmp_path / "written_info.yaml", OTHER)
    (tmp_path / "ros.yaml").write_text(ROS_FILE)
    (tmp_path / "msg.yaml").write_text(ROS_MESSAGE)
    for name in ("cv.yaml", "written_info.yaml", "ros.yaml", "msg.yaml"):
        c = load_calibration(tmp_path / name)
        assert c.size_wh == (1280, 800), name
        np.testing.assert_allclose(c.K, OTHER.K, err_msg=name)
        np.testing.assert_allclose(c.dist, OTHER.dist, err_msg=name)
        intr = read_intrinsics(tmp_path / name)  # `oibar calib --intrinsics` reads the same files
        np.testing.assert_allclose(intr.K, OTHER.K)
        np.testing.assert_allclose(intr.dist, OTHER.dist)
        assert (intr.width_px, intr.height_px) == (1280, 800)


def test_rational_and_no_distortion_load_other_models_are_refused(tmp_path):
    K = np.array([[450.0, 0, 319.5], [0, 450.0, 239.5], [0, 0, 1]])
    rational = CameraCalibration(640, 480, K, np.arange(8) * 0.01)
    write_camera_info_yaml(tmp_path / "r.yaml", rational)
    assert "rational_polynomial" in (tmp_path / "r.yaml").read_text()
    np.testing.assert_allclose(load_calibration(tmp_path / "r.yaml").dist, np.arange(8) * 0.01)
    write_opencv_yaml(tmp_path / "r_cv.yaml", rational)
    np.testing.assert_allclose(load_calibration(tmp_path / "r_cv.yaml").dist, np.arange(8) * 0.01)
    none = ROS_MESSAGE.replace('"plumb_bob"', "none").replace("d: [-0.25, 0.05, 0.0, 0.0, 0.0]", "d: []")
    (tmp_path / "n.yaml").write_text(none)
    np.testing.assert_array_equal(load_calibration(tmp_path / "n.yaml").dist, np.zeros(5))
    (tmp_path / "f.yaml").write_text(
        ROS_FILE.replace("plumb_bob", "equidistant").replace(
            "cols: 5\n  data: [-0.25, 0.05, 0.0, 0.0, 0.0]", "cols: 4\n  data: [0.1, 0.0, 0.0, 0.0]"
        )
    )
    with pytest.raises(CalibrationError, match="equidistant.*not supported"):
        load_calibration(tmp_path / "f.yaml")
    (tmp_path / "bad.yaml").write_text("image_width: 1280\nfoo: [1, 2\n")
    with pytest.raises(CalibrationError, match="bad.yaml"):
        load_calibration(tmp_path / "bad.yaml")
    (tmp_path / "nosize.yaml").write_text(ROS_MESSAGE.replace("height: 800\nwidth: 1280\n", ""))
    with pytest.raises(CalibrationError, match="image size"):
        load_calibration(tmp_path / "nosize.yaml")
    with pytest.raises(CalibrationError, match="not found"):
        load_calibration(tmp_path / "nothing.yaml")


# ------------------------------------------------------------------ the remap
def test_the_remap_puts_a_point_where_the_canonical_camera_sees_it():
    K_c, wh = canonical_camera()
    remap = CanonicalRemap(OTHER, K_c, wh)
    assert remap.uncovered_fraction == 0.0 and remap.warning() == ""
    canonical = PinholeCamera()
    rng = np.random.default_rng(3)
    for _ in range(12):
        uv_c = rng.uniform([40, 30], [704, 450])  # PIXEL_CORNER
        ray = np.array([(uv_c[0] - 372) / canonical.fx_px, (uv_c[1] - 240) / canonical.fy_px, 1.0])
        P = ray * rng.uniform(0.5, 9.0)
        uv_o = cv2.projectPoints(P[None], np.zeros(3), np.zeros(3), OTHER.K, OTHER.dist)[0].ravel()  # centres
        # a small blob at the point in the other camera's frame
        yy, xx = np.mgrid[0:800, 0:1280]
        blob = np.exp(-((xx - uv_o[0]) ** 2 + (yy - uv_o[1]) ** 2) / (2 * 1.5**2))
        frame = np.repeat((blob * 250).astype(np.uint8)[..., None], 3, axis=2)
        out = remap.apply(frame)[..., 0].astype(float)
        out[out < 20] = 0
        ys, xs = np.mgrid[0 : out.shape[0], 0 : out.shape[1]]
        found_centre = np.array([(out * xs).sum(), (out * ys).sum()]) / out.sum()
        expected_centre = canonical.project(P[None])[0] - 0.5  # PIXEL_CORNER -> array indices
        assert np.linalg.norm(found_centre - expected_centre) < 0.5, (uv_c, found_centre, expected_centre)


def test_a_narrower_camera_is_accepted_with_its_uncovered_border_reported():
    narrow = CameraCalibration(744, 480, np.array([[700.0, 0, 371.5], [0, 700.0, 239.5], [0, 0, 1]]))
    remap = CanonicalRemap(narrow, *canonical_camera())
    # it sees +-372/700 of the focal length: 372 * 583.33 / 700 = 310 px of the canonical 372
    left, top, right, bottom = remap.uncovered_border_px
    assert abs(left - 62) <= 1 and abs(right - 62) <= 1 and abs(top - 40) <= 1 and abs(bottom - 40) <= 1
    assert 0.25 < remap.uncovered_fraction < 0.35 and "covers less" in remap.warning()
    out = remap.apply(np.full((480, 744, 3), 200, np.uint8))
    assert out[:, :55].max() == 0 and out[:, -55:].max() == 0 and out[240, 372, 0] == 200


def test_a_strong_barrel_is_not_folded_back_into_the_view():
    # k1 = -0.6: r_d = r - 0.6 r^3 turns back at r = 0.745 (a corner of the canonical view is at
    # 0.759): rays beyond are not this camera's pixels, so they are uncovered, not mirrored in
    wide = CameraCalibration(
        744, 480, np.array([[583.33, 0, 371.5], [0, 583.33, 239.5], [0, 0, 1]]), [-0.6, 0, 0, 0, 0]
    )
    remap = CanonicalRemap(wide, *canonical_camera())
    assert remap.uncovered[0, 0] and remap.uncovered[-1, -1] and not remap.uncovered[240, 372]


def test_a_frame_of_another_size_is_refused():
    remap = CanonicalRemap(OTHER, *canonical_camera())
    with pytest.raises(CalibrationError, match="744x480 does not match the calibration's 1280x800"):
        remap.apply(np.zeros((480, 744, 3), np.uint8))


# ------------------------------------------------------------------ done when: another camera's frames
FRAMES = ("cold_0p7m", "cold_3m", "cold_8m", "track_5m_a")


def _native(name: str) -> np.ndarray:
    return np.asarray(Image.open(GOLDEN / f"{name}.png").convert("RGB"))


def warp_to(cam: CameraCalibration, native: np.ndarray) -> np.ndarray:
    """A canonical-camera frame as `cam` would have taken it (its resolution, focal length and
    distortion): each of cam's pixels looks up the canonical pixel of its ray; rays outside the
    canonical view are black."""
    u, v = np.meshgrid(np.arange(cam.width_px, dtype=float), np.arange(cam.height_px, dtype=float))
    uv = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    rays = cv2.undistortPointsIter(uv, cam.K, cam.dist, None, None, crit).reshape(-1, 2)
    back = cv2.projectPoints(
        np.hstack([rays, np.ones((len(rays), 1))]), np.zeros(3), np.zeros(3), cam.K, cam.dist
    )[0]
    assert np.max(np.abs(back.reshape(-1, 2) - uv.reshape(-1, 2))) < 0.01  # the inverse lens is exact
    Kc = PinholeCamera().K_centre()
    mx = (Kc[0, 0] * rays[:, 0] + Kc[0, 2]).reshape(cam.height_px, cam.width_px).astype(np.float32)
    my = (Kc[1, 1] * rays[:, 1] + Kc[1, 2]).reshape(cam.height_px, cam.width_px).astype(np.float32)
    return cv2.remap(native, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


@pytest.fixture(scope="module")
def estimator():
    from oibar.nav.pose import KeypointPoseEstimator, PoseEstimator
    from oibar.resources import default_model_path

    est = PoseEstimator(default_model_path(), threads=1)
    if isinstance(est, KeypointPoseEstimator):
        est.search.cold_crop_budget = None
    return est


def _poses(est, frames):
    out = []
    for f in frames:
        est.forget()
        e = est.estimate(f, t_s=0.0)
        out.append((float(np.linalg.norm(e.T_cam_target_m)), e.R_cam_target))
    return out


def test_frames_of_another_camera_read_with_its_file_give_the_native_poses(estimator, tmp_path):
    from oibar.nav.pose import FrameError

    write_opencv_yaml(tmp_path / "other.yaml", OTHER)
    write_camera_info_yaml(tmp_path / "other_info.yaml", OTHER)
    natives = [_native(n) for n in FRAMES]
    warped = [warp_to(OTHER, f) for f in natives]
    estimator.use_calibration(None)
    ref = _poses(estimator, natives)
    for name in ("other.yaml", "other_info.yaml"):
        remap = estimator.use_calibration(tmp_path / name)
        assert remap is not None and remap.uncovered_fraction == 0.0
        got = _poses(estimator, warped)
        dr = [abs(g[0] / r[0] - 1.0) for g, r in zip(got, ref, strict=True)]
        da = [rotation_angle_deg(g[1].T @ r[1]) for g, r in zip(got, ref, strict=True)]
        print(
            f"{name}: range differences {np.round(np.array(dr) * 100, 3)} %, rotation {np.round(da, 3)} deg"
        )
        assert np.median(dr) <= 0.01 and np.median(da) <= 1.0
    estimator.use_calibration(None)
    for f in warped:  # without the file: refused, never a guess
        with pytest.raises(FrameError):
            estimator.estimate(f, t_s=0.0)
    estimator.use_calibration(tmp_path / "other.yaml")
    with pytest.raises(FrameError, match="does not match the calibration"):
        estimator.estimate(natives[0], t_s=0.0)
    estimator.use_calibration(None)


# ------------------------------------------------------------------ oibar pose
def test_oibar_pose_prints_one_json_line_per_frame(capsys):
    frames = [str(GOLDEN / "cold_3m.png"), str(GOLDEN / "cold_8m.png")]
    rc = main(["pose", *frames, "--threads", "1"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    lines = [json.loads(x) for x in out.splitlines()]
    assert [x["frame"] for x in lines] == frames
    for x in lines:
        keys = {"frame", "T_cam_target_m", "q_cam_target_wxyz", "confidence", "flags", "latency_ms", "crops"}
        assert set(x) == keys
        assert len(x["T_cam_target_m"]) == 3 and len(x["q_cam_target_wxyz"]) == 4
        assert 0.0 <= x["confidence"] <= 1.0 and x["latency_ms"] > 0 and x["crops"] >= 1
    assert 3.0 < np.linalg.norm(lines[0]["T_cam_target_m"]) < 4.5 and lines[0]["confidence"] > 0.9


def test_oibar_pose_with_a_calibration_reads_the_other_camera(capsys, tmp_path):
    write_camera_info_yaml(tmp_path / "info.yaml", OTHER)
    Image.fromarray(warp_to(OTHER, _native("cold_3m"))).save(tmp_path / "w.png")
    rc = main(
        ["pose", str(tmp_path / "w.png"), "--calibration", str(tmp_path / "info.yaml"), "--threads", "1"]
    )
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert 3.0 < np.linalg.norm(json.loads(out)["T_cam_target_m"]) < 4.5


def test_oibar_pose_fails_on_a_bad_frame_without_a_traceback(capsys, tmp_path):
    good = GOLDEN / "cold_3m.png"
    corrupt = tmp_path / "corrupt.png"
    corrupt.write_bytes(good.read_bytes()[:3000])
    Image.new("RGB", (640, 480)).save(tmp_path / "small.png")
    rc = main(["pose", str(good), str(corrupt), str(tmp_path / "missing.png"), str(tmp_path / "small.png")])
    out, err = capsys.readouterr()
    assert rc == 3
    lines = [json.loads(x) for x in out.splitlines()]
    assert len(lines) == 4 and "error" not in lines[0]
    assert all(x["error"] and x["T_cam_target_m"] is None for x in lines[1:])
    assert "frame refused" in lines[3]["error"]
    assert "Traceback" not in err and "3 of 4 frame(s)" in err


def test_oibar_pose_start_up_errors_are_one_line(capsys, tmp_path):
    good = str(GOLDEN / "cold_3m.png")
    assert main(["pose", good, "--model", str(tmp_path / "none.onnx")]) == 2
    err = capsys.readouterr().err
    assert "model file not found" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    (tmp_path / "bad.yaml").write_text("just text\n")
    assert main(["pose", good, "--calibration", str(tmp_path / "bad.yaml")]) == 2
    err = capsys.readouterr().err
    assert "bad.yaml" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
