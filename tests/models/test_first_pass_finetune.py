"""The first pass's fine-tune (oibar_models.first_pass_finetune, issue 58 item 5): the shipped
direct model back into a trainable network that computes what the file computes, rolled frames
labelled alike, a few steps that lower the loss on their frames, and an export the flight code
opens as a first pass; bad inputs refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from models_helpers import CAMERA, SHIPPED_KP, write_sequence
from PIL import Image

from oibar_models.data import Sequence, load_sequence
from oibar_models.first_pass_finetune import (
    FirstPassError,
    LabFrames,
    main,
    parity,
    read_meta,
    recover,
    run,
)

SHIPPED_LITE = SHIPPED_KP.parent / "oibarnet_lite.onnx"


def test_the_shipped_first_pass_comes_back_as_the_network_the_file_computes():
    net, meta = recover(SHIPPED_LITE)
    w, h = meta["input_size_wh"]
    # frames unlike recover's own check: a dark one with a bright patch
    x = np.full((3, 3, h, w), 0.05, np.float32)
    x[:, :, 60:100, 100:160] = 0.8
    assert parity(SHIPPED_LITE, net, x) < 1e-4
    # and its batch norms are the folded identity (statistics fixed while it trains)
    bns = [m for m in net.modules() if m.__class__.__name__ == "BatchNorm2d"]
    assert bns and all(float(b.weight.detach().min()) == float(b.weight.detach().max()) == 1.0 for b in bns)


def test_a_file_that_is_not_a_first_pass_is_refused(tmp_path):
    with pytest.raises(FirstPassError, match="not a direct-model export"):
        read_meta(SHIPPED_KP)  # the keypoint network
    with pytest.raises(FirstPassError, match="not found"):
        recover(tmp_path / "missing.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not onnx")
    with pytest.raises(FirstPassError, match="not a readable ONNX"):
        recover(bad)


def one_dot_sequence(tmp_path: Path) -> Sequence:
    """One black frame with a bright dot where the fixture's origin projects."""
    T = np.array([0.4, -0.25, 3.0])
    u = CAMERA["fx_px"] * T[0] / T[2] + CAMERA["cx_px"]
    v = CAMERA["fy_px"] * T[1] / T[2] + CAMERA["cy_px"]
    img = np.zeros((CAMERA["height_px"], CAMERA["width_px"], 3), np.uint8)
    j, i = int(u), int(v)  # the pixel whose square holds (u, v) (pixel-corner convention)
    img[i - 4 : i + 5, j - 4 : j + 5] = 255
    Image.fromarray(img).save(tmp_path / "f.png")
    K = np.array([[CAMERA["fx_px"], 0, CAMERA["cx_px"]], [0, CAMERA["fy_px"], CAMERA["cy_px"]], [0, 0, 1.0]])
    return Sequence(
        "dot", tmp_path, ["f.png"], np.zeros(1), np.zeros(1, int), T[None], np.array([[1.0, 0, 0, 0]]),
        np.array([np.linalg.norm(T)]), K, CAMERA["width_px"], CAMERA["height_px"],
    )  # fmt: skip


def test_a_rolled_frame_and_its_label_roll_together(tmp_path):
    _, meta = read_meta(SHIPPED_LITE)
    frames = LabFrames([one_dot_sequence(tmp_path)], tuple(meta["input_size_wh"]), meta["camera"])
    K_in = np.asarray(meta["camera"]["K_input"], float)
    rng = np.random.default_rng(0)
    b = frames.batch(rng, 12, roll_share=1.0)
    moved = 0
    for img, T in zip(b["image"].numpy(), b["T_m"].numpy(), strict=True):
        # where the label projects, and where the rolled frame's dot is (continuous coordinates)
        u, v = K_in[0, 0] * T[0] / T[2] + K_in[0, 2], K_in[1, 1] * T[1] / T[2] + K_in[1, 2]
        lum = img.mean(0)
        ys, xs = np.nonzero(lum > 0.5 * lum.max())
        assert abs(xs.mean() + 0.5 - u) < 1.5 and abs(ys.mean() + 0.5 - v) < 1.5, (u, v, xs.mean(), ys.mean())
        moved += np.hypot(T[0] - 0.4, T[1] + 0.25) > 0.05
    assert moved >= 10  # the rolls were drawn over the whole turn, not left near zero


def test_a_few_steps_lower_the_loss_and_export_a_first_pass_the_flight_code_opens(tmp_path):
    import onnxruntime as ort

    from oibar.nav.pose import PoseEstimator, read_metadata

    write_sequence(tmp_path / "seq", 6, seed=5)
    out = tmp_path / "fp" / "oibarnet_lite.onnx"
    lines: list[str] = []
    info = run(SHIPPED_LITE, [tmp_path / "seq"], out, steps=40, lr=1e-3, seed=0, threads=2, log=lines.append)
    assert info["steps"] == 40 and info["frames"] == 6 and info["ships"] is False
    rows = [ln for ln in lines if ln.startswith("first pass step")]
    first, last = (float(r.split("position ")[1].split(" %")[0]) for r in (rows[0], rows[-1]))
    assert last < 0.7 * first, rows  # the training frames' position error fell
    est = PoseEstimator(out, warmup_runs=0)  # a direct model: the flight code's first pass
    assert est.__class__.__name__ == "PoseEstimator"
    meta, shipped = read_metadata(out), read_metadata(SHIPPED_LITE)
    assert meta["camera"] == shipped["camera"] and meta["input_size_wh"] == shipped["input_size_wh"]
    assert meta["finetune"]["steps"] == 40 and meta["model_version"].endswith("+finetune")
    # it reads the sequence's frames better than the file it started from (the same frames)
    seq = load_sequence(tmp_path / "seq")
    err = {}
    for path in (SHIPPED_LITE, out):
        e = PoseEstimator(path, warmup_runs=0)
        T_hat = np.array([e(np.asarray(Image.open(seq.dir / f).convert("RGB")))[0] for f in seq.files])
        err[path] = float(np.mean(np.linalg.norm(T_hat - seq.T_cam_target, axis=1) / seq.range_m))
    assert err[out] < err[SHIPPED_LITE], err
    # a dynamic batch, as the file it replaces
    w, h = meta["input_size_wh"]
    got = ort.InferenceSession(str(out)).run(None, {"image": np.zeros((3, 3, h, w), np.float32)})
    assert got[0].shape == (3, 3) and got[1].shape == (3, 4)


def test_bad_arguments_are_refused(tmp_path, capsys):
    base = ["--data", str(tmp_path), "--out", str(tmp_path / "x.onnx")]
    for argv in (
        ["--init", str(SHIPPED_LITE), *base, "--steps", "0"],
        ["--init", str(SHIPPED_LITE), *base, "--roll-share", "2"],
        ["--init", str(SHIPPED_LITE), *base, "--lr", "nan"],
    ):
        with pytest.raises(SystemExit) as exc:
            main([*argv, "--no-progress"])
        assert exc.value.code == 2
    assert main(["--init", str(tmp_path / "none.onnx"), *base, "--no-progress"]) == 2
    assert "not found" in capsys.readouterr().err
    # a folder that holds no sequence
    assert main(["--init", str(SHIPPED_LITE), *base, "--no-progress"]) == 2


def test_a_first_pass_without_a_keypoint_branch_comes_back_too(tmp_path):
    """Stage 1's shape (models/configs/oibarnet_lite_base.yaml: no keypoint branch), written by
    this module's own export, is recovered as that shape and computes what its file computes."""
    import torch

    from oibar_models.first_pass_finetune import export
    from oibar_models.nets import OibarNet

    torch.manual_seed(0)
    net = OibarNet("oibar_lite", 1.0, coord_channels=True, pos_param="uvlogz", keypoints=0).eval()
    with torch.no_grad():  # a trained look: heads not at their zero start
        net.head_t.weight.normal_(0.0, 0.01)
    path = export(net, SHIPPED_LITE, tmp_path / "base.onnx", {"note": "test"})
    back, meta = recover(path)
    assert back.keypoints == 0 and meta["finetune"] == {"note": "test"}
    x = np.random.default_rng(2).random((2, 3, 160, 248), dtype=np.float32)
    assert parity(path, back, x) < 1e-4
