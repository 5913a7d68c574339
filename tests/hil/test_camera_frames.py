import numpy as np

from oibar.geometry.camera import PinholeCamera
from oibar.geometry.docking import MOUNT
from oibar.geometry.rotations import matrix_to_quat, quat_to_matrix, rotvec_to_matrix
from oibar_hil.camera import gl_projection
from oibar_hil.frames import lvlh_rotation
from oibar_hil.ports import PORTS
from oibar_hil.relpose import camera_poses
from oibar_hil.trajectory import generate


def test_camera_model_matches_lens_and_sensor():
    cam = PinholeCamera()
    assert (cam.width_px, cam.height_px) == (744, 480)
    assert abs(cam.fx_px - 583.3333) < 1e-3 and cam.fx_px == cam.fy_px
    assert (cam.cx_px, cam.cy_px) == (372.0, 240.0)
    assert round(cam.hfov_deg, 1) == 65.1 and round(cam.vfov_deg, 1) == 44.7
    np.testing.assert_allclose(cam.project([[0, 0, 5.0]])[0], [372, 240])
    np.testing.assert_allclose(
        cam.project([[1.0, -0.5, 2.0]])[0], [372 + 583.3333 / 2, 240 - 583.3333 / 4], atol=1e-3
    )
    np.testing.assert_allclose(cam.K_opencv()[:2, 2], [371.5, 239.5])
    assert np.isnan(cam.project([[0, 0, -1.0]])).all()


def test_gl_projection_reproduces_pinhole():
    cam = PinholeCamera()
    P = gl_projection(cam)
    rng = np.random.default_rng(0)
    for _ in range(20):
        p = np.array([rng.uniform(-2, 2), rng.uniform(-1, 1), rng.uniform(0.5, 20)])
        eye = np.array([p[0], -p[1], -p[2], 1.0])
        clip = P @ eye
        ndc = clip[:3] / clip[3]
        u = (ndc[0] + 1) / 2 * cam.width_px
        v = (1 - ndc[1]) / 2 * cam.height_px
        np.testing.assert_allclose([u, v], cam.project(p[None])[0], atol=1e-6)


def test_quaternion_round_trip():
    rng = np.random.default_rng(1)
    for _ in range(50):
        R = rotvec_to_matrix(rng.normal(size=3))
        q = matrix_to_quat(R)
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-12)


def test_lvlh_axes_iss_convention():
    r = np.array([6778.0, 0.0, 0.0])
    v = np.array([0.0, 4.8, 6.0])
    R = lvlh_rotation(r, v)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0
    np.testing.assert_allclose(R[:, 2], -r / np.linalg.norm(r))  # +Z to Earth
    np.testing.assert_allclose(R[:, 0], v / np.linalg.norm(v), atol=1e-12)  # +X along v (circular)
    h = np.cross(r, v)
    np.testing.assert_allclose(R[:, 1], -h / np.linalg.norm(h))  # +Y = -orbit normal


def test_port_frames_right_handed_and_facing_their_approach():
    for port in PORTS.values():
        R = port.R_lvlh_t
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) > 0


def test_aligned_pose_label_convention():
    traj = generate(5)
    cp = camera_poses(traj, PORTS[1])
    k = int(np.argmax(traj.phase == 2))  # first phase-2 sample: on axis, attitude aligned
    k -= 1  # last phase-1 sample is exactly on axis, aligned
    np.testing.assert_allclose(cp.q_cam_target[k], [1, 0, 0, 0], atol=1e-12)
    d = traj.distance_m[k]
    np.testing.assert_allclose(
        cp.T_cam_target[k], [0, -MOUNT.p_s_cam_m[1], d - MOUNT.p_s_cam_m[2]], atol=1e-9
    )
    # Camera in LVLH looks along +Z_t, i.e. into the port (-X LVLH for the +V-bar port).
    np.testing.assert_allclose(cp.R_lvlh_cam[k][:, 2], [-1, 0, 0], atol=1e-12)
