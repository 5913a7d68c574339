"""The pose-estimation stage (oibar.nav.pose) against a tiny OibarNet exported here: same
answers as PyTorch, clear errors for bad model files and bad frames, the plausibility signal;
and the filter study end to end on a few frames."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from oibar.geometry.rotations import matrix_to_quat, rot_x, rot_y
from oibar.nav.pose import FrameError, ModelFileError, PoseEstimator, read_metadata, resize_frame

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

CAMERA = {
    "width_px": 744,
    "height_px": 480,
    "fx_px": 583.3333,
    "fy_px": 583.3333,
    "cx_px": 372.0,
    "cy_px": 240.0,
}
IN_W, IN_H = 93, 60  # 744x480 / 8: the camera's aspect


def tiny_net():
    from oibar_models.nets import OibarNet

    torch.manual_seed(0)
    net = OibarNet("oibar_lite", width=0.5, coord_channels=True, pos_mean_m=(0.0, 0.1, 5.0))
    with torch.no_grad():  # the heads start input-independent; make the outputs depend on the frame
        net.head_t.weight.normal_(0.0, 0.5)
        net.head_r.weight.normal_(0.0, 0.5)
    return net.eval()


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    from oibar_models.export import export_onnx

    net = tiny_net()
    ck = {
        "config": {
            "name": "tiny",
            "model": {"backbone": "oibar_lite", "input_width_px": IN_W, "input_height_px": IN_H},
        },
        "labels": {"mean_T_cam_target": [0.0, 0.1, 5.0], "mean_q_cam_target": [1.0, 0.0, 0.0, 0.0]},
        "camera": CAMERA,
    }
    path = export_onnx(net, ck, tmp_path_factory.mktemp("model") / "tiny.onnx", model_version="0.0.1")
    return path, net


@pytest.fixture(scope="module")
def est(model):
    return PoseEstimator(model[0], threads=1, warmup_runs=1)


def frames(n, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (480, 744, 3), dtype=np.uint8) for _ in range(n)]


def test_estimate_matches_pytorch(model, est):
    from oibar_models.nets import PoseOutputs

    _, net = model
    got = []
    for k, frame in enumerate(frames(3)):
        e = est.estimate(frame, t_s=1.5 + k)
        with torch.no_grad():
            # as in training: the shared resize, then uint8 / 255, channels first
            x = (
                torch.from_numpy(resize_frame(frame, (IN_W, IN_H)).copy()).permute(2, 0, 1)[None].float()
                / 255.0
            )
            t, q, R, _ = PoseOutputs(net)(x)
        np.testing.assert_allclose(e.T_cam_target_m, t[0].numpy(), atol=1e-4)
        np.testing.assert_allclose(e.q_cam_target, q[0].numpy(), atol=1e-4)
        np.testing.assert_allclose(e.R_cam_target, R[0].numpy(), atol=1e-4)
        np.testing.assert_allclose(matrix_to_quat(e.R_cam_target), e.q_cam_target, atol=1e-4)
        assert e.t_s == 1.5 + k and e.latency_ms > 0 and 0.0 <= e.confidence <= 1.0
        assert e.T_cam_target_m.shape == (3,) and e.R_cam_target.shape == (3, 3) and e.finite
        got.append(e.T_cam_target_m)
    # the comparison means something only if the outputs depend on the frame
    assert np.abs(got[0] - got[1]).max() > 1e-3


def test_frame_already_at_input_size_gives_the_same_answer(est):
    frame = frames(1, seed=4)[0]
    small = resize_frame(frame, (IN_W, IN_H))
    np.testing.assert_allclose(
        est.estimate(small).T_cam_target_m, est.estimate(frame).T_cam_target_m, atol=1e-6
    )


def test_metadata_drives_the_runtime(est):
    assert est.size_wh == (IN_W, IN_H) and est.frame_wh == (744, 480)
    assert est.meta["model_version"] == "0.0.1"
    assert est.range_limits_m == (0.2, 20.0)  # no train_range_m in this export: the documented default


@pytest.mark.parametrize(
    "frame, match",
    [
        (np.zeros((480, 744), np.uint8), "shape"),
        (np.zeros((480, 744, 4), np.uint8), "shape"),
        (np.zeros((480, 744, 3), np.float32), "dtype"),
        (np.full((480, 744, 3), np.nan, np.float32), "NaN"),
        (np.zeros((480, 480, 3), np.uint8), "aspect"),
        (np.zeros((744, 480, 3), np.uint8), "aspect"),  # rotated
        (np.zeros((30, 47, 3), np.uint8), "smaller than the network input"),
        (np.zeros((0, 0, 3), np.uint8), "smaller"),
        ([[0, 0, 0]], "numpy array"),
    ],
)
def test_malformed_frames_raise_frame_error(est, frame, match):
    with pytest.raises(FrameError, match=match) as info:
        est.estimate(frame)
    assert isinstance(info.value, ValueError)  # the daemon catches ValueError-derived errors


def test_non_finite_frame_time_is_a_frame_error(est):
    with pytest.raises(FrameError, match="t_s"):
        est.estimate(frames(1)[0], t_s=float("nan"))


def test_bad_model_files_raise_model_file_error(model, tmp_path):
    import onnx
    from onnx import TensorProto, helper

    good = model[0].read_bytes()
    with pytest.raises(ModelFileError, match="model file not found"):
        PoseEstimator(tmp_path / "absent.onnx")
    cases = {
        "random.onnx": np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8).tobytes(),
        "truncated.onnx": good[: len(good) // 2],
        "empty.onnx": b"",
    }
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(ModelFileError, match=f"{name}: not a readable ONNX model"):
            PoseEstimator(tmp_path / name)
    m = onnx.load(str(model[0]))
    del m.metadata_props[:]
    onnx.save(m, str(tmp_path / "bare.onnx"))
    with pytest.raises(ModelFileError, match="no OibarNet metadata"):
        PoseEstimator(tmp_path / "bare.onnx")
    # metadata present but not OibarNet's outputs
    g = helper.make_graph(
        [helper.make_node("Identity", ["image"], ["out"])],
        "g",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, IN_H, IN_W])],
        [helper.make_tensor_value_info("out", TensorProto.FLOAT, [1, 3, IN_H, IN_W])],
    )
    other = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    p = other.metadata_props.add()
    p.key, p.value = "oibar.input_size_wh", json.dumps([IN_W, IN_H])
    onnx.save(other, str(tmp_path / "other.onnx"))
    with pytest.raises(ModelFileError, match="outputs .*position_m.* missing"):
        PoseEstimator(tmp_path / "other.onnx")
    p.value = "[93, "
    onnx.save(other, str(tmp_path / "badjson.onnx"))
    with pytest.raises(ModelFileError, match="not valid JSON"):
        read_metadata(tmp_path / "badjson.onnx")


def _r6(R):
    return np.concatenate([R[:, 0], R[:, 1]])


def test_plausibility_flags_impossible_and_unusual_outputs(est):
    R = rot_x(0.02) @ rot_y(-0.03)
    T = np.array([0.05, 0.1, 4.0])
    conf, rng_m, defect, flags = est.plausibility(T, R, _r6(R))
    assert conf == pytest.approx(1.0) and flags == () and rng_m == pytest.approx(np.linalg.norm(T))
    # a raw 6D off orthonormal: lower confidence, growing with the defect
    c_small = est.plausibility(T, R, _r6(R) + np.array([0, 0, 0, 0.01, 0, 0]))[0]
    c_big = est.plausibility(T, R, _r6(R) * 1.1)[0]
    assert 1.0 > c_small > c_big and "ortho_defect" in est.plausibility(T, R, _r6(R) * 1.1)[3]
    assert est.plausibility(np.array([0.0, 0.1, -1.0]), R, _r6(R))[0] == 0.0  # behind the camera
    conf, _, _, flags = est.plausibility(np.array([0.0, 0.1, 50.0]), R, _r6(R))  # beyond training
    assert conf == pytest.approx(0.2) and "out_of_range" in flags
    conf, _, _, flags = est.plausibility(np.array([3.0, 0.0, 2.0]), R, _r6(R))  # outside the image
    assert conf == pytest.approx(0.2) and "out_of_view" in flags
    conf, *_, flags = est.plausibility(np.array([np.nan, 0, 1.0]), R, _r6(R))
    assert conf == 0.0 and flags == ("non_finite",)


def test_constructor_arguments_are_checked(model):
    with pytest.raises(ValueError, match="threads"):
        PoseEstimator(model[0], threads=0)
    with pytest.raises(ValueError, match="range_limits_m"):
        PoseEstimator(model[0], range_limits_m=(5.0, 1.0))


def test_models_package_uses_this_runtime():
    from oibar_models import infer

    assert infer.OnnxPoseEstimator is PoseEstimator and infer.ModelFileError is ModelFileError
    assert infer.resize_frame is resize_frame


def test_filter_study_end_to_end(model, tmp_path):
    """Four frames of a sequence (random pixels: the tiny net is untrained) through the study."""
    from PIL import Image

    from oibar_models import filter_study  # a study: it lives with the models, not in flight code

    seq = tmp_path / "data" / "seq01"
    (seq / "frames").mkdir(parents=True)
    with open(seq / "poses.csv", "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(
            ["frame", "file", "time_s", "phase", "tx_m", "ty_m", "tz_m", "qw", "qx", "qy", "qz", "range_m"]
        )
        for k, frame in enumerate(frames(4, seed=9)):
            name = f"frames/{k:06d}.jpg"
            Image.fromarray(frame).save(seq / name, quality=90)
            w.writerow([k, name, f"{0.1 * k:.1f}", 2, 0.0, 0.1, 5.0 - 0.01 * k, 1, 0, 0, 0, 5.0])
    (seq / "frames" / "000002.jpg").write_bytes(b"broken")  # a bad frame is skipped, not fatal
    out = tmp_path / "out"
    assert (
        filter_study.main(
            [
                "--model",
                str(model[0]),
                "--data",
                str(tmp_path / "data"),
                "--seqs",
                "1",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    res = json.loads((out / "filter_study.json").read_text())
    s = res["sequences"]["seq01"]
    assert s["frames"] == 4 and s["scored_frames"] == 3 and len(s["frame_errors"]) == 1
    assert s["filter_counts"]["initialised"] == 1
    assert "| seq01 | raw |" in (out / "filter_study.md").read_text()
    assert (out / "seq01_filter.png").stat().st_size > 1000
    assert (
        filter_study.main(
            [
                "--model",
                str(tmp_path / "nope.onnx"),
                "--data",
                str(tmp_path / "data"),
                "--seqs",
                "1",
                "--out",
                str(tmp_path / "o2"),
                "--no-progress",
            ]
        )
        == 2
    )
    assert not (tmp_path / "o2").exists()
