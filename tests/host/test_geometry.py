"""oibar.geometry: round trips, known values, the two pixel conventions, the docking frames, the
fixture's numbers and the paper's metrics. numpy only, like the package."""

from __future__ import annotations

import json
from dataclasses import asdict

import numpy as np
import pytest

from oibar.geometry import camera, docking, fixture, metrics, transforms
from oibar.geometry.camera import (
    CENTRE_MINUS_CORNER_PX,
    PIXEL_CENTRE,
    PIXEL_CORNER,
    PinholeCamera,
    centre_to_corner_px,
    corner_to_centre_px,
    intrinsics_corner_to_centre,
)
from oibar.geometry.rotations import (
    angle_between_quats_deg,
    matrix_to_quat,
    matrix_to_rotvec,
    quat_to_matrix,
    rot_x,
    rot_y,
    rot_z,
    rotation_angle_deg,
    rotation_angles_deg,
    rotvec_to_matrix,
    skew,
)


def random_rotvecs(n: int, seed: int = 0, max_angle_rad: float = np.pi) -> np.ndarray:
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return axis * rng.uniform(0.0, max_angle_rad, size=(n, 1))


# ----------------------------------------------------------------------------- rotations
def test_elementary_rotations_known_values():
    np.testing.assert_allclose(rot_z(np.pi / 2) @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(rot_x(np.pi / 2) @ [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(rot_y(np.pi / 2) @ [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], atol=1e-15)
    for f, axis in ((rot_x, 0), (rot_y, 1), (rot_z, 2)):
        v = np.zeros(3)
        v[axis] = 0.7
        np.testing.assert_allclose(f(0.7), rotvec_to_matrix(v), atol=1e-15)
    np.testing.assert_allclose(skew([1.0, 2.0, 3.0]) @ [4.0, 5.0, 6.0], np.cross([1, 2, 3], [4, 5, 6]))


def test_quaternion_known_values_and_sign():
    np.testing.assert_array_equal(matrix_to_quat(np.eye(3)), [1.0, 0.0, 0.0, 0.0])
    q = matrix_to_quat(rot_z(np.radians(90.0)))
    np.testing.assert_allclose(q, [np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)], atol=1e-15)
    # 180 deg about x: w = 0, the branch of the largest diagonal term
    np.testing.assert_allclose(matrix_to_quat(rot_x(np.pi)), [0.0, 1.0, 0.0, 0.0], atol=1e-15)
    # -q is the same rotation
    np.testing.assert_allclose(quat_to_matrix(-q), quat_to_matrix(q), atol=1e-15)


def test_rotation_round_trips_one_and_batched():
    rv = random_rotvecs(200, seed=1, max_angle_rad=np.pi - 1e-6)
    Rs = np.stack([rotvec_to_matrix(v) for v in rv])
    for v, R in zip(rv, Rs, strict=True):
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)
        np.testing.assert_allclose(matrix_to_rotvec(R), v, atol=1e-9)
        q = matrix_to_quat(R)
        assert q[0] >= 0.0 and np.linalg.norm(q) == pytest.approx(1.0)
        np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-14)
        assert rotation_angle_deg(R) == pytest.approx(np.degrees(np.linalg.norm(v)), abs=1e-6)
    # batched forms give what the one-rotation forms give, element by element (exactly)
    q_b = matrix_to_quat(Rs.reshape(10, 20, 3, 3))
    assert q_b.shape == (10, 20, 4)
    np.testing.assert_array_equal(q_b.reshape(-1, 4), np.stack([matrix_to_quat(R) for R in Rs]))
    np.testing.assert_allclose(quat_to_matrix(q_b).reshape(-1, 3, 3), Rs, atol=1e-14)
    np.testing.assert_allclose(matrix_to_rotvec(Rs), rv, atol=1e-9)
    np.testing.assert_allclose(rotation_angles_deg(Rs), [rotation_angle_deg(R) for R in Rs], atol=0)
    assert matrix_to_quat(np.zeros((0, 3, 3))).shape == (0, 4)


def test_small_angles_are_stable():
    for angle in (0.0, 1e-16, 1e-12, 1e-8):
        v = np.array([angle, -angle, 0.5 * angle])
        # below ~2e-12 rad the quaternion's vector part is taken as zero
        np.testing.assert_allclose(matrix_to_rotvec(rotvec_to_matrix(v)), v, rtol=1e-6, atol=3e-12)


def test_angle_between_quaternions():
    qa = matrix_to_quat(rot_y(np.radians(10.0)))
    qb = matrix_to_quat(rot_y(np.radians(-25.0)))
    assert angle_between_quats_deg(qa, qb) == pytest.approx(35.0, abs=1e-9)
    assert angle_between_quats_deg(qa, -qa) == pytest.approx(0.0, abs=1e-6)


def test_mean_quaternion_is_blind_to_sign_and_centred():
    from oibar.geometry.rotations import mean_quat

    # +-8 deg about z around a 20 deg turn about x: the mean is the turn, whatever each one's sign
    base = rot_x(np.radians(20.0))
    qs = [matrix_to_quat(rot_z(np.radians(a)) @ base) for a in (-8.0, 0.0, 8.0)]
    m = mean_quat(np.stack([qs[0], -qs[1], qs[2]]))
    assert angle_between_quats_deg(m, matrix_to_quat(base)) == pytest.approx(0.0, abs=1e-6)
    assert m[0] >= 0
    # two attitudes 10 deg apart about y: the mean is half way
    m2 = mean_quat(np.stack([matrix_to_quat(rot_y(0.0)), matrix_to_quat(rot_y(np.radians(10.0)))]))
    assert angle_between_quats_deg(m2, matrix_to_quat(rot_y(np.radians(5.0)))) == pytest.approx(0.0, abs=1e-6)


# ----------------------------------------------------------------------------- transforms
def test_rigid_transform_round_trips():
    rng = np.random.default_rng(2)
    for v in random_rotvecs(20, seed=3):
        t = rng.normal(size=3)
        T = transforms.make_T(rotvec_to_matrix(v), t)
        np.testing.assert_allclose(transforms.inv_T(T) @ T, np.eye(4), atol=1e-14)
        np.testing.assert_allclose(transforms.T_from_vec(transforms.log_T(T)), T, atol=1e-12)
        np.testing.assert_allclose(transforms.T_from_pose(t, matrix_to_quat(T[:3, :3])), T, atol=1e-14)
        p = rng.normal(size=(5, 3))
        np.testing.assert_allclose(
            transforms.transform_points(p, T[:3, :3], t), (T[:3, :3] @ p.T).T + t, atol=1e-14
        )
        dt_m, dr_deg = transforms.pose_error(
            T, T @ transforms.make_T(rot_x(np.radians(2.0)), [0.0, 0.03, 0.04])
        )
        assert dt_m == pytest.approx(0.05) and dr_deg == pytest.approx(2.0)
    stack = np.stack([transforms.make_T(rot_z(0.1 * k), [k, 0.0, 0.0]) for k in range(4)])
    np.testing.assert_allclose(
        transforms.inv_T(stack) @ stack, np.broadcast_to(np.eye(4), stack.shape), atol=1e-14
    )
    assert transforms.log_T(stack).shape == (4, 6)


def test_adjoint_moves_a_right_perturbation_to_the_left():
    T = transforms.T_from_vec(np.r_[0.3, -0.2, 1.0, 0.4, 0.1, -0.7])
    d = np.r_[1e-7, -2e-7, 3e-7, 2e-7, 1e-7, -1e-7]
    lhs = T @ transforms.T_from_vec(d)
    rhs = transforms.T_from_vec(transforms.adjoint(T) @ d) @ T
    np.testing.assert_allclose(lhs, rhs, atol=1e-12)


# ----------------------------------------------------------------------------- camera
def test_camera_numbers():
    cam = PinholeCamera()
    assert (cam.width_px, cam.height_px) == (744, 480)
    assert cam.fx_px == cam.fy_px == pytest.approx(583.3333, abs=1e-4)
    assert cam.hfov_deg == pytest.approx(65.06, abs=0.01) and cam.vfov_deg == pytest.approx(44.72, abs=0.01)
    d = cam.as_dict()
    assert json.loads(json.dumps(d)) == d and d["hfov_deg"] == round(cam.hfov_deg, 3)


def test_the_two_pixel_conventions_differ_by_exactly_half_a_pixel():
    assert (PIXEL_CORNER, PIXEL_CENTRE) == ("corner", "centre") and CENTRE_MINUS_CORNER_PX == -0.5
    cam = PinholeCamera()
    K_corner, K_centre = cam.K, cam.K_centre()
    np.testing.assert_array_equal(K_corner[:2, 2], [372.0, 240.0])  # the image centre, exactly
    np.testing.assert_array_equal(K_centre[:2, 2], [371.5, 239.5])  # OpenCV's
    np.testing.assert_array_equal(K_corner - K_centre, [[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    np.testing.assert_array_equal(intrinsics_corner_to_centre(K_corner), K_centre)
    np.testing.assert_array_equal(cam.K_opencv(), K_centre)
    p = np.random.default_rng(4).uniform([-2, -1, 1], [2, 1, 20], size=(50, 3))
    uv_corner = camera.project_camera_points(K_corner, p)
    uv_centre = camera.project_camera_points(K_centre, p)
    np.testing.assert_allclose(uv_corner - uv_centre, 0.5, atol=1e-12)
    np.testing.assert_allclose(corner_to_centre_px(uv_corner), uv_centre, atol=1e-12)
    np.testing.assert_allclose(centre_to_corner_px(uv_centre), uv_corner, atol=1e-12)
    # the top-left pixel's centre: (0.5, 0.5) in one convention, (0, 0) in the other
    np.testing.assert_array_equal(corner_to_centre_px([0.5, 0.5]), [0.0, 0.0])


def test_projections_agree_and_reject_points_behind():
    cam = PinholeCamera()
    np.testing.assert_array_equal(cam.project([[0.0, 0.0, 5.0]]), [[372.0, 240.0]])
    assert np.isnan(cam.project([[0.0, 0.0, -1.0]])).all()
    pts_t = fixture.fixture_corners_t()
    R, T = rot_y(np.radians(5.0)), np.array([0.1, 0.12, 3.0])
    uv = camera.project_target_points(cam.K, pts_t, R, T)
    np.testing.assert_allclose(uv, cam.project(transforms.transform_points(pts_t, R, T)), atol=1e-12)
    np.testing.assert_allclose(
        uv, camera.project_camera_points(cam.K, transforms.transform_points(pts_t, R, T)), atol=1e-12
    )
    behind = camera.project_target_points(cam.K, pts_t, np.eye(3), [0.0, 0.0, -1.0])
    assert np.isnan(behind).all()


def test_intrinsics_scale_exactly_in_the_corner_convention():
    K = camera.intrinsics(583.3, 583.3, 372.0, 240.0)
    Ks = camera.scale_intrinsics(K, 0.5, 0.5)
    p = np.array([[0.3, -0.2, 4.0]])
    np.testing.assert_allclose(camera.project_camera_points(Ks, p), camera.project_camera_points(K, p) * 0.5)
    np.testing.assert_allclose(Ks[:2, 2], [186.0, 120.0])  # still the image centre


def test_rotation_homography_maps_pixels_of_a_pure_rotation():
    K = PinholeCamera().K
    R = rot_z(0.2) @ rot_x(0.05)
    p = np.random.default_rng(5).uniform([-1, -1, 2], [1, 1, 9], size=(10, 3))
    H = camera.rotation_homography(K, R)
    uv = camera.project_camera_points(K, p)
    uvh = np.c_[uv, np.ones(len(uv))] @ H.T
    np.testing.assert_allclose(uvh[:, :2] / uvh[:, 2:], camera.project_camera_points(K, p @ R.T), atol=1e-9)


# ----------------------------------------------------------------------------- docking frames
def test_docking_round_trip_and_known_aligned_pose():
    g = docking.GEOMETRY
    # aligned, probe tip 5 m out: the fixture is straight ahead, 0.12 m below the boresight
    T, R = docking.camera_pose_from_docking([0.0, 0.0, 5.0], np.zeros(3))
    np.testing.assert_allclose(R, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(T, [0.0, 0.12, 5.0 + g.probe_tip_s_m + 0.30], atol=1e-12)
    rng = np.random.default_rng(6)
    for _ in range(20):
        r = rng.uniform([-0.5, -0.5, -0.1], [0.5, 0.5, 10.0])
        att = rng.uniform(-0.1, 0.1, 3)
        s = docking.docking_from_camera_pose(*docking.camera_pose_from_docking(r, att))
        np.testing.assert_allclose(s.r_D_m, r, atol=1e-12)
        np.testing.assert_allclose(s.att_rad, att, atol=1e-12)
        assert s.range_m == pytest.approx(r[2])
        assert s.lateral_m == pytest.approx(np.hypot(r[0], r[1]))
        np.testing.assert_allclose(s.R_D_cam, docking.R_D_cam_from_attitude(att), atol=1e-14)


def test_misalignment_and_lateral_offset():
    assert docking.lateral_offset_m([0.3, -0.4, 7.0]) == pytest.approx(0.5)
    assert docking.misalignment_deg(docking.R_D_cam_from_attitude(np.zeros(3))) == pytest.approx(
        0.0, abs=1e-6
    )
    assert docking.misalignment_deg(
        docking.R_D_cam_from_attitude(np.radians([3.0, 4.0, 0.0]))
    ) == pytest.approx(5.0)
    # roll does not count
    assert docking.misalignment_deg(
        docking.R_D_cam_from_attitude(np.radians([0.0, 0.0, 30.0]))
    ) == pytest.approx(0.0, abs=1e-6)


def test_mount_is_the_geometry_as_json():
    m = docking.MOUNT
    assert m.p_s_cam_m == tuple(docking.GEOMETRY.p_s_cam_m) == (0.0, -0.12, -0.30)
    np.testing.assert_array_equal(np.asarray(m.R_s_cam), docking.GEOMETRY.R_s_cam)
    d = asdict(m)
    assert json.loads(json.dumps(d)) == json.loads(
        json.dumps({"p_s_cam_m": [0.0, -0.12, -0.3], "R_s_cam": np.eye(3).tolist()})
    )
    np.testing.assert_array_equal(m.T_s_cam()[:3, 3], [0.0, -0.12, -0.30])


# ----------------------------------------------------------------------------- fixture
def test_fixture_numbers():
    d = fixture.FIXTURE
    c = fixture.fixture_corners_t()
    np.testing.assert_array_equal(
        c, [[-0.25, -0.18, 0.0], [0.25, -0.18, 0.0], [0.25, 0.18, 0.0], [-0.25, 0.18, 0.0]]
    )
    assert d.width_m > d.height_m
    kp = dict(fixture.FIXTURE_KEYPOINTS)
    assert len(kp) == len(fixture.FIXTURE_KEYPOINTS) == 14
    np.testing.assert_array_equal(fixture.keypoints_m()[:4], c)  # the rim corners, bit for bit
    # the literal keypoints are the front faces of the default fixture's parts
    zp = d.rim_depth_m
    expect = {
        "pin_guide_left": (-d.pin_guide_x_m, 0.0, zp - 0.015),
        "pin_guide_right": (d.pin_guide_x_m, 0.0, zp - 0.015),
        "coupling_left": (*d.couplings_xy_m[0], 0.002),
        "coupling_right": (*d.couplings_xy_m[1], 0.002),
        "connector_top_left": (
            d.connector_xy_m[0] - d.connector_size_m[0] / 2,
            d.connector_xy_m[1] - d.connector_size_m[1] / 2,
            zp - 0.0155,
        ),
        "connector_bottom_right": (
            d.connector_xy_m[0] + d.connector_size_m[0] / 2,
            d.connector_xy_m[1] + d.connector_size_m[1] / 2,
            zp - 0.0155,
        ),
        "drogue_centre": (0.0, 0.0, zp - 0.008),
        "drogue_throat": (0.0, 0.0, zp + d.drogue_depth_m),
    }
    for name, p in expect.items():
        np.testing.assert_allclose(kp[name], p, atol=1e-12, err_msg=name)
    # the throat's view cone stays inside what the mouth lets through
    depth = kp["drogue_throat"][2] - kp["drogue_centre"][2]  # lip to throat, 0.168 m
    assert fixture.KEYPOINT_VIEW_LIMIT_DEG["drogue_throat"] < np.degrees(
        np.arctan(d.drogue_mouth_radius_m / depth)
    )


def test_fixture_wireframe_outlines_the_rim():
    segs = fixture.fixture_wireframe_t()
    assert segs.ndim == 3 and segs.shape[1:] == (2, 3)
    pts = segs.reshape(-1, 3)
    np.testing.assert_allclose(pts[:, :2].min(0), [-0.25, -0.18])
    np.testing.assert_allclose(pts[:, :2].max(0), [0.25, 0.18])
    assert pts[:, 2].min() == 0.0


# ----------------------------------------------------------------------------- metrics
def test_paper_metrics_known_values():
    T = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 2.0]])
    T_hat = T + [[0.3, 0.4, 0.0], [0.0, 0.0, 0.2]]
    np.testing.assert_allclose(metrics.position_error_m(T_hat, T), [0.5, 0.2])
    np.testing.assert_allclose(metrics.position_error_pct(T_hat, T), [5.0, 10.0])
    q = matrix_to_quat(np.eye(3))
    q_hat = matrix_to_quat(rot_x(np.radians(4.0)))
    assert metrics.attitude_error_deg(q_hat, q) == pytest.approx(4.0)
    assert metrics.attitude_error_deg(-q_hat, q) == pytest.approx(4.0)  # sign-invariant
    s = metrics.summarize(T_hat, np.stack([q_hat, q]), T, np.stack([q, q]))
    assert s["frames"] == 2 and s["compliance_pos_pct"] == 50.0 and s["compliance_att_pct"] == 100.0
    assert s["dt_mean_pct"] == pytest.approx(7.5) and s["dq_mean_deg"] == pytest.approx(2.0)
    assert metrics.score(s) == pytest.approx(0.075 + np.radians(2.0))
    T_mean, q_mean = metrics.mean_pose(T, np.stack([q, -q]))
    np.testing.assert_allclose(T_mean, [0.0, 0.0, 6.0])
    np.testing.assert_allclose(q_mean, [1.0, 0.0, 0.0, 0.0], atol=1e-12)
    assert (metrics.POS_REQ_PCT, metrics.ATT_REQ_DEG) == (5.0, 5.0)


def test_attitude_error_matches_the_rotation_angle():
    rv = random_rotvecs(50, seed=7)
    q = matrix_to_quat(np.stack([rotvec_to_matrix(v) for v in rv]))
    q0 = np.tile(matrix_to_quat(np.eye(3)), (50, 1))
    np.testing.assert_allclose(
        metrics.attitude_error_deg(q, q0), np.degrees(np.linalg.norm(rv, axis=1)), atol=1e-6
    )
