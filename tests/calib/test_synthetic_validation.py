"""End to end on a rendered recording with known transforms, through the `oibar` CLI:
estimate -> apply -> overlay. Tolerances from issue 9: 1 mm and 0.1 deg on both transforms."""

import csv
import json

import cv2
import numpy as np
import pytest

from oibar.calib import io
from oibar.calib.pnp import Detector, project
from oibar.cli import main
from oibar.dataset_format import POSES_COLUMNS
from oibar.geometry.rotations import rotation_angle_deg
from oibar.geometry.transforms import T_from_pose, inv_T, pose_error
from oibar_hil.calib_synth import SynthConfig, T_target_cam_at, frame_times


@pytest.fixture(scope="module")
def calib(recording, tmp_path_factory):
    out = tmp_path_factory.mktemp("calib_out") / "calib.json"
    rc = main(
        [
            "calib",
            "estimate",
            "--mocap",
            str(recording / "mocap.csv"),
            "--frames",
            str(recording / "frames.csv"),
            "--pattern",
            str(recording / "pattern.json"),
            "--intrinsics",
            str(recording / "intrinsics.json"),
            "--housing-body",
            "housing",
            "--target-body",
            "tmarkers",
            "-o",
            str(out),
        ]
    )
    assert rc == 0
    return json.loads(out.read_text()), out


def test_recovers_static_transforms(calib, truth, capsys):
    res, _ = calib
    figures = {}
    for key in ("T_housing_cam", "T_tmarkers_target"):
        T_est = T_from_pose(res[key]["t_m"], res[key]["q_wxyz"])
        T_true = T_from_pose(truth[key]["t_m"], truth[key]["q_wxyz"])
        dt_m, dr_deg = pose_error(T_est, T_true)
        figures[key] = (dt_m * 1e3, dr_deg)
    with capsys.disabled():
        print(
            f"\n[calib] poses used {res['poses']['used']}; "
            + "; ".join(f"{k}: {t:.3f} mm, {r:.4f} deg" for k, (t, r) in figures.items())
            + f"; offset {res['offset_s'] * 1e3:.2f} ms (true {truth['offset_s'] * 1e3:.2f});"
            f" chi2/dof {res['residuals']['chi2_per_dof']:.2f}"
        )
    for key, (t_mm, r_deg) in figures.items():
        assert t_mm < 1.0, f"{key}: translation error {t_mm:.3f} mm"
        assert r_deg < 0.1, f"{key}: rotation error {r_deg:.4f} deg"
    assert abs(res["offset_s"] - truth["offset_s"]) < 0.003
    assert res["poses"]["used"] >= 190
    assert 0.5 < res["residuals"]["chi2_per_dof"] < 2.0  # the stated noise matches the data


def _apply_errors(calib_path, recording, out, *extra):
    """`oibar calib apply` on the recording: its rows and each frame's position (m) and attitude
    (deg) error against the rig's truth."""
    argv = ["calib", "apply", "--calib", str(calib_path), "--mocap", str(recording / "mocap.csv")]
    assert main([*argv, "--frames", str(recording / "frames.csv"), "-o", str(out), *extra]) == 0
    with open(out, newline="") as fh:
        rows = list(csv.DictReader(fh))
    cfg = SynthConfig()
    T_true = inv_T(T_target_cam_at(frame_times(cfg) + cfg.offset_s, cfg))
    dt = [
        np.linalg.norm([float(r[k]) for k in ("tx_m", "ty_m", "tz_m")] - T_true[i][:3, 3])
        for i, r in enumerate(rows)
    ]
    dr = [
        rotation_angle_deg(
            T_from_pose([0, 0, 0], [float(r[k]) for k in ("qw", "qx", "qy", "qz")])[:3, :3].T
            @ T_true[i][:3, :3]
        )
        for i, r in enumerate(rows)
    ]
    return rows, np.array(dt), np.array(dr)


def test_apply_gives_time_aligned_ground_truth(calib, recording, truth, tmp_path):
    _, calib_path = calib
    rows, dt, dr = _apply_errors(calib_path, recording, tmp_path / "poses.csv")
    assert tuple(rows[0].keys()) == POSES_COLUMNS
    assert len(rows) == truth["n_frames"]
    times = frame_times(SynthConfig())
    assert all(abs(float(r["time_s"]) - t) < 1e-6 for r, t in zip(rows, times, strict=True))
    # Interpolated, a frame's label carries the noise of one or two mocap samples of two bodies
    # (0.5 deg each, ~1 m lever arm); the default local fit (+-0.1 s, ~19 samples) averages it down.
    _, dt_i, dr_i = _apply_errors(
        calib_path, recording, tmp_path / "interp.csv", "--smooth-half-width-s", "0"
    )
    assert np.median(dt_i) < 0.012 and np.median(dr_i) < 0.8
    assert np.median(dr) < 0.6 * np.median(dr_i) and np.median(dt) < 0.6 * np.median(dt_i)
    assert np.median(dr) < 0.4


@pytest.mark.parametrize("value", ["-0.1", "nan", "11"])
def test_apply_refuses_a_smoothing_window_out_of_range(calib, recording, tmp_path, capsys, value):
    _, calib_path = calib
    argv = ["calib", "apply", "--calib", str(calib_path), "--mocap", str(recording / "mocap.csv")]
    argv += ["--frames", str(recording / "frames.csv"), "-o", str(tmp_path / "p.csv")]
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--smooth-half-width-s", value])
    assert exc.value.code == 2
    assert "--smooth-half-width-s" in capsys.readouterr().err
    assert not (tmp_path / "p.csv").exists()


def test_overlay_draws_the_model(calib, recording, tmp_path):
    _, calib_path = calib
    poses = recording / "gt.csv"
    main(
        [
            "calib",
            "apply",
            "--calib",
            str(calib_path),
            "--mocap",
            str(recording / "mocap.csv"),
            "--frames",
            str(recording / "frames.csv"),
            "-o",
            str(poses),
        ]
    )
    assert main(["calib", "overlay", "--poses", str(poses), "--out", str(tmp_path), "--every", "100"]) == 0
    pngs = sorted(tmp_path.glob("overlay_*.png"))
    assert len(pngs) == 2
    raw = cv2.imread(str(recording / "frames" / "000000.png"))
    drawn = cv2.imread(str(pngs[0]))
    assert drawn.shape == raw.shape and np.count_nonzero(np.any(drawn != raw, axis=2)) > 2000


def test_charuco_corners_unbiased(recording):
    """Guards the re-refinement of OpenCV's ChArUco corners (+0.5 px in 4.13, opencv#25539)."""
    pattern, intr = (
        io.read_pattern(recording / "pattern.json"),
        io.read_intrinsics(recording / "intrinsics.json"),
    )
    det = Detector(pattern, intr)
    cfg = SynthConfig()
    T_tc = T_target_cam_at(frame_times(cfg) + cfg.offset_s, cfg)
    diffs = []
    for k in range(0, cfg.n_frames, 20):
        ids, uv = det.detect(cv2.imread(str(recording / "frames" / f"{k:06d}.png"), cv2.IMREAD_GRAYSCALE))
        uv_true = project(pattern.corners_pattern_m()[ids], inv_T(T_tc[k]) @ pattern.T_target_pattern, intr)
        diffs.append(uv - uv_true)
    d = np.concatenate(diffs)
    assert np.all(np.abs(d.mean(axis=0)) < 0.1), d.mean(axis=0)
    assert np.sqrt(np.mean(d**2)) < 0.4
