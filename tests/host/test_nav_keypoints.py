"""Crop windows and PnP (oibar.nav.keypoints): the geometry the keypoint estimator relies on,
tested without a network (exact projections in, the pose out)."""

from __future__ import annotations

import numpy as np
import pytest

from oibar.geometry.rotations import matrix_to_rotvec, rotation_angle_deg, rotvec_to_matrix
from oibar.nav.keypoints import CropWindow, cut, project, solve_pnp, window_around

K = np.array([[583.3333, 0, 372.0], [0, 583.3333, 240.0], [0, 0, 1]])
# a fixture-like point set (rim corners, pin guides, couplings, connector corners, centre)
POINTS = np.array(
    [
        [-0.25, -0.18, 0],
        [0.25, -0.18, 0],
        [0.25, 0.18, 0],
        [-0.25, 0.18, 0],
        [-0.17, 0, 0.005],
        [0.17, 0, 0.005],
        [-0.1, 0.115, 0.002],
        [0.1, 0.115, 0.002],
        [-0.045, -0.135, 0.0045],
        [0.045, -0.135, 0.0045],
        [0.045, -0.095, 0.0045],
        [-0.045, -0.095, 0.0045],
        [0, 0, 0.012],
    ]
)


def test_window_maps_points_both_ways():
    win = CropWindow((400.3, 200.7), 87.0, 160, np.radians(12))
    uv = np.array([[400.3, 200.7], [410.0, 190.0], [380.5, 230.25]])
    c = win.to_crop(uv)
    assert np.allclose(c[0], [80, 80])  # the centre lands in the middle
    assert np.allclose(win.to_frame(c), uv)
    assert np.isclose(np.linalg.norm(c[1] - c[0]), np.linalg.norm(uv[1] - uv[0]) * 160 / 87.0)


@pytest.mark.parametrize("side_px", [60.0, 160.0, 700.0])  # enlarging, 1:1, area-shrunk by 4
def test_cut_puts_a_frame_point_where_the_window_says(side_px):
    """A bright square centred on a frame point must appear centred on its crop coordinates,
    whatever the scale (the pixel-convention conversions to OpenCV are where this breaks)."""
    img = np.zeros((480, 744, 3), np.uint8)
    p = np.array([352.0, 251.0])  # frame point (corner convention)
    r = max(2, int(side_px / 40))
    img[int(p[1]) - r : int(p[1]) + r, int(p[0]) - r : int(p[0]) + r] = 255
    win = CropWindow((360.4, 240.8), side_px, 160)
    crop = cut(img, win).astype(float)[..., 0]
    ys, xs = np.mgrid[0:160, 0:160]
    m = crop / crop.sum()
    centroid = np.array([(m * (xs + 0.5)).sum(), (m * (ys + 0.5)).sum()])
    assert np.linalg.norm(centroid - win.to_crop(p[None])[0]) < 0.15 * max(1.0, 160 / side_px)


def test_cut_reads_black_outside_the_frame():
    img = np.full((480, 744, 3), 200, np.uint8)
    crop = cut(img, CropWindow((0.0, 0.0), 100.0, 64))
    assert crop[:20, :20].max() == 0 and crop[-20:, -20:].min() == 200


def _pose(rotvec, T):
    return rotvec_to_matrix(np.asarray(rotvec, float)), np.asarray(T, float)


@pytest.mark.parametrize("T", [(0.02, 0.12, 0.8), (0.3, -0.2, 4.0), (-1.2, 0.5, 10.3)])
def test_pnp_recovers_the_pose_from_exact_keypoints(T):
    R, T = _pose(np.radians([3.0, -4.0, 8.0]), T)
    uv = project(K, POINTS, R, T)
    r = solve_pnp(uv, POINTS, K, reproj_px=1.0)
    assert r.ok, r.reason
    assert np.linalg.norm(r.T_cam_target_m - T) < 1e-6 * np.linalg.norm(T) + 1e-9
    assert np.allclose(r.R_cam_target, R, atol=1e-7)
    assert r.rms_px < 1e-6 and len(r.inliers) == len(POINTS)


def test_pnp_rejects_outliers_and_missing_points():
    R, T = _pose(np.radians([1.0, 2.0, -3.0]), (0.1, 0.1, 3.0))
    uv = project(K, POINTS, R, T)
    uv[[0, 5, 9]] += np.array([[25, -30], [40, 12], [-18, 22]])  # three wrong detections
    uv[12] = np.nan  # one not found
    r = solve_pnp(uv, POINTS, K, reproj_px=2.0)
    assert r.ok, r.reason
    assert set(r.inliers.tolist()).isdisjoint({0, 5, 9, 12})
    assert np.linalg.norm(r.T_cam_target_m - T) / 3.0 < 1e-6


def test_pnp_says_why_it_has_no_answer():
    R, T = _pose([0, 0, 0], (0, 0, 2.0))
    uv = project(K, POINTS, R, T)
    uv[4:] = np.nan
    r = solve_pnp(uv, POINTS, K, reproj_px=2.0)
    assert not r.ok and "only 4 keypoints" in r.reason
    noise = np.random.default_rng(1).uniform(0, 744, (len(POINTS), 2))  # points with no consistent pose
    r = solve_pnp(noise, POINTS, K, reproj_px=0.5)
    assert not r.ok and r.reason


def test_window_around_grows_with_margin_and_keeps_a_minimum():
    pts = np.array([[100.0, 100.0], [140.0, 120.0]])
    w = window_around(pts, 160, 1.25)
    assert w.center_px == (120.0, 110.0) and w.side_px == pytest.approx(50.0)
    assert window_around(pts[:1], 160, 1.25).side_px == 24.0


def test_a_stepped_window_moves_in_its_own_sides_and_scales_about_its_new_centre():
    w = CropWindow((100.0, 50.0), 40.0, 128)
    s = w.stepped(-0.5, 0.25, 0.6)
    assert s.center_px == (80.0, 60.0) and s.side_px == pytest.approx(24.0) and s.out_px == 128
    assert w.stepped(0, 0, 1.0) == w
    # the new window's centre lands on the crop point the step names in the old one
    assert np.allclose(w.to_crop(np.array([s.center_px])), [[64.0 - 0.5 * 128, 64.0 + 0.25 * 128]])


def test_translation_given_rotation_is_exact():
    from oibar.nav.keypoints import translation_given_rotation

    R, T = _pose(np.radians([2.0, -1.0, 4.0]), (0.4, -0.1, 7.5))
    assert np.allclose(translation_given_rotation(project(K, POINTS, R, T), POINTS, K, R), T, atol=1e-9)


def test_prior_weight_moves_the_attitude_between_keypoints_and_prior():
    from oibar.nav.keypoints import refine_with_prior

    R, T = _pose(np.radians([1.0, 2.0, 0.5]), (0.1, 0.1, 2.0))
    uv = project(K, POINTS, R, T)
    R_prior = rotvec_to_matrix(np.radians([3.0, -2.0, 0.0])) @ R
    R1, T1, rms, _ = refine_with_prior(
        uv, POINTS, K, R, T, R_prior, sigma_px=0.01, sigma_prior_rad=np.radians(90)
    )
    assert np.allclose(R1, R, atol=1e-6) and rms < 1e-3  # the keypoints win
    R2, _, _, _ = refine_with_prior(
        uv, POINTS, K, R, T, R_prior, sigma_px=100.0, sigma_prior_rad=np.radians(0.01)
    )
    assert np.allclose(R2, R_prior, atol=1e-4)  # the prior wins


@pytest.mark.parametrize(
    "prior_deg", [(3.0, -2.0, 0.5), (0.0, 0.0, 0.0), (1e-6, 0.0, 0.0), (40.0, 70.0, -30.0)]
)
def test_prior_fit_jacobian_matches_central_differences(prior_deg):
    """The closed-form Jacobian refine_with_prior steps with is the derivative of its residuals
    (checked the way it used to be computed: central differences of the residual function),
    across a small, a zero, a tiny and a large prior disagreement and per-point weights."""
    from oibar.nav.keypoints import _prior_fit_jacobian

    R, T = _pose(np.radians([4.0, -7.0, 20.0]), (0.3, -0.2, 1.7))
    rng = np.random.default_rng(3)
    uv = project(K, POINTS, R, T) + rng.normal(0.0, 0.8, (len(POINTS), 2))
    sig = rng.uniform(0.5, 3.0, (len(POINTS), 1))
    R_prior = rotvec_to_matrix(np.radians(prior_deg)) @ R
    s_prior = np.radians(2.0)

    def residuals(x):
        Rx = rotvec_to_matrix(x[:3]) @ R
        r_img = ((project(K, POINTS, Rx, T + x[3:]) - uv) / sig).ravel()
        return np.concatenate([r_img, matrix_to_rotvec(Rx @ R_prior.T) / s_prior])

    r, J = _prior_fit_jacobian(K, POINTS, uv, sig, R, T, R_prior, s_prior)
    assert np.allclose(r, residuals(np.zeros(6)), atol=1e-12)
    J_num = np.empty_like(J)
    for j in range(6):
        d = np.zeros(6)
        d[j] = 1e-6
        J_num[:, j] = (residuals(d) - residuals(-d)) / 2e-6
    assert np.allclose(J, J_num, rtol=1e-5, atol=1e-4 * np.abs(J_num).max())


@pytest.mark.parametrize("range_m", [0.8, 3.0, 10.0])
def test_the_reprojection_refinement_finds_opencvs_minimum(range_m):
    """solve_pnp's refinement (refine_reprojection, Levenberg-Marquardt on the closed-form
    Jacobian) lands where OpenCV's solvePnPRefineLM does from RANSAC's start, near and far (where
    the tilt is nearly flat in the cost), and never above that start's cost."""
    import cv2

    from oibar.nav.keypoints import refine_reprojection

    R, T = _pose(np.radians([2.0, -1.0, 5.0]), (0.04 * range_m, -0.03 * range_m, range_m))
    rng = np.random.default_rng(7)
    uv = project(K, POINTS, R, T) + rng.normal(0.0, 0.4, (len(POINTS), 2))
    uv[3] += 9.0  # an outlier RANSAC leaves out
    Kc = K.copy()
    Kc[:2, 2] -= 0.5  # OpenCV counts from pixel centres
    ok, rv, tv, inl = cv2.solvePnPRansac(
        POINTS, uv - 0.5, Kc, np.zeros(4), reprojectionError=4.0, flags=cv2.SOLVEPNP_SQPNP
    )
    inl = inl.ravel()
    assert ok and 3 not in inl
    R0, T0 = cv2.Rodrigues(rv)[0], tv.ravel()
    rv, tv = cv2.solvePnPRefineLM(POINTS[inl], uv[inl] - 0.5, Kc, np.zeros(4), rv, tv)
    R_cv, T_cv = cv2.Rodrigues(rv)[0], tv.ravel()
    R1, T1 = refine_reprojection(uv[inl], POINTS[inl], K, R0, T0)
    assert rotation_angle_deg(R1.T @ R_cv) < 1e-3 and np.linalg.norm(T1 - T_cv) < 1e-6 * range_m

    def cost(Rx, Tx):
        return float(np.sum((project(K, POINTS[inl], Rx, Tx) - uv[inl]) ** 2))

    assert cost(R1, T1) <= cost(R_cv, T_cv) + 1e-9 and cost(R1, T1) <= cost(R0, T0)
    # from a start off the minimum it still goes downhill
    R2, T2 = refine_reprojection(uv[inl], POINTS[inl], K, rotvec_to_matrix(np.radians([1.0, 0, 0])) @ R0, T0)
    assert cost(R2, T2) < cost(rotvec_to_matrix(np.radians([1.0, 0, 0])) @ R0, T0)


def test_far_keypoints_with_an_attitude_prior_give_no_mirrored_pose():
    """At 10 m the near-planar fixture's keypoints barely constrain its tilt: with 0.15 px noise PnP
    alone may return a pose tilted tens of degrees. With the direct model's attitude (1 deg off)
    as a prior, every answer stays within 3 deg and 1 % of range."""
    from oibar.nav.keypoints import map_pose

    rng = np.random.default_rng(7)
    for _ in range(25):
        R, T = _pose(
            np.radians(rng.uniform(-3, 3, 3)), (rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(8, 10.5))
        )
        uv = project(K, POINTS, R, T) + rng.normal(0, 0.15, (len(POINTS), 2))
        R_prior = rotvec_to_matrix(np.radians(rng.normal(0, 0.6, 3))) @ R
        r = map_pose(uv, POINTS, K, 1.0, R_prior, 0.15, np.radians(2.0))
        assert r.ok
        att = np.degrees(
            np.linalg.norm(
                __import__("oibar.geometry.rotations", fromlist=["x"]).matrix_to_rotvec(r.R_cam_target @ R.T)
            )
        )
        assert att < 3.0 and np.linalg.norm(r.T_cam_target_m - T) / np.linalg.norm(T) < 0.01, (att, T)


# ----------------------------------------------------------------------------- model 0.5.0: depth, weights, tracking
DEEP = np.vstack([POINTS, [[0.0, 0.0, 0.18]]])  # + the drogue's throat, 0.18 m behind the rim


def _att_deg(Ra, Rb):
    from oibar.geometry.rotations import matrix_to_rotvec

    return float(np.degrees(np.linalg.norm(matrix_to_rotvec(Ra @ Rb.T))))


def test_a_deep_point_pins_the_tilt_that_near_planar_points_cannot():
    """The reason for the throat keypoint: with 0.3 px of keypoint noise at 3 m, PnP on the
    near-planar front points alone is degrees off in tilt; one point 0.18 m deep brings it under
    a degree."""
    rng = np.random.default_rng(11)
    flat, deep = [], []
    for _ in range(30):
        R, T = _pose(np.radians(rng.uniform(-3, 3, 3)), (rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), 3.0))
        noise = rng.normal(0, 0.3, (len(DEEP), 2))
        uv = project(K, DEEP, R, T) + noise
        flat.append(_att_deg(solve_pnp(uv[:-1], POINTS, K, 3.0).R_cam_target, R))
        deep.append(_att_deg(solve_pnp(uv, DEEP, K, 3.0).R_cam_target, R))
    assert np.mean(flat) > 1.5 and np.mean(deep) < 0.6 * np.mean(flat), (np.mean(flat), np.mean(deep))


def test_per_keypoint_sigmas_let_a_poorly_found_point_count_less():
    """The throat 1.5 px off (as it is found under 1.5 m): with one sigma for all it tilts the
    pose; with its own, larger sigma (the error model's) the others win."""
    from oibar.nav.keypoints import map_pose

    R, T = _pose(np.radians([1.0, -1.0, 0.5]), (0.05, 0.02, 1.2))
    uv = project(K, DEEP, R, T)
    uv[-1] += (1.5, -1.0)
    R_prior = rotvec_to_matrix(np.radians([1.5, 1.0, 0.0])) @ R
    same = map_pose(uv, DEEP, K, 4.0, R_prior, 0.3, np.radians(2.0))
    sig = np.full(len(DEEP), 0.3)
    sig[-1] = 3.0
    own = map_pose(uv, DEEP, K, 4.0, R_prior, sig, np.radians(2.0))
    assert same.ok and own.ok
    assert _att_deg(own.R_cam_target, R) < 0.5 * _att_deg(same.R_cam_target, R), (
        _att_deg(own.R_cam_target, R),
        _att_deg(same.R_cam_target, R),
    )


def test_error_model_scales_by_range_and_refuses_bad_tables():
    from oibar.nav.error_models import KeypointErrorModel

    table = {"range_edges_m": [0.0, 1.5, 5.0, 100.0], "rms_crop_px": [[0.5, 0.3, 0.4], [2.0, 0.3, 0.5]]}
    m = KeypointErrorModel(table)
    near, mid, far = m.scale(0.8), m.scale(3.0), m.scale(250.0)  # beyond the last edge: the last bin
    assert near[1] / near[0] == pytest.approx(4.0) and mid[1] / mid[0] == pytest.approx(1.0)
    assert far[1] / far[0] == pytest.approx(1.25)
    assert np.sqrt(np.mean(np.array(table["rms_crop_px"]) ** 2)) * mid[0] == pytest.approx(0.3)
    with pytest.raises(ValueError, match="must be"):
        KeypointErrorModel({"range_edges_m": [0.0, 1.0], "rms_crop_px": [[0.5, 0.3]]})
    with pytest.raises(ValueError, match="finite and > 0"):
        KeypointErrorModel({"range_edges_m": [0.0, 1.0, 2.0], "rms_crop_px": [[0.5, 0.0]]})


def _shell(
    points=POINTS,
    out_px=128,
    fusion=None,
    zoom=False,
    scan=False,
    cold_crop_budget=None,
    meta=None,
):
    """A KeypointPoseEstimator without networks: a KeypointReader whose sessions the test
    replaces (`est.reader.run`, `est.reader.read_crop`), and the real Fusion and WindowSearch
    over it. No crop budget unless given: the whole cold search on one frame."""
    from pathlib import Path

    from oibar.nav.pose.fusion import Fusion
    from oibar.nav.pose.keypoint import KeypointPoseEstimator
    from oibar.nav.pose.reader import KeypointReader
    from oibar.nav.pose.search import WindowSearch

    reader = object.__new__(KeypointReader)
    reader.path, reader.meta = Path("test.onnx"), dict(meta or {})
    reader.points_m, reader.K_frame, reader.out_px, reader.margin = points, K, out_px, 1.25
    reader.reproj_crop_px, reader.min_present = 4.0, 0.5
    reader.max_spread_crop_px, reader.spread_scale = 9.0, 1.0
    reader.R_att_ref, reader.mirror = None, None
    reader.turned_reading_deg, reader.turned_reading_head = 0.0, False
    reader.corner_refine_side_px, reader.corner_idx = 0.0, np.zeros(0, int)
    # these fakes read a window alike at any turn, so the roll checks (roll.UPRIGHT_TWIN,
    # TURN_STEPS_DEG) could only cost crops here: they are tested on the real network (test_nav_roll)
    reader.upright = False
    est = object.__new__(KeypointPoseEstimator)
    est.path, est.meta, est.K_frame, est.range_limits_m = reader.path, reader.meta, K, (0.2, 20.0)
    est.overlap_first_pass, est._first_pass_thread = False, None
    est.reader = reader
    f = fusion or {"sigma_crop_px": 1.0, "sigma_prior_deg": 2.0}
    est.fusion = Fusion(reader.path, {"fusion": f}, points, K, 4.0, has_head=True)
    est.search = WindowSearch(
        reader, est.fusion, est.range_limits_m, 2, zoom, scan, None, placed_pass_refines=False
    )
    est.search.cold_crop_budget = cold_crop_budget  # any budget, even one a real search refuses
    return est


def _bare_estimator(
    R_true,
    T_true,
    R_head=None,
    fusion=None,
    zoom=False,
    max_side_ratio=np.inf,
    noise_px=0.0,
    out_px=128,
    scan=False,
    cold_crop_budget=None,
    zoom_out=False,
):
    """A KeypointPoseEstimator without networks: its 'keypoint network' reports the true points
    when the crop holds the fixture's centre and is at most `max_side_ratio` times the fixture's
    own window, nothing otherwise (what a trained net does), `noise_px` (crop px, seeded) added;
    and `R_head` as its attitude head's reading. Its batch run (the zoom search) says "present"
    for the crops that would give keypoints. No crop budget unless given: the whole cold search
    on one frame. No zoom-out unless asked (its crops would count in every search test here; it
    has its own test on a real frame)."""
    from oibar.nav.pose.reader import CropReading

    est = _shell(DEEP, out_px, fusion, zoom, scan, cold_crop_budget)
    est.search.zoom_out = zoom_out
    truth = project(K, DEEP, R_true, T_true)
    centre = truth.mean(0)
    own_side = window_around(truth, out_px, 1.25).side_px
    est.crops, est.mirrored = [], []
    rng = np.random.default_rng(1)

    def sees(win):
        inside = np.all(np.abs(win.to_crop(centre[None])[0] - win.out_px / 2) < win.out_px * 0.3)
        return bool(inside and win.side_px <= max_side_ratio * own_side)

    def read_crop(image, win, mirror=False):
        est.crops.append(win)
        est.mirrored.append(mirror)
        if sees(win):
            uv = (
                win.to_frame(win.to_crop(truth) + rng.normal(0.0, noise_px, truth.shape))
                if noise_px
                else truth.copy()
            )
        else:
            uv = np.full_like(truth, np.nan)
        return CropReading(uv, np.zeros(len(uv)), np.ones(len(uv)), R_head)

    est.batches = []

    def run(x):  # the zoom search's batch: only presence and spread are read
        est.batches.append(len(x))
        return {
            "kp_present": np.zeros((len(x), len(DEEP))),
            "kp_spread_px": np.full((len(x), len(DEEP)), 8.0),
        }

    est.reader.read_crop, est.reader.run, est.sees = read_crop, run, sees
    return est


def test_the_predicted_pose_places_the_first_crop():
    """At 10 m the direct model can be a metre off sideways: its windows (and the search around
    them) miss the fixture. The filter's prediction puts the first crop on it."""
    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 10.0))
    image = np.zeros((480, 744, 3), np.uint8)
    T_direct = T + (1.6, 0.0, 0.0)
    est = _bare_estimator(R, T)
    r, _ = est.search.solve(image, R, T_direct)
    assert (
        r is None and len(est.crops) == 11
    )  # the whole search, in vain (no zoom: the window's size is right)
    est = _bare_estimator(R, T)
    r, _ = est.search.solve(image, R, T_direct, prior=(R, T + (0.05, 0.02, 0.1)))
    assert r is not None and np.linalg.norm(r.T_cam_target_m - T) < 1e-3
    assert len(est.crops) == 2  # the prediction's window, one refinement
    est = _bare_estimator(R, T)  # a wrong prediction costs one crop
    r, _ = est.search.solve(image, R, T, prior=(R, T + (1.6, 0.0, 0.0)))
    assert r is not None and np.linalg.norm(r.T_cam_target_m - T) < 1e-3 and len(est.crops) == 3


def test_a_placed_crop_can_be_read_as_the_refining_pass_and_end_the_frame():
    """oibar.placed_pass_refines: the crop placed by the prediction is read as the refining pass
    (turned readings, the corner step) and a strong fit there is final when the window around that
    fit is where the placed one was (WELL_PLACED_CROP_PX): one crop a tracked frame instead of
    two. A window that held the fixture but sat off it is read again around the fit (0.15.8 kept
    such reads and lost 1 deg beyond 8 m on validation); a prediction that misses still falls back
    on the search, whose strong fit is then refined as before."""
    from oibar.nav.pose.search import WELL_PLACED_CROP_PX

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 10.0))
    image = np.zeros((480, 744, 3), np.uint8)
    T_direct = T + (0.4, 0.0, 0.0)
    close, off = T + (0.005, 0.002, 0.01), T + (0.1, 0.0, 0.0)
    # off (the default): the prediction's window read plainly, then one refinement
    est = _bare_estimator(R, T)
    r, _ = est.search.solve(image, R, T_direct, prior=(R, close))
    assert r is not None and est.mirrored == [False, True]
    # on: the prediction's window alone, read as the refining pass
    est = _bare_estimator(R, T)
    est.search.placed_pass_refines = True
    r, win = est.search.solve(image, R, T_direct, prior=(R, close))
    assert r is not None and np.linalg.norm(r.T_cam_target_m - T) < 1e-3
    assert est.mirrored == [True] and win is est.crops[0]
    # the estimator's own latest fit (a hint) places the crop the same way
    est = _bare_estimator(R, T)
    est.search.placed_pass_refines = True
    r, _ = est.search.solve(image, R, T_direct, hint=(R, close))
    assert r is not None and est.mirrored == [True]
    # a window that holds the fixture but sits off it: its strong fit is read again around itself
    est = _bare_estimator(R, T)
    est.search.placed_pass_refines = True
    r, win = est.search.solve(image, R, T_direct, prior=(R, off))
    placed = est.crops[0]
    assert est.sees(placed) and not est.search._well_placed(r, placed)
    on_truth = window_around(project(K, DEEP, R, T), placed.out_px, 1.25)
    assert np.hypot(*np.subtract(on_truth.center_px, placed.center_px)) * placed.scale > WELL_PLACED_CROP_PX
    assert r is not None and est.mirrored == [True, True] and win is est.crops[1]
    assert est.search._well_placed(r, win)
    assert not est.search._well_placed(
        r, CropWindow(win.center_px, win.side_px * 1.3, win.out_px)
    )  # too large
    # a prediction that misses: the search's plain reads find it, and its fit is refined
    est = _bare_estimator(R, T)
    est.search.placed_pass_refines = True
    r, win = est.search.solve(image, R, T_direct, prior=(R, T + (1.6, 0.0, 0.0)))
    assert r is not None and np.linalg.norm(r.T_cam_target_m - T) < 1e-3
    assert est.mirrored[0] is True and est.mirrored[-1] is True and not any(est.mirrored[1:-1])
    assert len(est.crops) >= 3 and win is est.crops[-1]


def test_a_placed_refining_read_is_refused_with_the_mirror_reading_or_when_not_a_flag():
    """A predicted window may not hold the fixture, and a crop of anything averaged with its mirror
    makes a symmetric pattern that PnP fits well: the two options are refused together, and a
    value that is not true or false is a damaged export."""
    from pathlib import Path

    from oibar.nav.pose import KeypointPoseEstimator, ModelFileError

    model = Path(__file__).resolve().parents[2] / "models" / "oibarnet.onnx"
    assert KeypointPoseEstimator(model, warmup_runs=0).search.placed_pass_refines is False
    assert (
        KeypointPoseEstimator(model, warmup_runs=0, placed_pass_refines=True).search.placed_pass_refines
        is True
    )
    with pytest.raises(ModelFileError, match="placed_pass_refines must be true or false"):
        KeypointPoseEstimator(model, warmup_runs=0, placed_pass_refines="yes")  # type: ignore[arg-type]
    with pytest.raises(ModelFileError, match="cannot go with oibar.mirror_reading"):
        KeypointPoseEstimator(model, warmup_runs=0, mirror=True, placed_pass_refines=True)
    assert KeypointPoseEstimator(model, warmup_runs=0, mirror=True).reader.mirror is not None


def test_an_unusable_prediction_is_ignored_and_a_malformed_one_refused():
    from oibar.nav.pose.keypoint import _checked_prior

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 10.0))
    assert _checked_prior(None) is None
    assert _checked_prior((R, T)) is not None
    assert _checked_prior((R, np.array([0.0, 0.0, -1.0]))) is None  # behind the camera
    assert _checked_prior((np.full((3, 3), np.nan), T)) is None
    assert _checked_prior((2 * R, T)) is None  # not a rotation
    with pytest.raises(ValueError, match="prior must be"):
        _checked_prior((R, T[:2]))


def test_the_crop_camera_turns_with_the_window():
    """R_crop_cam: a camera looking through the window's centre, rolled with the window, sees the
    points where the crop has them (to the affine crop's own approximation, < 2 crop px at the corners here);
    the opposite roll would put them 10+ px off."""
    from oibar.nav.keypoints import R_crop_cam

    R, T = _pose(np.radians([2.0, -3.0, 1.0]), (0.4, -0.25, 4.0))
    uv = project(K, DEEP, R, T)
    P_cam = DEEP @ R.T + T
    base = window_around(uv, 128, 1.25)
    assert abs(base.center_px[0] - K[0, 2]) > 50  # off the boresight: the ray matters
    for angle in (0.0, 0.25, -0.25):
        win = CropWindow(base.center_px, base.side_px, 128, angle)
        p = P_cam @ R_crop_cam(win, K).T
        q = K[0, 0] * win.scale * p[:, :2] / p[:, 2:3] + 64.0
        assert np.abs(q - win.to_crop(uv)).max() < 2.0, angle
        if angle:
            flipped = CropWindow(base.center_px, base.side_px, 128, -angle)
            p = P_cam @ R_crop_cam(flipped, K).T
            q = K[0, 0] * win.scale * p[:, :2] / p[:, 2:3] + 64.0
            assert np.abs(q - win.to_crop(uv)).max() > 10.0
    centred = CropWindow((K[0, 2], K[1, 2]), 100.0, 128)
    assert np.allclose(R_crop_cam(centred, K), np.eye(3))


def test_the_attitude_in_a_crop_maps_back_to_the_camera():
    from oibar.nav.keypoints import attitude_from_crop, attitude_in_crop_deg

    R_ref = rotvec_to_matrix(np.radians([0.0, 180.0, 0.0]))
    R, T = _pose(np.radians([2.0, -3.0, 1.0]), (0.4, -0.25, 4.0))
    win = CropWindow((500.0, 150.0), 90.0, 128, 0.2)
    att = attitude_in_crop_deg(win, K, R, R_ref)
    assert np.allclose(attitude_from_crop(win, K, att, R_ref), R, atol=1e-12)
    # the crop's roll is part of what the crop shows: the label turns with it
    att0 = attitude_in_crop_deg(CropWindow((500.0, 150.0), 90.0, 128, 0.0), K, R, R_ref)
    assert _att_deg(rotvec_to_matrix(np.radians(att)), rotvec_to_matrix(np.radians(att0))) == pytest.approx(
        np.degrees(0.2), abs=1e-6
    )


def _priors_seen(monkeypatch):
    """A list that collects the attitude prior of every fit (fusion.map_pose) from now on."""
    import oibar.nav.pose.fusion as fusion_mod

    seen = []
    real = fusion_mod.map_pose

    def spy(uv, P, K_, reproj, R_prior, *a):
        seen.append(R_prior)
        return real(uv, P, K_, reproj, R_prior, *a)

    monkeypatch.setattr(fusion_mod, "map_pose", spy)
    return seen


def _prior_sigmas_seen(monkeypatch):
    """A list that collects the attitude prior's sigma (rad) of every fit from now on."""
    import oibar.nav.pose.fusion as fusion_mod

    seen = []
    real = fusion_mod.map_pose

    def spy(uv, P, K_, reproj, R_prior, s_px, s_rad, *a):
        seen.append(s_rad)
        return real(uv, P, K_, reproj, R_prior, s_px, s_rad, *a)

    monkeypatch.setattr(fusion_mod, "map_pose", spy)
    return seen


@pytest.mark.parametrize("source", ["head", "direct", None])
def test_the_attitude_head_is_the_fits_prior_when_the_fusion_says_so(monkeypatch, source):
    """fusion.attitude_prior = "head": each crop's own attitude reading is the prior of that
    crop's fit; "direct" or absent: the direct model's attitude, as before 0.6.0."""

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 6.0))
    R_head = R @ rotvec_to_matrix(np.radians([1.0, 0.0, 0.0]))
    R_direct = R @ rotvec_to_matrix(np.radians([0.0, -4.0, 0.0]))
    fusion = {"sigma_crop_px": 1.0, "sigma_prior_deg": 2.0}
    if source:
        fusion["attitude_prior"] = source
    est = _bare_estimator(R, T, R_head=R_head, fusion=fusion)
    seen = _priors_seen(monkeypatch)
    r, _ = est.search.solve(np.zeros((480, 744, 3), np.uint8), R_direct, T)
    assert r is not None and len(seen) == 2
    want = R_head if source == "head" else R_direct
    assert all(np.allclose(s, want) for s in seen)


def test_tilt_scaled_gives_a_shrunk_tilt_back_its_size_and_keeps_the_roll():
    """docking.tilt_scaled: the attitude error about x and y times the factor, about z as it was;
    a factor of 1 is the same attitude, and scaling by 1/g undoes scaling by g."""
    from oibar.geometry.docking import camera_pose_from_docking, docking_from_camera_pose, tilt_scaled

    att = np.radians([2.0, -1.5, 0.7])
    R = camera_pose_from_docking(np.zeros(3), att)[1]
    np.testing.assert_allclose(tilt_scaled(R, 1.0), R, atol=1e-12)
    got = docking_from_camera_pose(np.zeros(3), tilt_scaled(R, 1.25)).att_rad
    np.testing.assert_allclose(got, att * np.array([1.25, 1.25, 1.0]), atol=1e-12)
    np.testing.assert_allclose(tilt_scaled(tilt_scaled(R, 0.8), 1 / 0.8), R, atol=1e-12)


def test_the_head_gain_model_reads_its_range_bin_and_refuses_a_bad_table():
    """fusion.head_gain: one tilt gain per range bin, looked up by range (the end bins beyond the
    edges); a table of the wrong length, with falling edges or a gain outside 0.5-2 is refused."""
    from oibar.nav.error_models import HeadGainModel

    m = HeadGainModel({"range_edges_m": [0.0, 1.0, 3.0, 100.0], "tilt_gain": [0.8, 0.9, 1.0]})
    assert [m.gain(r) for r in (0.5, 1.0, 2.9, 50.0, 500.0, -1.0)] == [0.8, 0.9, 0.9, 1.0, 1.0, 0.8]
    with pytest.raises(ValueError, match="must have 3 entries"):
        HeadGainModel({"range_edges_m": [0.0, 1.0, 3.0, 100.0], "tilt_gain": [0.8, 0.9]})
    with pytest.raises(ValueError, match="rising"):
        HeadGainModel({"range_edges_m": [0.0, 3.0, 1.0], "tilt_gain": [0.8, 0.9]})
    with pytest.raises(ValueError, match="within 0.5-2.0"):
        HeadGainModel({"range_edges_m": [0.0, 1.0, 3.0], "tilt_gain": [0.8, 0.2]})
    with pytest.raises(ValueError, match="within"):
        HeadGainModel({"range_edges_m": [0.0, 1.0], "tilt_gain": [float("nan")]})


@pytest.mark.parametrize("edges", [[0.0, 3.0, 1.0], [0.0, 1.0, 1.0], [0.0, float("nan"), 3.0]])
@pytest.mark.parametrize(
    "kind", ["KeypointErrorModel", "PriorErrorModel", "HeadGainModel", "PriorSigmaScale"]
)
def test_every_range_table_refuses_edges_that_do_not_rise(kind, edges):
    """The export's per-range tables (keypoint and prior error models, head gain) share one check
    of their bins' edges: a falling, repeated or non-finite edge would bin a range silently into
    the wrong row, so the table is refused."""
    import oibar.nav.error_models as kp

    rows = {
        "KeypointErrorModel": {"rms_crop_px": [[0.5, 0.3]]},
        "PriorErrorModel": {"rms_deg": [1.0, 2.0]},
        "HeadGainModel": {"tilt_gain": [0.9, 1.0]},
        "PriorSigmaScale": {"sigma_scale": [1.0, 1000.0]},
    }[kind]
    getattr(kp, kind)({"range_edges_m": [0.0, 1.0, 3.0], **rows})  # the same table, rising: read
    with pytest.raises(ValueError, match="rising edges"):
        getattr(kp, kind)({"range_edges_m": edges, **rows})


def test_the_head_gain_gives_the_heads_tilt_back_before_it_is_the_prior(monkeypatch):
    """With fusion.head_gain the fit's prior is the head's reading with its tilt divided by the
    gain of the fixture's range bin (here 0.8 at 6 m: a 2 deg tilt read as 1.6 is given back 2);
    without it, the reading as it is."""
    from oibar.geometry.docking import camera_pose_from_docking, docking_from_camera_pose, tilt_scaled

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 6.0))
    att_true = docking_from_camera_pose(T, R).att_rad
    R_head = camera_pose_from_docking(np.zeros(3), att_true * np.array([0.8, 0.8, 1.0]))[1]  # shrunk
    gain = {"range_edges_m": [0.0, 3.0, 100.0], "tilt_gain": [0.5, 0.8]}
    seen = _priors_seen(monkeypatch)
    for table, want in ((gain, tilt_scaled(R_head, 1 / 0.8)), (None, R_head)):
        fusion = {"sigma_crop_px": 1.0, "sigma_prior_deg": 2.0, "attitude_prior": "head"}
        if table:
            fusion["head_gain"] = table
        seen.clear()
        r, _ = _bare_estimator(R, T, R_head=R_head, fusion=fusion).search.solve(
            np.zeros((480, 744, 3), np.uint8), R, T
        )
        assert r is not None and len(seen) == 2
        assert all(np.allclose(s, want, atol=1e-12) for s in seen)
    assert rotation_angle_deg(tilt_scaled(R_head, 1 / 0.8).T @ R) < 1e-6  # the truth again


def test_the_prior_error_model_weighs_the_prior_by_range(monkeypatch):
    """fusion.prior_error_model: the prior's sigma at a range is sigma_prior_deg times that bin's
    RMS over the overall RMS; a bad table is refused."""
    from oibar.nav.error_models import PriorErrorModel

    table = {"range_edges_m": [0.0, 3.0, 8.0, 100.0], "rms_deg": [2.0, 0.5, 2.0]}
    m = PriorErrorModel(table)
    ref = np.sqrt((4 + 0.25 + 4) / 3)
    assert m.scale(5.0) == pytest.approx(0.5 / ref) and m.scale(50.0) == pytest.approx(2.0 / ref)
    assert m.scale(500.0) == m.scale(50.0) and m.scale(-1.0) == m.scale(1.0)
    with pytest.raises(ValueError, match="must have 3 entries"):
        PriorErrorModel({"range_edges_m": [0.0, 3.0, 8.0, 100.0], "rms_deg": [1.0, 2.0]})
    with pytest.raises(ValueError, match="finite and > 0"):
        PriorErrorModel({"range_edges_m": [0.0, 1.0], "rms_deg": [0.0]})

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 5.0))
    fusion = {"sigma_crop_px": 1.0, "sigma_prior_deg": 2.0, "prior_error_model": table}
    est = _bare_estimator(R, T, fusion=fusion)
    seen = _prior_sigmas_seen(monkeypatch)
    r, _ = est.search.solve(np.zeros((480, 744, 3), np.uint8), R, T)
    assert r is not None and seen
    assert all(s == pytest.approx(np.radians(2.0) * 0.5 / ref) for s in seen)


def test_the_prior_sigma_scale_weakens_the_prior_only_in_its_ranges(monkeypatch):
    """fusion.prior_sigma_scale: the prior's sigma (after its error model) times the factor of the
    fixture's range bin: x1000 from 3 to 8 m, as measured elsewhere; a bad table, or one in a
    fusion with no prior to scale, is refused when the file is opened."""
    from oibar.nav.error_models import PriorSigmaScale
    from oibar.nav.pose import ModelFileError
    from oibar.nav.pose.fusion import Fusion

    table = {"range_edges_m": [0.0, 3.0, 8.0, 100.0], "sigma_scale": [1.0, 1000.0, 1.0]}
    m = PriorSigmaScale(table)
    assert (m.scale(2.9), m.scale(3.0), m.scale(7.9), m.scale(8.0), m.scale(500.0)) == (1, 1000, 1000, 1, 1)
    for bad, match in (
        ([1.0, 1000.0], "must have 3 entries"),
        ([1.0, 0.0, 1.0], "within"),
        ([1.0, float("inf"), 1.0], "within"),
        ([1.0, 1e5, 1.0], "within"),
    ):
        with pytest.raises(ValueError, match=match):
            PriorSigmaScale({"range_edges_m": table["range_edges_m"], "sigma_scale": bad})

    seen = _prior_sigmas_seen(monkeypatch)
    for range_m, factor in ((5.0, 1000.0), (2.0, 1.0), (9.0, 1.0)):
        R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.05, -0.02, range_m))
        fusion = {"sigma_crop_px": 1.0, "sigma_prior_deg": 2.0, "prior_sigma_scale": table}
        seen.clear()
        r, _ = _bare_estimator(R, T, fusion=fusion).search.solve(np.zeros((480, 744, 3), np.uint8), R, T)
        assert r is not None and seen
        assert all(s == pytest.approx(np.radians(2.0) * factor) for s in seen), (range_m, seen)

    args = ("m.onnx", DEEP, K, 2.0, False)
    with pytest.raises(ModelFileError, match="prior sigma scale"):
        Fusion(
            args[0],
            {
                "fusion": {
                    "sigma_crop_px": 1.0,
                    "sigma_prior_deg": 2.0,
                    "prior_sigma_scale": {"range_edges_m": [0, 1], "sigma_scale": [0.0]},
                }
            },
            *args[1:],
        )
    with pytest.raises(ModelFileError, match="no prior"):
        Fusion(args[0], {"fusion": {"prior_sigma_scale": table}}, *args[1:])


def test_a_fit_with_a_prior_carries_its_prior_free_twin_for_the_filter():
    """map_pose with a prior keeps the same keypoints' PnP alone as `no_prior`; a prior that is
    off by 2 deg pulls the fused pose, not the twin, which is what the estimator hands a filter
    (measurement_without_prior) unless it lies grossly off the fused pose (a mirrored far fit)."""
    from oibar.nav.keypoints import PnpResult, map_pose
    from oibar.nav.pose.fusion import MEAS_MAX_ATT_DEV_DEG, measurement_without_prior

    R, T = _pose(np.radians([1.0, -0.5, 0.3]), (0.2, -0.1, 4.0))
    uv = project(K, DEEP, R, T) + np.random.default_rng(3).normal(0, 0.05, (len(DEEP), 2))
    R_prior = rotvec_to_matrix(np.radians([2.0, 0.0, 0.0])) @ R  # a biased head
    fused = map_pose(uv, DEEP, K, 2.0, R_prior, 0.5, np.radians(1.0))
    alone = map_pose(uv, DEEP, K, 2.0, R_prior, None, None)
    assert fused.ok and alone.ok and alone.no_prior is None
    assert fused.no_prior is not None and np.allclose(fused.no_prior.R_cam_target, alone.R_cam_target)

    def off_deg(Ra):
        return rotation_angle_deg(Ra.T @ R)

    assert off_deg(fused.R_cam_target) > 0.8 and off_deg(alone.R_cam_target) < 0.4  # (1.2, 0.2)
    T_m, R_m = measurement_without_prior(fused, fused.T_cam_target_m, fused.R_cam_target)
    assert np.allclose(R_m, alone.R_cam_target) and np.allclose(T_m, alone.T_cam_target_m)
    assert measurement_without_prior(alone, alone.T_cam_target_m, alone.R_cam_target) == (None, None)
    flipped = PnpResult(
        True,
        rotvec_to_matrix(np.radians([MEAS_MAX_ATT_DEV_DEG + 5, 0, 0])) @ fused.R_cam_target,
        fused.T_cam_target_m,
    )
    fused.no_prior = flipped
    assert measurement_without_prior(fused, fused.T_cam_target_m, fused.R_cam_target) == (None, None)
    fused.no_prior = PnpResult(True, fused.R_cam_target, fused.T_cam_target_m * 1.2)
    assert measurement_without_prior(fused, fused.T_cam_target_m, fused.R_cam_target) == (None, None)


def test_a_weak_fit_does_not_stop_the_search():
    """A fit whose keypoints miss by more than STRONG_FIT_RMS_CROP_PX (what a 'fixture' drawn on
    the station's structure gives) does not end the search; the strong fit found later wins.
    With nothing strong anywhere, the best weak fit comes back (estimate flags it weak_fit)."""
    from oibar.nav.pose.fusion import STRONG_FIT_RMS_CROP_PX, fit_rms_crop_px

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 6.0))
    image = np.zeros((480, 744, 3), np.uint8)
    est = _bare_estimator(R, T, noise_px=3.0)  # every window that sees it gives a weak fit
    r, win = est.search.solve(image, R, T)
    assert r is not None and fit_rms_crop_px(r, win) > STRONG_FIT_RMS_CROP_PX
    assert len(est.crops) == 11  # the whole search ran: nothing strong stopped it
    # a strong fit behind a weak first window: the first window sees the fixture badly
    est = _bare_estimator(R, T)
    good_read = est.reader.read_crop

    def first_one_weak(image, win, mirror=False):
        reading = good_read(image, win, mirror)
        if len(est.crops) == 1:
            reading.uv_px = reading.uv_px + np.random.default_rng(0).normal(
                0, 3.0 / win.scale, reading.uv_px.shape
            )
        return reading

    est.reader.read_crop = first_one_weak
    r, win = est.search.solve(image, R, T)
    assert r is not None and fit_rms_crop_px(r, win) <= STRONG_FIT_RMS_CROP_PX
    assert np.linalg.norm(r.T_cam_target_m - T) < 1e-3 and len(est.crops) > 2  # searched on


def test_a_bigger_crop_is_held_to_the_same_fraction_of_its_crop():
    """The fit thresholds were measured on 128 px crops. A model reading a 256 px crop whose
    keypoints are as good relative to the fixture (twice the error in its own crop pixels) must
    get the same verdict: a strong fit in the first window, not a search run to the end and a
    weak answer."""
    from oibar.nav.pose.fusion import STRONG_FIT_RMS_CROP_PX, fit_rms_crop_px

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 6.0))
    image = np.zeros((480, 744, 3), np.uint8)
    rms = {}
    for out_px in (128, 256):
        est = _bare_estimator(R, T, noise_px=0.6 * out_px / 128, out_px=out_px)
        r, win = est.search.solve(image, R, T)
        assert r is not None and win.out_px == out_px
        rms[out_px] = fit_rms_crop_px(r, win)
        # strong at once: the first window and the refining pass, no search
        assert rms[out_px] <= STRONG_FIT_RMS_CROP_PX and len(est.crops) <= 3, (out_px, rms[out_px])
        # in the crop's own pixels the 256 px fit misses by more than the threshold
        own_px = float(r.rms_px) * win.scale
        assert own_px == pytest.approx(rms[out_px] * out_px / 128)
    assert float(r.rms_px) * win.scale > STRONG_FIT_RMS_CROP_PX
    assert rms[256] == pytest.approx(rms[128], rel=0.3)


def test_the_zoom_search_finds_a_far_fixture_the_first_pass_took_for_a_near_one():
    """The first pass puts the fixture 5x closer than it is: its window is 5x too large and the
    keypoint network (trained on windows within ~1.3x of the fixture's) finds nothing there.
    The zoom search reads smaller windows inside it in one batch and solves the most
    fixture-like; without it the frame has no answer."""
    from oibar.nav.pose.search import WIDE_STEPS, ZOOM_STEPS, ZOOM_TRY

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 9.0))
    image = np.zeros((480, 744, 3), np.uint8)
    T_direct = T / 5.0
    est = _bare_estimator(R, T, max_side_ratio=1.4)
    r, _ = est.search.solve(image, R, T_direct)
    assert r is None and len(est.crops) == 11 and not est.batches
    est = _bare_estimator(R, T, max_side_ratio=1.4, zoom=True)
    seen = est.reader.run

    def run(x):  # presence says which crops hold the fixture
        out = seen(x)
        ok = [est.sees(w) for w in est.zoom_windows_last]
        out["kp_present"][ok] = 1.0
        out["kp_spread_px"][ok] = 1.0
        return out

    real_zoom = type(est.search)._zoom_windows

    def zoom_windows(image, base, wide=False):
        from oibar.nav.keypoints import CropWindow
        from oibar.nav.pose.search import zoom_steps

        est.zoom_windows_last = [
            CropWindow(
                (base.center_px[0] + dx * base.side_px, base.center_px[1] + dy * base.side_px),
                base.side_px * k,
                base.out_px,
            )
            for dx, dy, k in zoom_steps(wide)
        ]
        return real_zoom(est.search, image, base, wide)

    est.reader.run, est.search._zoom_windows = run, zoom_windows
    r, _ = est.search.solve(image, R, T_direct, prior=(R, T + (2.0, 0.0, 0.0)))
    assert not est.batches  # with a prediction (a track), never: its cost would hit every weak frame
    est.crops.clear()
    r, _ = est.search.solve(image, R, T_direct)
    assert est.batches == [len(ZOOM_STEPS) + len(WIDE_STEPS)]
    assert r is not None and np.linalg.norm(r.T_cam_target_m - T) < 1e-3
    assert len(est.crops) <= 11 + ZOOM_TRY + 1  # the search, at most ZOOM_TRY zoomed, one refinement


def _zooming_estimator(R, T, background_spread_px=8.0):
    """A bare estimator whose zoom batch says which windows hold the fixture: presence 1 and a
    spread that grows with the window (a tighter window looks more fixture-like), the rest
    `background_spread_px`."""
    import oibar.nav.pose.search as search_mod
    from oibar.nav.keypoints import CropWindow

    est = _bare_estimator(R, T, max_side_ratio=1.4, zoom=True)
    truth = project(K, DEEP, R, T)
    centre, own_side = truth.mean(0), window_around(truth, 128, 1.25).side_px
    seen, windows = est.reader.run, []
    real_zoom = type(est.search)._zoom_windows

    def zoom_windows(image, base, wide=False):
        windows[:] = [
            CropWindow(
                (base.center_px[0] + dx * base.side_px, base.center_px[1] + dy * base.side_px),
                base.side_px * k,
                base.out_px,
            )
            for dx, dy, k in search_mod.zoom_steps(wide)
            if base.side_px * k >= search_mod.ZOOM_MIN_SIDE_PX  # as the real one drops them
        ]
        return real_zoom(est.search, image, base, wide)

    def run(x):
        out = seen(x)
        out["kp_spread_px"] = np.full_like(out["kp_present"], background_spread_px)
        for i, w in enumerate(windows):
            if np.all(np.abs(w.to_crop(centre[None])[0] - w.out_px / 2) < w.out_px * 0.3):
                out["kp_present"][i] = 1.0
                out["kp_spread_px"][i] = w.side_px / own_side
        return out

    est.reader.run, est.search._zoom_windows = run, zoom_windows
    return est


def test_the_zoom_goes_down_level_by_level_to_a_fixture_twenty_times_farther(monkeypatch):
    """A first pass that puts a 10 m fixture at 0.5 m (validation scene va012) draws a window 20x
    the fixture's: one level of zoom (at best 4x smaller) still sees nothing the keypoint
    network can read. The search zooms again into the most fixture-like window of each level
    until it finds it."""
    import oibar.nav.pose.search as search_mod

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 10.0))
    image = np.zeros((480, 744, 3), np.uint8)
    T_direct = T / 20.0

    est = _zooming_estimator(R, T)
    r, _ = est.search.solve(image, R, T_direct)
    assert len(est.batches) >= 2, est.batches
    assert r is not None and np.linalg.norm(r.T_cam_target_m - T) < 1e-3
    assert min(w.side_px for w in est.crops) >= search_mod.ZOOM_MIN_SIDE_PX
    monkeypatch.setattr(search_mod, "ZOOM_LEVELS", 1)
    est = _zooming_estimator(R, T)
    r, _ = est.search.solve(image, R, T_direct)
    # and no double windows around a first pass that has the scale wrong (WIDE_MAX_SIDE_PX)
    assert est.batches == [len(search_mod.ZOOM_STEPS)] and r is None


def test_the_first_zoom_level_looks_around_a_first_pass_that_missed_sideways(monkeypatch):
    """A first pass with the right range but the fixture 1.65 of its windows off (validation
    scene va003's look at 10 m: every cold start came out weak until the mission timed out).
    SEARCH_STEPS and the zoom inside the first pass's window cannot reach it; the first zoom
    level's WIDE_STEPS (double windows out to two sides away) can, and the next level zooms
    into the one that holds it."""
    import oibar.nav.pose.search as search_mod

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.0, 0.15, 10.0))
    image = np.zeros((480, 744, 3), np.uint8)
    side = window_around(project(K, DEEP, R, T), 128, 1.25).side_px
    T_direct = T + np.array([0.0, -1.65 * side * T[2] / K[1, 1], 0.0])  # 1.65 windows up

    est = _zooming_estimator(R, T, background_spread_px=30.0)
    r, _ = est.search.solve(image, R, T_direct)
    assert r is not None and np.linalg.norm(r.T_cam_target_m - T) < 1e-3
    monkeypatch.setattr(search_mod, "WIDE_STEPS", ())
    est = _zooming_estimator(R, T, background_spread_px=30.0)
    r, _ = est.search.solve(image, R, T_direct)
    assert r is None


def test_no_zoom_window_is_smaller_than_a_fixture_in_the_envelope():
    """A first pass that puts a far fixture a little nearer draws a small window already; the
    zoom must not cut it into windows smaller than ZOOM_MIN_SIDE_PX, where the keypoint network
    reads noise (a fit at 40 m)."""
    import oibar.nav.pose.search as search_mod

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 10.0))
    est = _bare_estimator(R, T, zoom=True)
    base = window_around(project(K, DEEP, R, T * 0.6), 128, 1.25)
    assert base.side_px * 0.25 < search_mod.ZOOM_MIN_SIDE_PX <= base.side_px * 0.5
    wins = est.search._zoom_windows(np.zeros((480, 744, 3), np.uint8), base)
    assert wins and all(w.side_px >= search_mod.ZOOM_MIN_SIDE_PX for w, _ in wins)
    assert est.batches == [sum(1 for *_, k in search_mod.ZOOM_STEPS if k == 0.5)]


def test_the_scan_windows_cover_the_frame_within_a_quarter_side():
    """Some scan window holds every frame point within a quarter of its side of its centre (per
    axis), as the keypoint network was trained; the outer windows sit flush with the edges."""
    from oibar.nav.pose.scan import SCAN_SIDE_PX, SCAN_STRIDE, scan_windows

    wins = scan_windows((744, 480), SCAN_SIDE_PX, SCAN_STRIDE, 128)
    c = np.array([w.center_px for w in wins])
    assert {w.side_px for w in wins} == {SCAN_SIDE_PX}
    assert c[:, 0].min() == SCAN_SIDE_PX / 2 and c[:, 0].max() == 744 - SCAN_SIDE_PX / 2
    assert c[:, 1].min() == SCAN_SIDE_PX / 2 and c[:, 1].max() == 480 - SCAN_SIDE_PX / 2
    gx, gy = np.meshgrid(np.linspace(SCAN_SIDE_PX / 2, 744 - SCAN_SIDE_PX / 2, 97), np.linspace(32, 448, 53))
    pts = np.c_[gx.ravel(), gy.ravel()]
    off = np.abs(pts[:, None, :] - c[None]).max(axis=2).min(axis=1)  # the nearest window, per axis
    assert off.max() <= 0.25 * SCAN_SIDE_PX + 1e-9
    assert len(wins) == 23 * 14
    one = scan_windows((60, 40), 64.0, 0.5, 128)  # a frame smaller than a window: one, centred
    assert [w.center_px for w in one] == [(30.0, 20.0)]


def _scanning_estimator(R, T, scan, cold_crop_budget=None):
    """A bare estimator whose first pass and zoom find nothing, and whose keypoint network reads
    a window holding the fixture exactly when it is within 1.4x of the fixture's own window and
    roughly (2 crop px of noise: a weak fit) when it is up to 2.5x; the scan's batch scores the
    windows that hold the fixture's centre by how tight they are."""
    from oibar.nav.pose.reader import CropReading

    est = _bare_estimator(R, T, zoom=False, scan=scan, cold_crop_budget=cold_crop_budget)
    truth = project(K, DEEP, R, T)
    centre, own_side = truth.mean(0), window_around(truth, 128, 1.25).side_px
    rng = np.random.default_rng(3)

    def holds(win):
        return bool(np.all(np.abs(win.to_crop(centre[None])[0] - win.out_px / 2) < win.out_px * 0.3))

    def read_crop(image, win, refining=False):
        est.crops.append(win)
        ratio = win.side_px / own_side
        if not holds(win) or ratio > 2.5:
            return CropReading(np.full_like(truth, np.nan), np.zeros(len(truth)), np.ones(len(truth)), None)
        noise = 0.0 if ratio <= 1.4 else 2.0
        uv = win.to_frame(win.to_crop(truth) + rng.normal(0.0, noise, truth.shape))
        return CropReading(uv, np.zeros(len(truth)), np.ones(len(truth)), None)

    def likeness(image, wins):
        est.batches.append(len(wins))
        return np.array([1.0 / (1.0 + w.side_px / own_side) if holds(w) else 0.0 for w in wins])

    est.reader.read_crop, est.reader.fixture_likeness = read_crop, likeness
    return est


def test_the_scan_finds_a_far_fixture_the_first_pass_misplaced_and_misjudged():
    """Validation scene va012's cold start: the first pass reads a 10 m fixture at ~0.5 m, its
    window is ~20x too large and off to one side; SEARCH_STEPS and the zoom find nothing. The
    scan reads the whole frame in 64 px windows (1.8x this fixture's), solves the most
    fixture-like: a weak fit, then again in the window that fit draws: a strong one. Without the
    scan the frame has no answer; with a prediction (a track) the scan never runs."""
    from oibar.nav.pose.fusion import STRONG_FIT_RMS_CROP_PX, fit_rms_crop_px
    from oibar.nav.pose.scan import SCAN_BATCH, SCAN_SIDE_PX

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 10.0))
    image = np.zeros((480, 744, 3), np.uint8)
    T_direct = (T + np.array([-2.0, 1.0, 0.0])) / 20.0
    assert 1.4 < SCAN_SIDE_PX / window_around(project(K, DEEP, R, T), 128, 1.25).side_px < 2.5

    est = _scanning_estimator(R, T, scan=False)
    r, _ = est.search.solve(image, R, T_direct)
    assert r is None and not est.batches
    est = _scanning_estimator(R, T, scan=True)
    r, win = est.search.solve(image, R, T_direct, prior=(R, T + (3.0, 0.0, 0.0)))
    assert r is None and not est.batches  # a track's weak frame never pays for the scan
    est = _scanning_estimator(R, T, scan=True)
    r, win = est.search.solve(image, R, T_direct)
    assert r is not None and np.linalg.norm(r.T_cam_target_m - T) < 1e-3
    assert fit_rms_crop_px(r, win) <= STRONG_FIT_RMS_CROP_PX
    n = 23 * 14
    assert est.batches == [SCAN_BATCH] * (n // SCAN_BATCH) + [n % SCAN_BATCH]
    scan_reads = [w for w in est.crops if w.side_px == SCAN_SIDE_PX]
    assert len(scan_reads) == 1  # the best-ranked held it; its weak fit drew the strong window
    assert len(est.crops) == 11 + 1 + 1 + 1  # the search, the scan's window, its redraw, refinement


def test_a_scan_window_that_sees_too_few_keypoints_is_read_again_smaller(monkeypatch):
    """Validation scene va012's look from 10.5 m with stage 15's network: the fixture's scan
    window ranks first but is too large for the network to see enough keypoints (3 of 14), so it
    gives no fit at all, not even a weak one to read again, and the scan ends empty (the rig's
    mission aborted). The scan's windows that give nothing are read again at SCAN_SHRINK_FACTOR
    of their side around their centre; the most fixture-like solves (weak here), and the window
    its pose draws solves strongly. Without SCAN_SHRINK the frame has no answer."""
    import oibar.nav.pose.scan as scan_mod
    from oibar.nav.pose.scan import SCAN_SHRINK, SCAN_SHRINK_FACTOR, SCAN_SIDE_PX

    R = FAR_R
    own_10m = window_around(project(K, DEEP, R, FAR_T), 128, 1.25).side_px
    T = FAR_T * own_10m / (SCAN_SIDE_PX / 2.6)  # further out: the scan's window 2.6x the fixture's own
    own = window_around(project(K, DEEP, R, T), 128, 1.25).side_px
    assert SCAN_SIDE_PX / own > 2.5 and SCAN_SIDE_PX * SCAN_SHRINK_FACTOR / own < 2.5
    image = np.zeros((480, 744, 3), np.uint8)
    T_direct = (T + np.array([-2.0, 1.0, 0.0])) / 20.0

    est = _scanning_estimator(R, T, scan=True)
    r, _ = est.search.solve(image, R, T_direct)
    assert r is not None and np.linalg.norm(r.T_cam_target_m - T) < 1e-3
    shrunk = [b for b in est.batches if b == len(SCAN_SHRINK)]
    assert len(shrunk) == 1  # the first-ranked window, read again smaller, found it
    assert len(est.crops) == 11 + 1 + 1 + 1 + 1  # search, scan window, its shrunk one, redraw, refine

    monkeypatch.setattr(scan_mod, "SCAN_SHRINK", ())
    est = _scanning_estimator(R, T, scan=True)
    r, _ = est.search.solve(image, R, T_direct)
    assert r is None


def test_a_shrunk_scan_read_that_overruns_the_budget_goes_on_next_frame():
    """The shrunk read (SCAN_SHRINK and its solve) is counted against the frame's crop budget;
    a frame without room for it leaves the search carried, and a later frame reads the window
    again and shrinks it."""
    from oibar.nav.pose.scan import SCAN_SHRINK, SCAN_SHRINK_FACTOR, SCAN_SIDE_PX

    R = FAR_R
    own_10m = window_around(project(K, DEEP, R, FAR_T), 128, 1.25).side_px
    T = FAR_T * own_10m / (SCAN_SIDE_PX / 2.6)
    assert SCAN_SIDE_PX * SCAN_SHRINK_FACTOR / window_around(project(K, DEEP, R, T), 128, 1.25).side_px < 2.5
    image = np.zeros((480, 744, 3), np.uint8)
    T_direct = (T + np.array([-2.0, 1.0, 0.0])) / 20.0
    # 57 crops a frame: the scan's last batch leaves 9, the first-ranked window takes 1, and its
    # shrunk read (9 + 1) does not fit
    est = _scanning_estimator(R, T, scan=True, cold_crop_budget=57)
    per_frame = []
    for _ in range(12):
        n_crops, n_batches = len(est.crops), len(est.batches)
        r, _ = est.search.solve(image, R, T_direct)
        per_frame.append((len(est.crops) - n_crops, est.batches[n_batches:]))
        if r is not None:
            break
        assert est.search.cold is not None  # carried, never dropped half-way
    assert r is not None and np.linalg.norm(r.T_cam_target_m - T) < 1e-3
    assert per_frame[-2][0] == 1 and len(SCAN_SHRINK) not in per_frame[-2][1]  # read, then out of crops
    assert per_frame[-1] == (4, [len(SCAN_SHRINK)])  # read again, shrunk, redrawn, refined


def test_the_latest_strong_fit_places_the_first_crop_when_there_is_no_prediction():
    """While the filter waits for a run of strong fits (the direct model disagrees), the
    estimator's own latest strong fit places the first crop: one crop, not the whole search
    again. A prediction, when there is one, comes first; and it is only a place: a wrong hint
    costs one crop and the search goes on."""
    from oibar.nav.fit_history import FitHistory

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 10.0))
    image = np.zeros((480, 744, 3), np.uint8)
    T_direct = T / 20.0
    est = _scanning_estimator(R, T, scan=True)
    r, _ = est.search.solve(image, R, T_direct, hint=(R, T + (0.05, 0.0, 0.1)))
    assert r is not None and np.linalg.norm(r.T_cam_target_m - T) < 1e-3
    assert len(est.crops) == 2 and not est.batches  # the hint's window, one refinement
    est = _scanning_estimator(R, T, scan=True)
    r, _ = est.search.solve(image, R, T_direct, hint=(R, T + (3.0, 0.0, 0.0)))
    assert r is not None and len(est.crops) == 1 + 11 + 3 and est.batches  # wrong hint: the search
    est = _scanning_estimator(R, T, scan=True)
    r, _ = est.search.solve(
        image, R, T_direct, prior=(R, T + (0.05, 0.0, 0.1)), hint=(R, T + (3.0, 0.0, 0.0))
    )
    assert r is not None and len(est.crops) == 2

    h = FitHistory()
    assert h.latest() is None
    h.advance(1.0)
    h.add(1.0, T, R)
    h.advance(1.1)
    h.add(1.1, T + 0.1, R)
    R_l, T_l = h.latest()
    assert np.allclose(T_l, T + 0.1) and np.allclose(R_l, R)
    h.advance(1.1 + 6.0)  # older than the window: nothing to place a crop with
    assert h.latest() is None


# va012's cold start, as in the scan's test above: the first pass reads a 10 m fixture at ~0.5 m
# and off to one side; only the scan finds it (11 + 322 + 2 crops, and the refining pass's one)
FAR_R, FAR_T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 10.0))
FAR_T_DIRECT = (FAR_T + np.array([-2.0, 1.0, 0.0])) / 20.0


def _with_first_pass(est, R_direct, T_direct):
    """A bare estimator that can `estimate`: a fake first pass answering (R_direct, T_direct)
    with confidence 1, and a frame with texture (not blank)."""
    from types import SimpleNamespace

    from oibar.geometry.rotations import matrix_to_quat
    from oibar.nav.fit_history import FitHistory
    from oibar.nav.pose import PoseEstimate

    def first_pass(image, t_s=0.0):
        q = matrix_to_quat(R_direct)
        rng_m = float(np.linalg.norm(T_direct))
        return PoseEstimate(T_direct.copy(), q, R_direct.copy(), t_s, 0.0, 1.0, rng_m, 0.0, ())

    est.first = SimpleNamespace(check_frame=lambda image: None, estimate=first_pass)
    est.fit_history, est.fusion.filter_measurement, est.frame_wh = FitHistory(), "prior_free", (744, 480)
    est.defect_scale = 0.02
    return est, np.random.default_rng(0).integers(0, 255, (480, 744, 3), dtype=np.uint8)


def _reads(est):
    """The windows est reads, in order, from now on: ("crop", centre, side) for one window through
    the keypoint network, ("batch", ((centre, side), ...)) for a batch of fixture-likeness."""
    log = []
    read_crop, likeness = est.reader.read_crop, est.reader.fixture_likeness

    def logged_read(image, win, refining=False):
        log.append(("crop", win.center_px, win.side_px))
        return read_crop(image, win, refining)

    def logged_likeness(image, wins):
        log.append(("batch", tuple((w.center_px, w.side_px) for w in wins)))
        return likeness(image, wins)

    est.reader.read_crop, est.reader.fixture_likeness = logged_read, logged_likeness
    return log


def _crops(log):
    return sum(1 if kind == "crop" else len(what[0]) for kind, *what in log)


def test_a_cold_frame_reads_no_more_crops_than_its_budget():
    """Without the budget a cold frame that reaches the scan reads 336 crops here (~1.8 s with
    the shipped model on 2 cores: past the MCU's 1 s link timeout). With it the frame stops at
    the budget, with no strong fit: the direct model's answer, low confidence, flagged
    `searching`."""
    from oibar.nav.pose.keypoint import FALLBACK_FACTOR
    from oibar.nav.pose.search import COLD_CROP_BUDGET

    est, frame = _with_first_pass(_scanning_estimator(FAR_R, FAR_T, scan=True), FAR_R, FAR_T_DIRECT)
    log = _reads(est)
    e = est.estimate(frame, 1.0)
    assert _crops(log) > 300 and "searching" not in e.flags  # the whole search in one frame

    est, frame = _with_first_pass(
        _scanning_estimator(FAR_R, FAR_T, scan=True, cold_crop_budget=COLD_CROP_BUDGET),
        FAR_R,
        FAR_T_DIRECT,
    )
    log = _reads(est)
    e = est.estimate(frame, 1.0)
    assert _crops(log) <= COLD_CROP_BUDGET
    assert "searching" in e.flags and "fallback_direct" in e.flags
    assert e.confidence <= FALLBACK_FACTOR + 1e-9  # never a fit the filter would take


def test_the_carried_search_finds_what_the_whole_search_finds_frame_by_frame():
    """Frames 0.3 s apart (the daemon's cycle while a cold search runs), each within the budget:
    the scan goes on where the last frame stopped, ranks every window it scored over the frames
    and solves the same window as the whole search on one frame, to the same answer. The frames
    before give provisional answers (`searching`, low confidence)."""
    from oibar.nav.pose.keypoint import FALLBACK_FACTOR
    from oibar.nav.pose.scan import SCAN_SIDE_PX
    from oibar.nav.pose.search import COLD_CROP_BUDGET

    est, frame = _with_first_pass(_scanning_estimator(FAR_R, FAR_T, scan=True), FAR_R, FAR_T_DIRECT)
    log = _reads(est)
    whole = est.estimate(frame, 1.0)
    solved = [what for kind, *what in log if kind == "crop" and what[1] == SCAN_SIDE_PX]
    assert np.linalg.norm(whole.T_cam_target_m - FAR_T) < 1e-3

    est, frame = _with_first_pass(
        _scanning_estimator(FAR_R, FAR_T, scan=True, cold_crop_budget=COLD_CROP_BUDGET),
        FAR_R,
        FAR_T_DIRECT,
    )
    log = _reads(est)
    scored = []
    for k in range(10):
        log.clear()
        e = est.estimate(frame, 1.0 + 0.3 * k)
        scored += [w for kind, *what in log if kind == "batch" for w in what[0]]
        if "searching" not in e.flags:
            break
        assert _crops(log) <= COLD_CROP_BUDGET and e.confidence <= FALLBACK_FACTOR + 1e-9
    assert k >= 5, k  # 335 crops (the refining pass aside) in frames of 60
    assert _crops(log) <= COLD_CROP_BUDGET + 1  # + the refining pass of the strong fit found
    assert [what for kind, *what in log if kind == "crop" and what[1] == SCAN_SIDE_PX] == solved
    assert len(scored) == 23 * 14 and len(set(scored)) == len(scored)  # each scan window once
    assert np.allclose(e.T_cam_target_m, whole.T_cam_target_m) and e.flags == whole.flags
    assert e.confidence == pytest.approx(whole.confidence)


def test_the_carried_zoom_goes_down_its_levels_frame_by_frame():
    """The zoom carried over frames (a 10 m fixture taken for a 0.5 m one): each level's batch
    and its solves as the frames' budgets allow, to the fixture the whole search finds."""
    from oibar.nav.pose.search import COLD_CROP_BUDGET

    image = np.zeros((480, 744, 3), np.uint8)
    est = _zooming_estimator(FAR_R, FAR_T)
    whole, _ = est.search.solve(image, FAR_R, FAR_T / 20.0)
    assert whole is not None and len(est.batches) >= 2
    assert len(est.crops) + sum(est.batches) > COLD_CROP_BUDGET

    est = _zooming_estimator(FAR_R, FAR_T)
    est.search.cold_crop_budget = COLD_CROP_BUDGET
    frames = 0
    while frames < 10:
        frames += 1
        est.crops.clear(), est.batches.clear()
        r, _ = est.search.solve(image, FAR_R, FAR_T / 20.0)
        if est.search.cold is None:
            break
        assert len(est.crops) + sum(est.batches) <= COLD_CROP_BUDGET
    assert frames >= 2 and len(est.crops) + sum(est.batches) <= COLD_CROP_BUDGET + 1
    assert np.allclose(r.T_cam_target_m, whole.T_cam_target_m)


def test_a_carried_search_ends_on_a_prediction_an_age_a_new_sequence_or_forget():
    """A carried search goes on only while its scores hold: a prediction (a track again) ends
    it, and so do COLD_CARRY_MAX_AGE_S of frame time since its first frame, a frame whose time
    does not advance, and forget(). A frame that goes on reads no SEARCH_STEPS (its first read
    is the scan's batch); one that starts afresh reads them first."""
    from oibar.nav.pose.search import COLD_CARRY_MAX_AGE_S, COLD_CROP_BUDGET, SEARCH_STEPS

    def carrying():
        est, frame = _with_first_pass(
            _scanning_estimator(FAR_R, FAR_T, scan=True, cold_crop_budget=COLD_CROP_BUDGET),
            FAR_R,
            FAR_T_DIRECT,
        )
        assert "searching" in est.estimate(frame, 1.0).flags
        return est, frame, _reads(est)

    def afresh(log):
        return [kind for kind, *_ in log[: len(SEARCH_STEPS)]] == ["crop"] * len(SEARCH_STEPS)

    est, frame, log = carrying()
    assert "searching" in est.estimate(frame, 1.0 + COLD_CARRY_MAX_AGE_S - 0.1).flags
    assert log[0][0] == "batch"  # went on
    est, frame, log = carrying()
    est.estimate(frame, 1.0 + COLD_CARRY_MAX_AGE_S + 0.1)
    assert afresh(log)
    est, frame, log = carrying()
    est.estimate(frame, 1.0)  # time not advancing: a new sequence
    assert afresh(log)
    est, frame, log = carrying()
    est.forget()
    est.estimate(frame, 1.1)
    assert afresh(log)
    est, frame, log = carrying()
    e = est.estimate(frame, 1.1, prior=(FAR_R, FAR_T + (3.0, 0.0, 0.0)))  # a prediction that misses
    assert "searching" not in e.flags and all(kind == "crop" for kind, *_ in log)  # no cold search
    log.clear()
    est.estimate(frame, 1.2)
    assert afresh(log)  # the next cold frame starts afresh


@pytest.mark.parametrize("scene", ["scan", "zoom", "zoom_levels"])
def test_a_cold_frame_within_its_budget_reads_what_it_reads_without_one(scene):
    """The budget changes nothing for a frame whose search fits it: the same windows read in
    the same order (single crops and batches) and the same answer as with no budget, down to
    a budget of exactly what the frame reads (the refining pass aside); one crop less stops it."""

    def run(budget):
        if scene == "scan":
            est = _scanning_estimator(FAR_R, FAR_T, scan=True, cold_crop_budget=budget)
            T_direct = FAR_T_DIRECT
        else:
            est = _zooming_estimator(FAR_R, FAR_T)
            est.search.cold_crop_budget = budget
            T_direct = FAR_T / (5.0 if scene == "zoom" else 20.0)
        log = _reads(est)
        r, win = est.search.solve(np.zeros((480, 744, 3), np.uint8), FAR_R, T_direct)
        return log, r, est.search.cold

    log, r, _ = run(None)
    assert r is not None and np.linalg.norm(r.T_cam_target_m - FAR_T) < 1e-3
    needed = _crops(log) - 1  # the refining pass is outside the budget
    for budget in (needed, needed + 50):
        log_b, r_b, cold = run(budget)
        assert log_b == log and cold is None
        assert np.array_equal(r_b.T_cam_target_m, r.T_cam_target_m)
    log_b, r_b, cold = run(needed - 1)
    assert cold is not None and (r_b is None or not np.allclose(r_b.T_cam_target_m, FAR_T, atol=1e-3))


def test_a_budget_below_the_zooms_first_batch_is_refused():
    """A budget that could never read the zoom's first batch (and the hint's crop) would stall
    the cold search for good."""
    from pathlib import Path

    from oibar.nav.pose import KeypointPoseEstimator
    from oibar.nav.pose.search import MIN_COLD_CROP_BUDGET

    model = Path(__file__).resolve().parents[2] / "models/oibarnet.onnx"
    with pytest.raises(ValueError, match="cold_crop_budget"):
        KeypointPoseEstimator(model, cold_crop_budget=MIN_COLD_CROP_BUDGET - 1, warmup_runs=0)


def test_a_weak_fit_inside_the_range_envelope_is_preferred_to_a_tighter_one_outside():
    """With no strong fit, solve returns the best weak one: inside the range envelope first,
    then the lowest RMS. A tiny window's fit at 40 m must not win on its RMS alone."""
    from oibar.nav.keypoints import CropWindow, PnpResult

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 10.0))
    est = _bare_estimator(R, T)
    win = CropWindow((372.0, 240.0), 64.0, 128)
    near = PnpResult(True, R, T, np.arange(8), 2.0 / win.scale)
    far = PnpResult(True, R, T * 4.0, np.arange(8), 1.5 / win.scale)
    assert est.search._weak_rank(near, win) < est.search._weak_rank(far, win)
    answers = iter([(far, win), (near, win)] + [(None, None)] * 20)
    est.search._one_pass = lambda *a, **k: next(answers)
    r, _ = est.search.solve(np.zeros((480, 744, 3), np.uint8), R, T)
    assert r is near


def test_the_fixture_keypoints_pair_up_in_the_mirror():
    from oibar.geometry.fixture import FIXTURE_KEYPOINTS
    from oibar.nav.keypoints import mirror_permutation

    names = [n for n, _ in FIXTURE_KEYPOINTS]
    twin = mirror_permutation(np.array([p for _, p in FIXTURE_KEYPOINTS]))
    assert twin is not None
    pairs = {names[i]: names[j] for i, j in enumerate(twin)}
    assert pairs["rim_top_left"] == "rim_top_right" and pairs["coupling_right"] == "coupling_left"
    assert pairs["drogue_throat"] == "drogue_throat" and np.array_equal(twin[twin], np.arange(len(twin)))
    lopsided = POINTS.copy()
    lopsided[4, 0] = -0.16  # one pin guide moved: no twin
    assert mirror_permutation(lopsided) is None


def _leaning_estimator(
    truth_crop: np.ndarray, att_deg: np.ndarray, lean_px: float, lean_deg: float, mirror: bool
):
    """A KeypointReader (with attitude head) whose network leans right: every keypoint
    `lean_px` crop px right of where it is and the head's y reading `lean_deg` high, in whatever
    image it is shown: the crop, or (a batch of two) the crop and its mirror image."""
    from oibar.nav.keypoints import MIRROR_ATT, mirror_permutation

    est = _shell(meta={"attitude_head": {"output": "att_crop_deg"}}).reader
    est.R_att_ref, est.head_output = np.eye(3), "att_crop_deg"
    est.mirror = mirror_permutation(POINTS) if mirror else None
    lean = np.array([lean_px, 0.0])
    est.batches = []

    def run(x):
        est.batches.append(len(x))
        kp, att = [truth_crop + lean], [att_deg + [0.0, lean_deg, 0.0]]
        if len(x) == 2:
            assert np.array_equal(x[1], x[0][:, :, ::-1])  # the second is the first, mirrored
            m = truth_crop[est.mirror].copy()
            m[:, 0] = 128 - m[:, 0]
            kp.append(m + lean)
            att.append(att_deg * MIRROR_ATT + [0.0, lean_deg, 0.0])
        n = len(POINTS)
        return {
            "kp_crop_px": np.array(kp, np.float32),
            "kp_present": np.ones((len(x), n), np.float32),
            "kp_spread_px": np.ones((len(x), n), np.float32),
            "att_crop_deg": np.array(att, np.float32),
        }

    est.run = run
    return est


def test_reading_the_crop_and_its_mirror_cancels_the_networks_left_right_leaning():
    """The fixture is left-right symmetric, so the mirror image of a crop is a view of it too. A
    network that leans right on every image (0.8.1 reads a -0.24 deg tilt about y at 2-5 m on
    validation, +0.12 in the mirror) leans left once its mirror reading is mapped back; the
    average of both is where the keypoints are, and the head's lean cancels the same way. A
    keypoint set without twins is read once, and so is a crop when the mirror is not asked for."""
    from oibar.nav.keypoints import attitude_from_crop

    R, T = rotvec_to_matrix(np.radians([0.4, -0.3, 0.1])), np.array([0.05, -0.03, 4.0])
    truth = project(K, POINTS, R, T)
    win = window_around(truth, 128, 1.25)
    att = np.array([0.8, 0.3, -0.2])
    image = np.random.default_rng(0).integers(0, 255, (480, 744, 3), dtype=np.uint8)

    single = _leaning_estimator(win.to_crop(truth), att, 0.3, 0.25, mirror=False)
    r1 = single.read_crop(image, win, refining=True)  # no twins: read once
    assert single.batches == [1] and np.allclose(r1.uv_px - truth, [0.3 / win.scale, 0.0], atol=1e-4)

    est = _leaning_estimator(win.to_crop(truth), att, 0.3, 0.25, mirror=True)
    assert np.allclose(est.read_crop(image, win).uv_px, r1.uv_px) and est.batches == [1]  # not asked
    r2 = est.read_crop(image, win, refining=True)
    assert est.batches == [1, 2]
    assert np.allclose(r2.uv_px, truth, atol=1e-4)
    want = attitude_from_crop(win, K, att, np.eye(3))
    assert rotation_angle_deg(r2.R_cam_target_head.T @ want) < 1e-4
    assert rotation_angle_deg(r1.R_cam_target_head.T @ want) == pytest.approx(0.25, abs=1e-3)


def test_only_the_refining_pass_reads_the_mirror():
    """Which windows hold the fixture is decided on single readings (the prediction's window, the
    search's, the zoom's): a crop of anything averaged with its mirror is a symmetric pattern
    PnP fits well (validation scene va012's cold start: 96 % range errors at confidence 0.96
    when every window was read with its mirror). The refining pass, cut around a strong fit, is."""
    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 10.0))
    image = np.zeros((480, 744, 3), np.uint8)
    est = _bare_estimator(R, T)
    r, _ = est.search.solve(image, R, T * np.array([1.0, 1.0, 1.02]))
    assert r is not None and est.mirrored == [False, True]
    est = _bare_estimator(R, T)  # a prediction that misses, then the direct model's window
    r, _ = est.search.solve(image, R, T, prior=(R, T + (1.6, 0.0, 0.0)))
    assert r is not None and est.mirrored == [False, False, True]
    est = _bare_estimator(R, T, noise_px=3.0)  # nothing strong: no refining pass, no mirror
    r, _ = est.search.solve(image, R, T)
    assert r is not None and len(est.mirrored) == 11 and not any(est.mirrored)


@pytest.mark.parametrize("out_px", [128, 192])
def test_a_keypoint_with_a_broad_heat_map_is_not_there(out_px):
    """On the fixture every heat map is ~5.7 px wide (in 128 px crop terms); a crop of the station's
    structure gives broad ones that PnP can still fit (va012's cold start: six keypoints spread
    8.5-25 px, a 0.42 m answer for a 10 m fixture at confidence 0.94). Keypoints broader than
    MAX_SPREAD_CROP_PX (scaled with the crop) are dropped like absent ones; with too few left
    there is no fit to be confident about."""
    from oibar.nav.pose.reader import MAX_SPREAD_CROP_PX

    R, T = _pose(np.radians([0.5, -0.5, 0.2]), (0.3, -0.1, 4.0))
    truth = project(K, POINTS, R, T)
    win = window_around(truth, out_px, 1.25)
    scale = out_px / 128
    n = len(POINTS)
    spread = np.full(n, 5.7 * scale)
    spread[:8] = (MAX_SPREAD_CROP_PX + 1.0) * scale  # eight broad: five tight ones remain

    est = _shell(out_px=out_px).reader

    def run(x):
        return {
            "kp_crop_px": win.to_crop(truth)[None].astype(np.float32),
            "kp_present": np.ones((1, n), np.float32),
            "kp_spread_px": spread[None].astype(np.float32),
        }

    est.run = run
    image = np.zeros((480, 744, 3), np.uint8)
    r = est.read_crop(image, win)
    assert np.all(np.isnan(r.uv_px[:8])) and np.allclose(r.uv_px[8:], truth[8:], atol=1e-3)
    spread[:8] = (MAX_SPREAD_CROP_PX - 0.5) * scale  # tight enough: all kept
    assert np.all(np.isfinite(est.read_crop(image, win).uv_px))
    # a network with its own, broader gate (oibar.pnp.max_spread_crop_px: trained on measured
    # labels) keeps what the default gate drops, and reports its spreads in the default's terms
    spread[:8] = (MAX_SPREAD_CROP_PX + 1.0) * scale
    est.max_spread_crop_px, est.spread_scale = 2 * MAX_SPREAD_CROP_PX, 0.5
    assert np.all(np.isfinite(est.read_crop(image, win).uv_px))
    spread[:8] = (2 * MAX_SPREAD_CROP_PX + 1.0) * scale
    assert np.all(np.isnan(est.read_crop(image, win).uv_px[:8]))
    assert est.heat_spread(image, [win])[0] == pytest.approx(0.5 * spread.mean() / scale)


@pytest.mark.parametrize("gate", [0, -3.0, "9", True, float("inf")])
def test_a_keypoint_gate_that_is_not_a_spread_is_refused(gate, tmp_path):
    """oibar.pnp.max_spread_crop_px, when an export carries it, must be a spread > 0."""
    import json
    import shutil
    from pathlib import Path

    import onnx

    from oibar.nav.pose import KeypointPoseEstimator, ModelFileError, read_metadata
    from oibar.nav.pose.model_file import companion_files

    shipped = Path(__file__).resolve().parents[2] / "models"
    m = onnx.load(str(shipped / "oibarnet.onnx"))
    for p in m.metadata_props:
        if p.key == "oibar.pnp":
            p.value = json.dumps({**json.loads(p.value), "max_spread_crop_px": gate})
    onnx.save(m, str(tmp_path / "oibarnet.onnx"))
    meta = read_metadata(shipped / "oibarnet.onnx")
    for name in companion_files(meta).values():
        shutil.copy(shipped / name, tmp_path / name)
    with pytest.raises(ModelFileError, match="max_spread_crop_px"):
        KeypointPoseEstimator(tmp_path / "oibarnet.onnx", warmup_runs=0)


def _windowed_estimator(monkeypatch, truth: np.ndarray, turned_deg: float, seen_in=None):
    """A keypoint estimator whose network reads every keypoint exactly, in whichever window it
    is shown (each cut crop carries its window's index, so the fake network knows the window);
    `seen_in(i)` -> the keypoints present in window i's reading."""
    import oibar.nav.pose.reader as reader_mod

    est = _shell()
    est.reader.turned_reading_deg = turned_deg
    est.windows, est.batches = [], []

    def cut_spy(image, win):
        est.windows.append(win)
        return np.full((win.out_px, win.out_px, 3), len(est.windows) - 1, np.uint8)

    def run(x):
        est.batches.append(len(x))
        idx = [int(round(float(c[0, 0, 0]) * 255)) for c in x]
        n = len(POINTS)
        present = np.ones((len(x), n), np.float32)
        if seen_in is not None:
            for b, i in enumerate(idx):
                present[b] = 0.0
                present[b, seen_in(i)] = 1.0
        return {
            "kp_crop_px": np.array([est.windows[i].to_crop(truth) for i in idx], np.float32),
            "kp_present": present,
            "kp_spread_px": np.full((len(x), n), 5.0, np.float32),
        }

    monkeypatch.setattr(reader_mod, "cut", cut_spy)
    est.reader.run = run
    return est


def test_the_refining_pass_can_also_read_its_window_turned(monkeypatch):
    """oibar.turned_reading_deg: the refining pass reads its window three times in one batch, as
    cut and turned +-8 deg about its centre (a camera rolled about its boresight), and averages
    the keypoints in frame pixels, each reading mapped back through its own window. 0.8.1 on
    validation: attitude 0.84 -> 0.81 deg, the filter's measurement 0.86 -> 0.82. Any other
    window is read once."""
    R, T = _pose(np.radians([0.4, -0.3, 0.1]), (0.05, -0.03, 4.0))
    truth = project(K, POINTS, R, T)
    win = window_around(truth, 128, 1.25)
    image = np.zeros((480, 744, 3), np.uint8)

    est = _windowed_estimator(monkeypatch, truth, 8.0)
    once = est.reader.read_crop(image, win)
    assert est.batches == [1] and np.allclose(once.uv_px, truth, atol=1e-3)
    r = est.reader.read_crop(image, win, refining=True)
    assert est.batches == [1, 3]
    turned = est.windows[1:]
    assert [np.degrees(w.angle_rad) for w in turned] == pytest.approx([0.0, 8.0, -8.0])
    assert all(w.center_px == win.center_px and w.side_px == win.side_px for w in turned)
    # each reading through its own window: a mixed-up window would put the points 8 deg off
    assert np.allclose(r.uv_px, truth, atol=1e-3)

    off = _windowed_estimator(monkeypatch, truth, 0.0)
    off.reader.read_crop(image, win, refining=True)
    assert off.batches == [1]


def test_a_turned_reading_keeps_a_keypoint_only_where_most_readings_see_it(monkeypatch):
    R, T = _pose(np.radians([0.4, -0.3, 0.1]), (0.05, -0.03, 4.0))
    truth = project(K, POINTS, R, T)
    win = window_around(truth, 128, 1.25)
    # keypoint 0 seen by the first reading only, keypoint 1 by the last two, the rest by all
    seen = {
        0: [0] + list(range(2, len(POINTS))),
        1: list(range(1, len(POINTS))),
        2: list(range(1, len(POINTS))),
    }
    est = _windowed_estimator(monkeypatch, truth, 8.0, seen_in=lambda i: seen[i])
    r = est.reader.read_crop(np.zeros((480, 744, 3), np.uint8), win, refining=True)
    assert np.all(np.isnan(r.uv_px[0]))
    assert np.allclose(r.uv_px[1:], truth[1:], atol=1e-3)
    assert r.present[0] == pytest.approx(1 / 3) and r.present[1] == pytest.approx(2 / 3)


def test_a_turned_reading_can_read_the_attitude_head_on_every_window(monkeypatch):
    """oibar.turned_reading_head: the head's answer is the mean of the three readings' (each
    already in the camera's axes); without it, the untouched window's alone. 0.15.3 at 8 deg on
    validation: attitude 0.539 -> 0.531 deg."""
    from dataclasses import replace as dc_replace

    R, T = _pose(np.radians([0.4, -0.3, 0.1]), (0.05, -0.03, 4.0))
    truth = project(K, POINTS, R, T)
    win = window_around(truth, 128, 1.25)
    image = np.zeros((480, 744, 3), np.uint8)
    # the fake head reads 1, 2 and 3 mrad about x in the untouched, +8 and -8 deg windows
    tilt = {0.0: 0.001, 8.0: 0.002, -8.0: 0.003}
    for on, want_rad in ((False, 0.001), (True, 0.002)):
        est = _windowed_estimator(monkeypatch, truth, 8.0)
        est.reader.turned_reading_head = on
        plain = est.reader._reading

        def with_head(w, out, plain=plain):
            a = round(float(np.degrees(w.angle_rad - win.angle_rad)), 6)
            return dc_replace(plain(w, out), R_cam_target_head=rotvec_to_matrix([tilt[a], 0.0, 0.0]))

        est.reader._reading = with_head
        r = est.reader.read_crop(image, win, refining=True)
        assert r.R_cam_target_head is not None
        assert np.allclose(matrix_to_rotvec(r.R_cam_target_head), [want_rad, 0.0, 0.0], atol=1e-9)
        assert np.allclose(r.uv_px, truth, atol=1e-3)  # the keypoints as before


def test_a_turned_reading_can_feed_the_filter_the_untouched_windows_fit(monkeypatch):
    """oibar.turned_reading_measurement: with "untouched" the refining pass's prior-free fit (what
    the filter is fed) is solved from the untouched window's keypoints, while the answer is fitted
    to the averaged ones; with "mean" (0.15.6) both use the average. 0.15.6's average shifted the
    measurement's signed attitude bias by 0.07-0.10 deg on validation and lost the loop on one turn.
    Here the turned windows read every keypoint 1.5 crop px to the right: the mean moves, the
    untouched window does not."""
    from oibar.nav.keypoints import solve_pnp

    R, T = _pose(np.radians([0.4, -0.3, 0.1]), (0.05, -0.03, 4.0))
    truth = project(K, POINTS, R, T)
    win = window_around(truth, 128, 1.25)
    image = np.zeros((480, 744, 3), np.uint8)
    fusion = {"sigma_crop_px": 0.5, "sigma_prior_deg": 1.0}
    got = {}
    for mode in ("mean", "untouched"):
        est = _windowed_estimator(monkeypatch, truth, 8.0)
        est.reader.reproj_crop_px, est.reader.margin, est.fusion.turned_reading_measurement = 4.0, 1.25, mode
        exact = est.reader.run

        def biased(x, exact=exact):
            out = exact(x)
            out["kp_crop_px"][1:, :, 0] += 1.5  # the turned readings (rows 1 and 2 of the batch)
            return out

        est.reader.run = biased
        r, w = est.search._one_pass(image, win, R, fusion, 4.0, refining=True)
        assert r is not None and w is win and r.no_prior is not None
        got[mode] = r
        # the answer is the fit to the averaged keypoints either way
        mean_uv = est.reader.read_crop(image, win, refining=True).uv_px
        assert np.linalg.norm(mean_uv - truth, axis=1).min() > 0.5
    R_u, T_u = got["untouched"].no_prior.pose()
    assert rotation_angle_deg(R_u.T @ R) < 1e-4 and np.allclose(T_u, T, atol=1e-6)
    R_m, T_m = got["mean"].no_prior.pose()
    want = solve_pnp(mean_uv, POINTS, K, 4.0 / win.scale, min_points=5)
    assert np.allclose(T_m, want.T_cam_target_m, atol=1e-9)
    assert np.linalg.norm(T_m - T) > 1e-3
    assert np.allclose(got["mean"].T_cam_target_m, got["untouched"].T_cam_target_m, atol=1e-9)

    # a window read once (the search's, not the refining pass's) keeps its own fit's twin
    est = _windowed_estimator(monkeypatch, truth, 8.0)
    est.reader.reproj_crop_px, est.reader.margin, est.fusion.turned_reading_measurement = (
        4.0,
        1.25,
        "untouched",
    )
    r, _ = est.search._one_pass(image, win, R, fusion, 4.0, refining=False)
    assert r is not None and r.no_prior is not None and est.batches == [1]


def test_a_turned_reading_head_flag_that_is_not_a_flag_is_refused(tmp_path):
    """A damaged export (oibar.turned_reading_head not true or false) is refused when it opens."""
    from pathlib import Path

    from oibar.nav.pose import KeypointPoseEstimator, ModelFileError

    model = Path(__file__).resolve().parents[2] / "models" / "oibarnet.onnx"
    with pytest.raises(ModelFileError, match="turned_reading_head"):
        KeypointPoseEstimator(model, warmup_runs=0, turned_reading_head="yes")  # type: ignore[arg-type]
    with pytest.raises(ModelFileError, match="turned_reading_measurement"):
        KeypointPoseEstimator(model, warmup_runs=0, turned_reading_measurement="median")
    assert KeypointPoseEstimator(model, warmup_runs=0).fusion.turned_reading_measurement == "mean"
    assert (
        KeypointPoseEstimator(model, warmup_runs=0, turned_reading_head=True).reader.turned_reading_head
        is True
    )


@pytest.mark.parametrize("bad", [20.0, -1.0, "8", True])
def test_a_turned_reading_the_network_never_saw_is_refused(bad):
    """Crops were turned up to 15 deg in training; beyond that the reading is of crops the
    network never saw, and a malformed value is a damaged export: refused when it opens."""
    from pathlib import Path

    from oibar.nav.pose import KeypointPoseEstimator, ModelFileError

    model = Path(__file__).resolve().parents[2] / "models" / "oibarnet.onnx"
    with pytest.raises(ModelFileError, match="turned_reading_deg"):
        KeypointPoseEstimator(model, warmup_runs=0, turned_reading_deg=bad)
    assert KeypointPoseEstimator(model, warmup_runs=0, turned_reading_deg=8).reader.turned_reading_deg == 8.0


def _dark_rectangle(corners_px: np.ndarray, shape=(480, 744), dark=30.0, bright=110.0, ss=8) -> np.ndarray:
    """A grey frame with a dark axis-aligned rectangle whose corners lie at sub-pixel positions
    (corner convention), anti-aliased by area: each pixel is the mean of ss x ss samples."""
    lo, hi = corners_px.min(0), corners_px.max(0)
    h, w = shape
    ys = (np.arange(h * ss) + 0.5) / ss
    xs = (np.arange(w * ss) + 0.5) / ss
    inside = ((ys >= lo[1]) & (ys < hi[1]))[:, None] & ((xs >= lo[0]) & (xs < hi[0]))[None, :]
    img = np.where(inside, dark, bright).reshape(h, ss, w, ss).mean(axis=(1, 3))
    return img.astype(np.uint8)


def test_a_rim_corner_is_moved_onto_the_frames_own_corner_to_a_fraction_of_a_pixel():
    """The keypoint network reads close corners 2-5x coarser than the frame has them; the
    sub-pixel search puts a corner it found within a pixel or two onto the image's own corner."""
    from oibar.nav.keypoints import refine_corners_px

    truth = np.array([[236.3, 207.7], [508.6, 207.7], [508.6, 403.2], [236.3, 403.2]])
    gray = _dark_rectangle(truth)
    rng = np.random.default_rng(4)
    start = truth + rng.uniform(-1.5, 1.5, truth.shape)
    uv = np.vstack([start, [[372.0, 300.0]]])  # a fifth keypoint that is not a corner
    out, moved = refine_corners_px(gray, uv, np.arange(4), half_win_px=5, max_move_px=2.5)
    assert moved.all()
    # within 0.3 px (the search's own bias, which depends on where in its pixel an edge lies, is
    # up to ~0.2 px), from a start up to 1.5 px off
    assert np.abs(out[:4] - truth).max() < 0.3
    assert np.linalg.norm(out[:4] - truth, axis=1).mean() < 0.2
    assert np.abs(start - truth).max() > 0.8
    np.testing.assert_array_equal(out[4], uv[4])  # untouched


def test_a_corner_search_keeps_the_network_where_it_cannot_trust_itself():
    """Flat windows (a corner in shadow), windows off the frame, missing keypoints and a search
    that runs further than allowed (it found another corner) leave the keypoint as read."""
    from oibar.nav.keypoints import refine_corners_px

    truth = np.array([[236.3, 207.7], [508.6, 207.7]])
    gray = _dark_rectangle(np.array([[236.3, 207.7], [508.6, 403.2]]))
    uv = np.array(
        [
            [120.0, 100.0],  # in the flat background
            [2.0, 3.0],  # its window would leave the frame
            [np.nan, np.nan],  # not seen
            truth[0] + [2.0, -2.0],  # 2.8 px off: further than max_move_px allows
            truth[1] + [0.6, 0.4],  # a good one
        ]
    )
    out, moved = refine_corners_px(gray, uv, np.arange(5), half_win_px=5, max_move_px=2.0)
    assert moved.tolist() == [False, False, False, False, True]
    np.testing.assert_array_equal(out[:4], uv[:4])
    assert np.linalg.norm(out[4] - truth[1]) < 0.3
    # off: half window 0, or no corners named
    for args in ((5, np.arange(0)), (0, np.arange(5))):
        o, m = refine_corners_px(gray, uv, args[1], half_win_px=args[0], max_move_px=2.0)
        assert not m.any()
        np.testing.assert_array_equal(o, uv)


def test_a_fixture_part_read_as_a_far_fixture_is_read_again_larger():
    """The lab look (validation scene va000 drawn by Mitsuba 3: matte grey print, one lamp at the
    camera, black background; 8 samples a pixel): at 2.36 m 0.34.0's keypoint network (kept beside
    its registry entry) takes the plate's right coupling for a whole fixture 8.6 m away, a strong
    fit the direct model agrees with. The zoom-out (oibar.nav.pose.zoom_out.ZOOM_OUT_*) finds the
    plate around it. The shipped network, fine-tuned on randomised looks, reads it without."""
    from pathlib import Path

    from PIL import Image

    from oibar.nav.pose import PoseEstimator

    frame = np.asarray(Image.open(Path(__file__).parent / "data" / "lab_look_2p36m.jpg").convert("RGB"))
    T_true_m = np.array([0.0, 0.12, 2.361511])
    models = Path(__file__).resolve().parents[2] / "models"
    for path in (models / "registry" / "oibarnet-0.34.0" / "oibarnet.onnx", models / "oibarnet.onnx"):
        est = PoseEstimator(path)
        e = est.estimate(frame, 0.0)
        assert abs(np.linalg.norm(e.T_cam_target_m) / np.linalg.norm(T_true_m) - 1.0) < 0.15, (path, e)
        est.search.zoom_out = False
        est.forget()
        e = est.estimate(frame, 0.0)
        ratio = np.linalg.norm(e.T_cam_target_m) / np.linalg.norm(T_true_m)
        if path.parent.name == "models":
            assert abs(ratio - 1.0) < 0.15, e.T_cam_target_m  # the shipped network needs no zoom-out here
        else:
            assert ratio > 2.5, e.T_cam_target_m  # the part, read far


def test_the_files_beside_an_export_are_named_by_role_and_the_version_line_names_each(tmp_path):
    """model_file.companion_files: the first pass, far network and finder an export names, in that
    order, roles it lacks left out; `oibar --version`'s model line names each with its version, and
    a companion missing makes the line say so instead of failing."""
    import shutil
    from pathlib import Path

    from oibar.nav.pose import read_metadata
    from oibar.nav.pose.model_file import companion_files
    from oibar.resources import model_version_text

    meta = {
        "first_pass": "lite.onnx",
        "finder": {"file": "f.onnx"},
        "far_network": {"file": "far.onnx", "from_m": 8},
    }
    assert list(companion_files(meta).items()) == [
        ("first_pass", "lite.onnx"),
        ("far_network", "far.onnx"),
        ("finder", "f.onnx"),
    ]
    assert companion_files({"first_pass": "lite.onnx"}) == {"first_pass": "lite.onnx"}
    assert companion_files({"finder": {}}) == {}
    shipped = Path(__file__).resolve().parents[2] / "models"
    files = companion_files(read_metadata(shipped / "oibarnet.onnx"))
    assert set(files) == {"first_pass", "finder"}  # 0.35.15: one network, a finder
    for name in ("oibarnet.onnx", *files.values()):
        shutil.copy(shipped / name, tmp_path / name)
    finder_v, first_v = (
        read_metadata(tmp_path / files[k])["model_version"] for k in ("finder", "first_pass")
    )
    line = model_version_text(tmp_path / "oibarnet.onnx")
    assert f"; finder {finder_v}, first pass {first_v}) " in line, line
    (tmp_path / files["finder"]).unlink()
    assert model_version_text(tmp_path / "oibarnet.onnx").startswith("unreadable: ")
