"""oibar_models.rolled: a sequence as the camera rolled about its boresight sees it. The labels
turn with the frames: the fixture drawn afresh at a rolled frame's label (models_helpers.draw_frame,
the plate a bright polygon) covers the plate of the turned frame."""

from __future__ import annotations

import json

import numpy as np
import pytest
from models_helpers import draw_frame, write_sequence
from PIL import Image

from oibar.geometry.rotations import quat_to_matrix
from oibar_models.data import load_sequence
from oibar_models.rolled import main, roll_sequence


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    d = tmp_path_factory.mktemp("seq") / "s000"
    write_sequence(d, 3, seed=5)
    return d


def _plate(img: np.ndarray) -> np.ndarray:
    """The drawn plate's pixels (grey 180 on a background of ~12)."""
    return np.asarray(img).astype(int).sum(axis=2) > 3 * 100


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


@pytest.mark.parametrize("roll_deg", [90.0, -35.0, 180.0])
def test_the_labels_turn_with_the_frames(seq, tmp_path, roll_deg):
    src = load_sequence(seq)
    out = roll_sequence(seq, tmp_path / f"r{roll_deg:g}", roll_deg)
    rolled = load_sequence(out, verify_hashes=True)
    assert rolled.files == src.files and np.allclose(rolled.range_m, src.range_m)
    for k in range(len(src.files)):
        # the pose turned about the boresight: the same range, the attitude turned by the roll
        assert np.linalg.norm(rolled.T_cam_target[k]) == pytest.approx(
            np.linalg.norm(src.T_cam_target[k]), abs=2e-6
        )
        R0, R1 = quat_to_matrix(src.q_cam_target[k]), quat_to_matrix(rolled.q_cam_target[k])
        turn = np.degrees(np.arctan2((R1 @ R0.T)[1, 0], (R1 @ R0.T)[0, 0]))
        assert abs((turn - roll_deg + 180.0) % 360.0 - 180.0) < 1e-4
        turned = _plate(Image.open(out / rolled.files[k]).convert("RGB"))
        drawn = _plate(draw_frame(rolled.T_cam_target[k], rolled.q_cam_target[k], np.random.default_rng(0)))
        assert drawn.sum() > 200 and _iou(turned, drawn) > 0.8, (k, _iou(turned, drawn))
    meta = json.loads((out / "manifest.json").read_text())["rolled"]
    assert meta["roll_deg"] == roll_deg


def test_the_unturned_label_does_not_fit_a_turned_frame(seq, tmp_path):
    """The check above can fail: a quarter turn's frame against the source's own label."""
    src = load_sequence(seq)
    out = roll_sequence(seq, tmp_path / "q", 90.0)
    turned = _plate(Image.open(out / src.files[0]).convert("RGB"))
    drawn = _plate(draw_frame(src.T_cam_target[0], src.q_cam_target[0], np.random.default_rng(0)))
    assert _iou(turned, drawn) < 0.5


def test_bad_arguments_and_an_existing_sequence_are_refused(seq, tmp_path, capsys):
    out = tmp_path / "o"
    assert main([str(seq), "--roll-deg", "45", "--out", str(out)]) == 0
    assert main([str(seq), "--roll-deg", "45", "--out", str(out)]) == 2  # a sequence is there
    assert "holds a sequence" in capsys.readouterr().err
    assert main([str(tmp_path / "nothing"), "--roll-deg", "45", "--out", str(tmp_path / "p")]) == 2
    with pytest.raises(SystemExit):
        main([str(seq), "--roll-deg", "nan", "--out", str(tmp_path / "n")])
