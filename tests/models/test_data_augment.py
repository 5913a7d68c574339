"""Dataset reading (and its errors), the paper's split, and label-consistent augmentation."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from models_helpers import CAMERA, tiny_config

from oibar.geometry.camera import intrinsics, rotation_homography, scale_intrinsics
from oibar.geometry.camera import project_camera_points as project_np
from oibar.geometry.rotations import quat_to_matrix as quat_to_matrix_np
from oibar.geometry.rotations import rot_x, rot_y, rot_z
from oibar_models.config import AugmentConfig
from oibar_models.data import (
    Augmenter,
    DatasetError,
    build_splits,
    load_frame,
    load_sequence,
    split_subsequences,
    warp_homography,
)


def test_reads_the_dataset_layout(tiny_dataset):
    s = load_sequence(tiny_dataset / "seq02")
    assert len(s) == 48 and s.T_cam_target.shape == (48, 3) and s.q_cam_target.shape == (48, 4)
    assert s.width_px == 744 and s.K[0, 2] == 372.0
    img = load_frame(s, 0, (93, 60))
    assert img.shape == (60, 93, 3) and img.dtype == np.uint8


def test_paper_split_by_subsequences():
    rng = np.random.default_rng(0)
    lengths = [64, 128, 256, 512, 1024]
    tr, va, chunks, val_chunks = split_subsequences(3600, lengths, 0.2, rng)
    assert sorted(np.concatenate([tr, va]).tolist()) == list(range(3600))  # disjoint, complete
    assert all((b - a) in lengths for a, b in chunks[:-1])  # the last one may be cut short
    assert 0.17 < len(va) / 3600 < 0.23
    starts = {a for a, _ in chunks}
    for i in val_chunks:  # whole sub-sequences only
        a, b = chunks[i]
        assert a in starts and set(range(a, b)) <= set(va.tolist())
    tr2, va2, _, _ = split_subsequences(3600, lengths, 0.2, np.random.default_rng(0))
    assert np.array_equal(va, va2)  # reproducible


def test_test_sequences_never_in_training(tiny_dataset, tmp_path):
    cfg = tiny_config(tiny_dataset, tmp_path / "run")
    sp = build_splits(cfg)
    assert {s.name for s in sp.train.seqs} == {"seq02", "seq03"}
    assert len(sp.train) + len(sp.val) == 96 and len(sp.val) > 0


def _dot_image(K, T, size_wh):
    """Black image with a small bright disc at the projection of T (sub-pixel centroid)."""
    w, h = size_wh
    uv = project_np(K, T[None])[0]
    yy, xx = np.mgrid[0:h, 0:w] + 0.5  # pixel centres, corner convention
    img = np.clip(255 * (1.5 - np.hypot(xx - uv[0], yy - uv[1]) / 2.0), 0, 255)
    return np.repeat(img[..., None], 3, 2).astype(np.uint8), uv


def _centroid(img):
    m = img[..., 0].astype(float)
    yy, xx = np.mgrid[0 : m.shape[0], 0 : m.shape[1]] + 0.5
    return np.array([(m * xx).sum() / m.sum(), (m * yy).sum() / m.sum()])


@pytest.mark.parametrize("angles_deg", [(20, 0, 0), (-15, 0, 0), (0, 4, -3), (10, -3, 4)])
def test_pose_augmentation_moves_image_and_label_together(angles_deg):
    size = (248, 160)
    K = scale_intrinsics(intrinsics(CAMERA["fx_px"], CAMERA["fy_px"], 372.0, 240.0), 248 / 744, 160 / 480)
    T = np.array([0.4, -0.25, 3.0])  # off-centre, so rotations move it
    R = rot_x(0.05)
    img, _ = _dot_image(K, T, size)
    roll, pitch, yaw = np.radians(angles_deg)
    R_aug = rot_z(roll) @ rot_x(pitch) @ rot_y(yaw)
    aug = Augmenter(AugmentConfig(), K, size)
    img2, T2, R2 = aug.pose(img, T, R, np.random.default_rng(0), R_aug=R_aug)
    np.testing.assert_allclose(T2, R_aug @ T)
    np.testing.assert_allclose(R2, R_aug @ R)
    # the fixture centre seen in the augmented image is where the augmented label projects
    np.testing.assert_allclose(_centroid(img2), project_np(K, T2[None])[0], atol=0.15)


def test_homography_of_a_pure_rotation_is_depth_independent():
    K = intrinsics(583.3, 583.3, 372.0, 240.0)
    R_aug = rot_z(0.2) @ rot_x(0.05)
    H = rotation_homography(K, R_aug)
    for depth in (0.5, 3.0, 10.0):
        p = np.array([0.3, -0.2, 1.0]) * depth
        x = H @ np.append(project_np(K, p[None])[0], 1.0)
        np.testing.assert_allclose(x[:2] / x[2], project_np(K, (R_aug @ p)[None])[0], atol=1e-9)


def test_random_augmentation_keeps_fixture_in_view_and_labels_valid(tiny_dataset, tmp_path):
    cfg = tiny_config(tiny_dataset, tmp_path / "run")
    sp = build_splits(cfg)
    ds = sp.train
    for i in range(0, len(ds), 7):
        item = ds[i]
        x = item["image"].numpy()
        assert x.shape == (3, 60, 93) and x.min() >= 0.0 and x.max() <= 1.0
        R = quat_to_matrix_np(item["q_cam_target"].numpy())
        np.testing.assert_allclose(R[:, 0], item["rot6d"].numpy()[:3], atol=1e-5)
        uv = project_np(sp.K_input, item["T_cam_target"].numpy()[None].astype(float))[0]
        assert 0 < uv[0] < 93 and 0 < uv[1] < 60
        assert float(item["range_m"]) == pytest.approx(np.linalg.norm(item["T_cam_target"].numpy()), rel=1e-5)


def test_photometric_augmentation_leaves_labels(tiny_dataset):
    K = intrinsics(583.3, 583.3, 372.0, 240.0)
    cfg = AugmentConfig(p_pose=0.0, p_photometric=1.0, p_blur=1.0)
    aug = Augmenter(cfg, K, (744, 480))
    img = np.full((480, 744, 3), 100, np.uint8)
    T, R = np.array([0.0, 0.1, 3.0]), np.eye(3)
    x, T2, R2 = aug(img, T, R, np.random.default_rng(1))
    assert x.dtype == np.float32 and not np.allclose(x, 100 / 255)
    assert np.array_equal(T2, T) and np.array_equal(R2, R)


def test_warp_identity_is_lossless():
    img = np.random.default_rng(0).integers(0, 255, (40, 60, 3), dtype=np.uint8)
    assert np.array_equal(warp_homography(img, np.eye(3)), img)


# ----------------------------------------------------------------------------- clear errors
def _copy(tiny_dataset, tmp_path, name="seq02"):
    d = tmp_path / name
    shutil.copytree(tiny_dataset / name, d)
    return d


def test_missing_dataset_folder(tmp_path):
    with pytest.raises(DatasetError, match="not found.*make dataset"):
        load_sequence(tmp_path / "seq05")


def test_missing_manifest_means_incomplete(tiny_dataset, tmp_path):
    d = _copy(tiny_dataset, tmp_path)
    (d / "manifest.json").unlink()
    with pytest.raises(DatasetError, match="manifest.json: missing.*incomplete"):
        load_sequence(d)


def test_corrupt_manifest(tiny_dataset, tmp_path):
    d = _copy(tiny_dataset, tmp_path)
    (d / "manifest.json").write_text("{not json")
    with pytest.raises(DatasetError, match="corrupt manifest"):
        load_sequence(d)


def test_truncated_pose_table(tiny_dataset, tmp_path):
    d = _copy(tiny_dataset, tmp_path)
    lines = (d / "poses.csv").read_text().splitlines()
    (d / "poses.csv").write_text("\n".join(lines[:-5]) + "\n")
    with pytest.raises(DatasetError, match=r"poses.csv: 43 rows but the manifest says 48"):
        load_sequence(d)


def test_garbage_in_pose_table(tiny_dataset, tmp_path):
    d = _copy(tiny_dataset, tmp_path)
    text = (d / "poses.csv").read_text().replace(",2,forced_translation,", ",x,forced_translation,", 1)
    (d / "poses.csv").write_text(text)
    with pytest.raises(DatasetError, match="non-numeric"):
        load_sequence(d)


def test_corrupt_and_missing_frames_are_named(tiny_dataset, tmp_path):
    d = _copy(tiny_dataset, tmp_path)
    s = load_sequence(d)
    (d / s.files[3]).write_bytes(b"\xff\xd8 not a jpeg")
    with pytest.raises(DatasetError, match="000003.jpg: cannot decode"):
        load_frame(s, 3, (93, 60))
    (d / s.files[4]).unlink()
    with pytest.raises(DatasetError, match="000004.jpg: frame file missing"):
        load_frame(s, 4, (93, 60))
    with pytest.raises(DatasetError, match="bad file"):
        load_sequence(d, verify_hashes=True)


def test_manifest_camera_drives_intrinsics(tiny_dataset, tmp_path):
    d = _copy(tiny_dataset, tmp_path)
    m = json.loads((d / "manifest.json").read_text())
    m["config"]["camera"]["cx_px"] = 371.5
    (d / "manifest.json").write_text(json.dumps(m))
    assert load_sequence(d).K[0, 2] == 371.5


def test_warp_leaves_no_black_band_that_would_give_the_shift_away():
    # a bright frame (the station filling the view at close range) shifted sideways: the
    # uncovered strip must not be black, or the network learns the band instead of the fixture
    rng = np.random.default_rng(3)
    img = (150 + rng.integers(0, 60, (60, 93, 3))).astype(np.uint8)
    H = np.array([[1.0, 0.0, 12.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # 12 px to the right
    out = warp_homography(img, H)
    assert out[:, :12].min() > 100, "the uncovered strip is filled from the image"
    assert np.array_equal(out[:, 20:60], img[:, 8:48]), "the rest is the shifted image"
    black = warp_homography(img, H, border="black")
    assert black[:, :11].max() == 0
