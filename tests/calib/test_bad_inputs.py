"""Bad inputs end in one clear line and exit status 2 (CLI) or a CalibError (library)."""

import shutil

import numpy as np
import pytest

from oibar.calib import handeye, io
from oibar.calib.errors import CalibError
from oibar.cli import main
from oibar.geometry.transforms import T_from_vec, inv_T, make_T
from oibar_hil.calib_synth import SynthConfig, T_target_cam_at, frame_times, mocap_samples, write_mocap_csv

GOOD_HEADER = "time_s,body,x_m,y_m,z_m,qw,qx,qy,qz\n"


def _cli_error(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()  # progress lines may come first
    errors = [ln for ln in err if ln.startswith("oibar: error: ")]
    assert len(errors) == 1 and err[-1] == errors[0] and "Traceback" not in "\n".join(err), err
    return errors[0]


@pytest.mark.parametrize(
    "text, message",
    [
        ("time_s,body,x_m,y_m,z_m,qx,qy,qz\n0,a,0,0,0,0,0,0\n", "no 'qw' column"),
        (GOOD_HEADER + "0.0,a,0,0,0,1,0,0,0\n0.01,a,0,zero,0,1,0,0,0\n", ":3: column 'y': not a number"),
        (GOOD_HEADER + "0.0,a,0,0,0,0.5,0,0,0\n", "quaternion norm"),
        (GOOD_HEADER + "0.0,a,0,0,0,1,0,0\n", "8 fields, the header has 9"),
        (GOOD_HEADER, "no samples"),
        ("", "empty file"),
        (GOOD_HEADER + "0.0,a,0,0,0,1,0,0,0\n0.0,a,0,0,0,1,0,0,0\n", "repeated time stamps"),
    ],
)
def test_malformed_mocap_csv(tmp_path, text, message):
    p = tmp_path / "m.csv"
    p.write_text(text)
    with pytest.raises(CalibError, match=message):
        io.read_mocap_csv(p)


def test_occluded_samples_are_dropped_and_mm_units(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text(
        GOOD_HEADER + "0.0,a,1000,0,0,1,0,0,0\n0.01,a,,,,,,,\n0.02,a,NaN,0,0,1,0,0,0\n"
        "0.03,a,2000,0,0,1,0,0,0\n"
    )
    tr = io.read_mocap_csv(p, "mm")["a"]
    assert list(tr.t_s) == [0.0, 0.03] and tr.T_mocap_body[1][0, 3] == pytest.approx(2.0)


def test_too_few_poses():
    T = np.stack([T_from_vec(np.r_[0, 0, 1, np.radians([5 * k, 3 * k, 0])]) for k in range(5)])
    with pytest.raises(CalibError, match="too few calibration poses: 5"):
        handeye.check_motion(T)


def test_pure_translation_is_degenerate():
    T = np.stack([make_T(np.eye(3), [0.1 * np.sin(k), 0.05 * k, 1.0]) for k in range(60)])
    with pytest.raises(CalibError, match="degenerate motion.*pure translation"):
        handeye.check_motion(T)


def test_rotation_about_one_axis_is_degenerate():
    rng = np.random.default_rng(0)
    T = np.stack(
        [T_from_vec(np.r_[0.1 * rng.normal(size=3), 0, np.radians(30 * np.sin(k / 5)), 0]) for k in range(60)]
    )
    with pytest.raises(CalibError, match="about one axis"):
        handeye.check_motion(T)


def test_good_motion_passes():
    cfg = SynthConfig(n_frames=100)
    spread = handeye.check_motion(inv_T(T_target_cam_at(frame_times(cfg), cfg)))
    assert spread["axis_spread"] > 0.5


def test_missing_frames(tmp_path, capsys):
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "000000.png").write_bytes(b"")
    (tmp_path / "frames.csv").write_text(
        "frame,file,time_s\n0,frames/000000.png,0.0\n1,frames/000001.png,0.1\n2,frames/000002.png,0.2\n"
    )
    with pytest.raises(CalibError, match="2 frame file\\(s\\) missing: frames/000001.png, frames/000002.png"):
        io.read_frames_csv(tmp_path / "frames.csv")
    (tmp_path / "m.csv").write_text(
        GOOD_HEADER + "0.0,h,0,0,0,1,0,0,0\n0.0,t,0,0,0,1,0,0,0\n0.1,h,0,0,0,1,0,0,0\n0.1,t,0,0,0,1,0,0,0\n"
    )
    (tmp_path / "p.json").write_text(
        '{"squares_x": 7, "squares_y": 5, "square_m": 0.065, "marker_m": 0.048,'
        ' "T_target_pattern": {"t_m": [0, 0, 0], "q_wxyz": [1, 0, 0, 0]}}'
    )
    line = _cli_error(
        capsys,
        [
            "calib",
            "estimate",
            "--mocap",
            str(tmp_path / "m.csv"),
            "--frames",
            str(tmp_path / "frames.csv"),
            "--pattern",
            str(tmp_path / "p.json"),
            "--housing-body",
            "h",
            "--target-body",
            "t",
            "-o",
            str(tmp_path / "c.json"),
        ],
    )
    assert "missing" in line


def test_frames_not_increasing(tmp_path):
    (tmp_path / "f.csv").write_text("frame,file,time_s\n0,a.png,0.2\n1,b.png,0.1\n")
    with pytest.raises(CalibError, match="must increase"):
        io.read_frames_csv(tmp_path / "f.csv", check_files=False)


def test_unknown_body_and_bad_json(tmp_path, capsys):
    cfg = SynthConfig(n_frames=20)
    write_mocap_csv(tmp_path / "m.csv", mocap_samples(cfg))
    (tmp_path / "f.csv").write_text("frame,file,time_s\n0,a.png,5.0\n")
    (tmp_path / "calib.json").write_text("{not json")
    line = _cli_error(
        capsys,
        [
            "calib",
            "apply",
            "--calib",
            str(tmp_path / "calib.json"),
            "--mocap",
            str(tmp_path / "m.csv"),
            "--frames",
            str(tmp_path / "f.csv"),
            "-o",
            str(tmp_path / "o.csv"),
        ],
    )
    assert "not valid JSON" in line
    with pytest.raises(CalibError, match="no rigid body 'camera' \\(found: housing, tmarkers\\)"):
        io.pick_tracks(io.read_mocap_csv(tmp_path / "m.csv"), "camera", "tmarkers", tmp_path / "m.csv")


def test_too_few_frames_with_the_pattern(recording, tmp_path, capsys):
    """A real recording cut to 6 frames: detection works, then a clear 'too few' error."""
    lines = (recording / "frames.csv").read_text().splitlines()
    shutil.copytree(recording / "frames", tmp_path / "frames")
    (tmp_path / "frames.csv").write_text("\n".join(lines[:7]) + "\n")
    line = _cli_error(
        capsys,
        [
            "calib",
            "estimate",
            "--mocap",
            str(recording / "mocap.csv"),
            "--frames",
            str(tmp_path / "frames.csv"),
            "--pattern",
            str(recording / "pattern.json"),
            "--housing-body",
            "housing",
            "--target-body",
            "tmarkers",
            "-o",
            str(tmp_path / "c.json"),
        ],
    )
    assert "too few calibration poses" in line


def test_apply_skips_frames_in_mocap_gaps(tmp_path, capsys):
    cfg = SynthConfig(n_frames=30)
    mo = mocap_samples(cfg)
    keep = (mo["t_s"] < 6.0) | (mo["t_s"] > 6.5)  # a 0.5 s occlusion of both bodies
    write_mocap_csv(tmp_path / "m.csv", {k: v[keep] for k, v in mo.items()})
    t_f = frame_times(cfg)
    (tmp_path / "f.csv").write_text(
        "frame,file,time_s\n" + "".join(f"{k},f{k}.png,{t}\n" for k, t in enumerate(t_f))
    )
    cal = {
        "housing_body": "housing",
        "target_body": "tmarkers",
        "offset_s": cfg.offset_s,
        "T_housing_cam": cfg.T_housing_cam,
        "T_tmarkers_target": cfg.T_tmarkers_target,
    }
    io.write_calibration(tmp_path / "c.json", cal)
    assert (
        main(
            [
                "calib",
                "apply",
                "--calib",
                str(tmp_path / "c.json"),
                "--mocap",
                str(tmp_path / "m.csv"),
                "--frames",
                str(tmp_path / "f.csv"),
                "-o",
                str(tmp_path / "o.csv"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    n_gap = int(np.sum((t_f + cfg.offset_s > 6.0 - 0.01) & (t_f + cfg.offset_s < 6.5 + 0.01)))
    assert f"{30 - n_gap} of 30 frames" in out and "without mocap coverage skipped" in out
