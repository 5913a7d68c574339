"""`oibar calib to-dataset`: a labelled lab recording becomes one sequence in the data set
generator's layout, read back unchanged by the loaders, its poses the labels; bad input refused
with one line and exit status 2, nothing half-written left behind."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from oibar.calib import io
from oibar.calib.dataset import sha256_file
from oibar.cli import main
from oibar.geometry.rotations import matrix_to_quat
from oibar_hil.calib_synth import SynthConfig, truth, write_recording

N_FRAMES = 6


def _cli_error(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    errors = [ln for ln in err if ln.startswith("oibar: error: ")]
    assert len(errors) == 1 and "Traceback" not in "\n".join(err), err
    return errors[0]


def _write_calibration(path: Path, cfg: SynthConfig, intrinsics: str = "oibar default") -> None:
    """The calibration `estimate` would write, at the recording's true transforms."""
    tr = truth(cfg)
    path.write_text(
        json.dumps(
            {
                "format": io.CALIB_FORMAT,
                "housing_body": "housing",
                "target_body": "tmarkers",
                "T_housing_cam": tr["T_housing_cam"],
                "T_tmarkers_target": tr["T_tmarkers_target"],
                "offset_s": cfg.offset_s,
                "settings": {"intrinsics": intrinsics},
            }
        )
    )


@pytest.fixture(scope="module")
def labelled(tmp_path_factory) -> Path:
    """A synthetic recording (calib_synth's mocap and frame index; frames drawn here, no GL),
    its calibration and the labels `oibar calib apply` wrote for it."""
    rec = tmp_path_factory.mktemp("lab_rec")
    cfg = SynthConfig(n_frames=N_FRAMES, seed=3)
    write_recording(rec, cfg, images=False)
    rng = np.random.default_rng(0)
    for k in range(N_FRAMES):
        img = rng.integers(0, 255, (480, 744, 3), dtype=np.uint8)
        cv2.imwrite(str(rec / "frames" / f"{k:06d}.png"), img)
    _write_calibration(rec / "calib.json", cfg)
    argv = ["calib", "apply", "--calib", str(rec / "calib.json"), "--mocap", str(rec / "mocap.csv")]
    assert main([*argv, "--frames", str(rec / "frames.csv"), "-o", str(rec / "poses.csv")]) == 0
    return rec


def _copy(rec: Path, dst: Path) -> Path:
    shutil.copytree(rec, dst)
    return dst


def test_the_sequence_reads_back_with_the_labels_as_poses(labelled, tmp_path, capsys):
    from oibar_hil.sequence import read_manifest, verify_files
    from oibar_models.data import load_sequence

    out = tmp_path / "data" / "lab01"
    argv = ["calib", "to-dataset", str(labelled), "--calib", str(labelled / "calib.json"), "--out", str(out)]
    assert main(argv) == 0
    seq = load_sequence(out, verify_hashes=True)
    labels = io.read_poses_csv(labelled / "poses.csv")
    assert len(seq) == len(labels) == N_FRAMES
    T = np.stack([lb["T_cam_target"] for lb in labels])
    assert np.abs(seq.T_cam_target - T[:, :3, 3]).max() < 1e-9
    q = np.stack([matrix_to_quat(t[:3, :3]) for t in T])
    assert np.abs(seq.q_cam_target - q).max() < 1e-8
    frames = io.read_frames_csv(labelled / "frames.csv")
    assert np.allclose(seq.time_s, [f["time_s"] for f in frames], atol=1e-6)
    assert (seq.width_px, seq.height_px) == (744, 480) and seq.K[0, 2] == 372.0
    for f, name in zip(frames, seq.files, strict=True):  # the canonical camera: copied as they are
        assert (out / name).read_bytes() == f["path"].read_bytes()
    m = read_manifest(out)
    verify_files(out, m)
    assert m["source"] == "lab" and m["spec"]["kind"] == "lab_recording"
    assert m["lab"]["calibration_sha256"] == sha256_file(labelled / "calib.json")
    assert not m["lab"]["remapped_to_canonical"]
    with open(out / "poses.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert {r["phase_name"] for r in rows} == {"lab"} and {r["sun_cam_x"] for r in rows} == {""}
    # again: the same input, nothing written; the output left as it was
    capsys.readouterr()
    assert main(argv) == 0 and "already holds" in capsys.readouterr().out
    assert not list(out.parent.glob(".*partial"))


def test_a_camera_other_than_the_canonical_is_remapped_into_it(labelled, tmp_path):
    from oibar_models.data import load_sequence

    rec = _copy(labelled, tmp_path / "rec")
    lab_cam = {"width_px": 744, "height_px": 480, "fx_px": 600.0, "fy_px": 600.0, "cx_px": 370.0}
    (rec / "cam.json").write_text(json.dumps({**lab_cam, "cy_px": 241.0, "dist": [-0.05, 0.01, 0, 0, 0]}))
    _write_calibration(rec / "calib.json", SynthConfig(n_frames=N_FRAMES, seed=3), str(rec / "cam.json"))
    out = tmp_path / "data" / "lab02"
    assert main(["calib", "to-dataset", str(rec), "--calib", str(rec / "calib.json"), "--out", str(out)]) == 0
    m = json.loads((out / "manifest.json").read_text())
    assert m["lab"]["remapped_to_canonical"] and m["lab"]["camera"]["K_opencv"][0][0] == 600.0
    seq = load_sequence(out)
    assert seq.K[0, 0] == pytest.approx(583.333, abs=1e-3) and len(seq) == N_FRAMES
    assert cv2.imread(str(out / seq.files[0])).shape == (480, 744, 3)


def _drop_row(path: Path, k: int) -> None:
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(lines[: k + 1] + lines[k + 2 :]))


def test_bad_inputs_are_refused_and_nothing_is_left(labelled, tmp_path, capsys):
    def refused(rec: Path, message: str, *extra: str) -> None:
        out = tmp_path / "data" / rec.name
        argv = ["calib", "to-dataset", str(rec), "--calib", str(rec / "calib.json"), "--out", str(out)]
        assert message in _cli_error(capsys, [*argv, *extra])
        assert not out.exists() and not list(out.parent.glob(".*partial"))

    # a frame without a label (no mocap coverage): refused, or left out when asked
    rec = _copy(labelled, tmp_path / "unlabelled")
    _drop_row(rec / "poses.csv", 2)
    refused(rec, "1 of 6 frames of")
    out = tmp_path / "data" / "dropped"
    argv = ["calib", "to-dataset", str(rec), "--calib", str(rec / "calib.json"), "--out", str(out)]
    assert main([*argv, "--drop-unlabelled"]) == 0
    assert json.loads((out / "manifest.json").read_text())["frames"] == N_FRAMES - 1
    # a label with an empty pose
    rec = _copy(labelled, tmp_path / "nopose")
    text = (rec / "poses.csv").read_text().splitlines()
    cells = text[3].split(",")
    cells[6] = ""
    (rec / "poses.csv").write_text("\n".join([*text[:3], ",".join(cells), *text[4:]]) + "\n")
    refused(rec, "has no label")
    # a corrupt frame
    rec = _copy(labelled, tmp_path / "corrupt")
    (rec / "frames" / "000004.png").write_bytes(b"\x89PNG not really")
    refused(rec, "corrupt frame")
    # a corrupt label: not a unit quaternion
    rec = _copy(labelled, tmp_path / "quat")
    text = (rec / "poses.csv").read_text().splitlines()
    cells = text[1].split(",")
    cells[9] = "0.5"
    (rec / "poses.csv").write_text("\n".join([text[0], ",".join(cells), *text[2:]]) + "\n")
    refused(rec, "quaternion norm")
    # another camera than the calibration's, and frames of another size than the camera's
    rec = _copy(labelled, tmp_path / "camera")
    other = {
        "width_px": 744,
        "height_px": 480,
        "fx_px": 590.0,
        "fy_px": 590.0,
        "cx_px": 371.5,
        "cy_px": 239.5,
    }
    (rec / "other.json").write_text(json.dumps(other))
    refused(rec, "camera mismatch", "--intrinsics", str(rec / "other.json"))
    cv2.imwrite(str(rec / "frames" / "000001.png"), np.zeros((240, 372, 3), np.uint8))
    refused(rec, "camera mismatch: the frame is 372x240")
    # labels of another recording (times off)
    rec = _copy(labelled, tmp_path / "times")
    rows = (rec / "frames.csv").read_text().splitlines()
    head, t = rows[2].rsplit(",", 1)
    rows[2] = f"{head},{float(t) + 0.001:.6f}"
    (rec / "frames.csv").write_text("\n".join(rows) + "\n")
    refused(rec, "labels of another recording")
    # an output that holds something else is kept unless --force
    refused(labelled, "exists and holds another recording", "--out", str(tmp_path / "data" / "dropped"))
    assert (tmp_path / "data" / "dropped" / "manifest.json").is_file()
