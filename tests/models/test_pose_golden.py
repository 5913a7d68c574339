"""Golden vectors of the shipped estimator (tests/golden/pose, made by `python -m
oibar_models.golden_pose`): the post-processing between the ONNX files and the pose is pinned
with the networks' stored raw outputs fed back (no onnxruntime: no CPU-to-CPU rounding), and
onnxruntime on this machine is held to the stored outputs separately, more loosely."""

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from oibar.geometry.rotations import quat_to_matrix, rotation_angle_deg
from oibar.nav.pose import PoseEstimator
from oibar_models.golden_pose import FRAMES, estimate_frames, sessions

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = ROOT / "tests" / "golden" / "pose"
# onnxruntime's kernels differ by CPU (AVX-512 or AVX2 GEMM sum in other orders): on an AMD EPYC
# without AVX-512 (2026-12-03) the near network's keypoints came out up to 4.4e-3 crop px from the
# stored ones and a tracked 5 m pose 0.17 mm away. A model, graph or runtime change moves them by
# far more; the post-processing itself is pinned exactly by the replay test (no onnxruntime).
ORT_ATOL = 1e-2  # raw outputs: crop px for keypoints (the crop is 128 px), the heads' own units
ORT_POS_FRAC = 1e-4  # position: 0.01 % of range (the model's error is 0.25 %), 0.5 mm at 5 m


@pytest.fixture(scope="module")
def golden():
    meta = json.loads((GOLDEN / "golden.json").read_text())
    raw = dict(np.load(GOLDEN / "raw.npz"))
    frames = [np.asarray(Image.open(GOLDEN / f"{name}.png").convert("RGB")) for name, *_ in FRAMES]
    return meta, raw, frames


def _estimator():
    return PoseEstimator(ROOT / "models" / "oibarnet.onnx", threads=1, warmup_runs=0)


def test_the_golden_vectors_are_of_the_shipped_model(golden):
    from oibar_hil.sequence import sha256_file

    meta, _, _ = golden
    assert meta["model_sha256"] == sha256_file(ROOT / "models" / "oibarnet.onnx"), (
        "models/oibarnet.onnx changed: make its golden vectors again (python -m oibar_models.golden_pose)"
    )
    assert [p["frame"] for p in meta["poses"]] == [f[0] for f in FRAMES]


def test_the_stored_raw_outputs_give_the_stored_poses(golden):
    """Every network call is answered from the store, in each session's order, and its input
    checked against the stored one (within one grey level: a crop's resampling may round the
    other way on another CPU): the poses must come out to 1e-9."""
    meta, raw, frames = golden
    est = _estimator()
    used = {}
    for role, sess in sessions(est).items():
        used[role] = 0

        def replay(names, feed, role=role):
            i = used[role]
            used[role] += 1
            key = f"{role}{i}"
            assert f"{key}_in" in raw, f"the post-processing asks the {role} network more often than stored"
            (x,) = feed.values()
            x8 = np.rint(np.asarray(x) * 255.0).astype(np.int16)
            want = raw[f"{key}_in"].astype(np.int16)
            assert x8.shape == want.shape, f"{key}: fed {x8.shape}, stored {want.shape}"
            diff = np.abs(x8 - want)
            assert diff.max() <= 1 and (diff > 0).mean() < 0.01, (
                f"{key}: the post-processing feeds the {role} network other pixels than stored"
            )
            k = 0
            out = []
            while f"{key}_out{k}" in raw:
                out.append(raw[f"{key}_out{k}"])
                k += 1
            return out

        sess.run = replay
    poses = estimate_frames(est, frames)
    assert used == meta["calls"]
    for got, want in zip(poses, meta["poses"], strict=True):
        assert got["flags"] == want["flags"], got["frame"]
        assert np.allclose(got["T_cam_target_m"], want["T_cam_target_m"], rtol=0, atol=1e-9), got["frame"]
        assert np.allclose(got["q_cam_target"], want["q_cam_target"], rtol=0, atol=1e-9), got["frame"]
        assert got["confidence"] == pytest.approx(want["confidence"], abs=1e-9), got["frame"]


def test_onnxruntime_here_answers_as_stored(golden):
    """The networks themselves on this machine: each call's raw outputs within ORT_ATOL of the
    stored (keypoints in crop pixels, the heads' readings), the poses within ORT_POS_FRAC of the
    range and 0.01 deg."""
    meta, raw, frames = golden
    est = _estimator()
    seen = {}
    for role, sess in sessions(est).items():
        seen[role] = 0

        def checked(names, feed, role=role, run=sess.run):
            out = run(names, feed)
            i = seen[role]
            seen[role] += 1
            for k, v in enumerate(out):
                stored = raw.get(f"{role}{i}_out{k}")
                if stored is not None and stored.shape == np.shape(v):
                    assert np.allclose(v, stored, rtol=0, atol=ORT_ATOL), f"{role}{i}_out{k}"
            return out

        sess.run = checked
    poses = estimate_frames(est, frames)
    assert seen == meta["calls"]
    for got, want in zip(poses, meta["poses"], strict=True):
        range_m = float(np.linalg.norm(want["T_cam_target_m"]))
        assert np.allclose(
            got["T_cam_target_m"], want["T_cam_target_m"], rtol=0, atol=ORT_POS_FRAC * range_m
        ), got["frame"]
        turn = rotation_angle_deg(
            quat_to_matrix(np.array(got["q_cam_target"])).T @ quat_to_matrix(np.array(want["q_cam_target"]))
        )
        assert turn < 0.01, got["frame"]
