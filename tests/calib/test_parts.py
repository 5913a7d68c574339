"""The building blocks: transforms, interpolation, closed form, refinement on exact data."""

import numpy as np
import pytest

from oibar.calib import handeye, refine, timing
from oibar.geometry.rotations import matrix_to_quat, quat_to_matrix
from oibar.geometry.transforms import T_from_vec, adjoint, inv_T, log_T, pose_error
from oibar_hil.calib_synth import SynthConfig, T_target_cam_at, frame_times, mocap_samples


def test_quaternion_convention_matches_scipy():
    """oibar.geometry (the dataset's (w, x, y, z), w >= 0) against scipy's (x, y, z, w), which the
    toolbox used before the geometry core: same rotation, same sign rule, batched too."""
    from scipy.spatial.transform import Rotation

    R = T_from_vec(np.r_[0, 0, 0, 0.3, -1.2, 2.0])[:3, :3]
    q_scipy = Rotation.from_matrix(R).as_quat()[[3, 0, 1, 2]]
    assert np.allclose(matrix_to_quat(R), q_scipy if q_scipy[0] >= 0 else -q_scipy)
    assert np.allclose(
        quat_to_matrix(matrix_to_quat(R)), Rotation.from_quat(q_scipy[[1, 2, 3, 0]]).as_matrix()
    )
    Rs = Rotation.random(20, random_state=3)
    q = matrix_to_quat(Rs.as_matrix())
    assert q.shape == (20, 4) and np.all(q[:, 0] >= 0)
    assert np.allclose(quat_to_matrix(q), Rs.as_matrix())
    assert np.allclose(log_T(np.stack([np.eye(4)] * 3)), 0.0)
    rv = Rs.as_rotvec()
    assert np.allclose(np.stack([T_from_vec(np.r_[0, 0, 0, v])[:3, :3] for v in rv]), Rs.as_matrix())


def test_adjoint_moves_a_right_perturbation_to_the_left():
    T = T_from_vec(np.r_[0.3, -0.2, 1.0, 0.4, 0.1, -0.7])
    d = np.r_[1e-4, -2e-4, 3e-4, 2e-4, 1e-4, -1e-4]
    lhs = T @ T_from_vec(d)
    rhs = T_from_vec(adjoint(T) @ d) @ T
    assert np.allclose(lhs, rhs, atol=1e-7)


def test_interpolation_and_gaps():
    t = np.array([0.0, 0.01, 0.02, 0.10])
    T = np.stack([T_from_vec(np.r_[k, 0, 0, 0, 0, 0.1 * k]) for k in range(4)])
    tr = timing.Track("a", t, T)
    out, valid, k = timing.interpolate(tr, np.array([0.005, 0.05, -1.0]), with_variance=True)
    assert valid.tolist() == [True, False, False]
    assert out[0][0, 3] == pytest.approx(0.5) and np.degrees(np.arccos(out[0][0, 0])) == pytest.approx(
        np.degrees(0.05)
    )
    assert k[0] == pytest.approx(0.5)


def _exact_problem(n=60):
    cfg = SynthConfig(n_frames=n)
    t_f = frame_times(cfg)
    A = np.einsum(
        "nij,jk->nik", inv_T(T_target_cam_at(t_f + cfg.offset_s, cfg)), cfg.pattern.T_target_pattern
    )
    Z = inv_T(cfg.T_housing_cam)
    X = inv_T(cfg.T_tmarkers_target @ cfg.pattern.T_target_pattern)
    B = np.einsum("ij,njk,kl->nil", inv_T(Z), A, X)
    return A, B, X, Z


def test_closed_form_on_exact_data():
    A, B, X, Z = _exact_problem()
    X0, Z0 = handeye.closed_form(A, B)
    assert pose_error(X0, X)[0] < 1e-6 and pose_error(Z0, Z)[1] < 1e-5


def test_refinement_fixes_a_perturbed_start():
    A, B, X, Z = _exact_problem()
    n = len(A)
    B_at = lambda off: (B, np.ones(n, bool), np.ones(n), np.ones(n))  # noqa: E731
    noise = refine.MocapNoise()
    A_cov = np.tile(np.eye(6) * 1e-10, (n, 1, 1))
    res = refine.refine(
        A,
        A_cov,
        B_at,
        X @ T_from_vec(np.r_[0.01, 0, -0.01, 0.02, 0, 0.01]),
        Z @ T_from_vec(np.r_[-0.01, 0.02, 0, 0, 0.03, 0]),
        0.0,
        noise,
        noise,
    )
    assert pose_error(res.X, X)[0] < 1e-7 and pose_error(res.Z, Z)[1] < 1e-6
    assert np.all(np.abs(log_T(inv_T(res.Z) @ Z)) < 1e-7)


def test_offset_from_angular_speed():
    cfg = SynthConfig(n_frames=120)
    mo = mocap_samples(cfg)
    h, m = timing.Track("h", mo["t_s"], mo["housing"]), timing.Track("m", mo["t_s"], mo["tmarkers"])
    t_f = frame_times(cfg)
    A = inv_T(T_target_cam_at(t_f + cfg.offset_s, cfg))
    coarse = timing.offset_by_speed(t_f, A[:, :3, :3], h, m, 0.5)
    fine = timing.offset_by_handeye(t_f, A, h, m, coarse)
    assert abs(coarse - cfg.offset_s) < 0.05 and abs(fine - cfg.offset_s) < 0.005


def test_local_fit_of_the_mocap():
    """timing.smooth: exact on smooth motion, ~0.14 of one sample's noise variance wherever the
    query falls, smooth in the query time, and no fit across a gap."""
    cfg = SynthConfig(sigma_t_m=0.0, sigma_r_deg=0.0)
    mo = mocap_samples(cfg)
    tr = timing.Track("h", mo["t_s"], mo["housing"])
    tq = np.linspace(6.0, 20.0, 300) + 0.00371
    out, valid, k = timing.smooth(tr, tq, with_variance=True)
    lin, _ = timing.interpolate(tr, tq)
    assert valid.all() and k.min() > 0.13 and k.max() < 0.15
    errs = [pose_error(out[i], lin[i]) for i in range(len(tq))]
    # Interpolation is itself within 0.01 mm of the true motion here; the fit agrees with it.
    assert max(e[0] for e in errs) < 2e-5 and max(e[1] for e in errs) < 1e-3
    # Smooth in the query time with the reference samples fixed.
    a = timing.smooth(tr, tq, ref_t_s=tq)[0]
    b = timing.smooth(tr, tq + 1e-6, ref_t_s=tq)[0]
    assert np.max(np.abs(a - b)) < 1e-5
    keep = (mo["t_s"] < 8.0) | (mo["t_s"] > 8.2)
    gap = timing.Track("g", mo["t_s"][keep], mo["housing"][keep])
    _, v = timing.smooth(gap, np.array([7.9, 8.1, 8.3]))
    assert v.tolist() == [True, False, True]
