"""The far network (``oibar.far_network``, docs/model_history.md "Candidate 0.26.0"): a second
keypoint network of the same graph, beside the main one, reads every crop window whose head-on
range is its `from_m` or more. Built here from the shipped model and a copy of it whose weights
are nudged, so the two read the same crop differently and a wrong choice shows."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from models_helpers import one_network_copy


def _nudged_copy(src: Path, dst: Path, seed: int = 0) -> None:
    """`src` with every float weight scaled by 1 +- 2 %: the same graph and metadata, another network."""
    import onnx
    from onnx import numpy_helper

    m = onnx.load(str(src))
    rng = np.random.default_rng(seed)
    for init in m.graph.initializer:
        w = numpy_helper.to_array(init)
        if w.dtype == np.float32 and w.size > 1:
            init.CopyFrom(
                numpy_helper.from_array(
                    (w * (1 + 0.02 * rng.standard_normal(w.shape))).astype(np.float32), init.name
                )
            )
    onnx.save(m, str(dst))


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """(folder, main network alone, far network alone, the pair), the pair switching at 5 m."""
    from oibar.nav.pose import KeypointPoseEstimator
    from oibar_models.kp_export import main as export_main

    d = tmp_path_factory.mktemp("pair")
    one_network_copy(d)  # the shipped main network alone, whatever far network it ships with
    _nudged_copy(d / "oibarnet.onnx", d / "oibarnet_far.onnx")
    near = KeypointPoseEstimator(d / "oibarnet.onnx", warmup_runs=0)
    far = KeypointPoseEstimator(d / "oibarnet_far.onnx", warmup_runs=0)
    args = ["--retag", str(d / "oibarnet.onnx"), "--out", str(d / "pair.onnx")]
    assert export_main(args + ["--far-network", "oibarnet_far.onnx", "--far-from-m", "5"]) == 0
    return d, near, far, KeypointPoseEstimator(d / "pair.onnx", warmup_runs=1)


def _frame() -> np.ndarray:
    """A bright fixture-sized block on a dark, noisy frame: enough for the networks to answer."""
    rng = np.random.default_rng(3)
    img = rng.integers(0, 40, (480, 744, 3), np.uint8)
    img[200:280, 330:420] = 210
    return img


def test_each_window_is_read_by_the_network_for_its_range(pair):
    from oibar.nav.keypoints import CropWindow

    _, near, far, both = pair
    img = _frame()
    assert both.reader.far_from_m == 5.0
    read_far = read_near = 0
    for side_px in (40.0, 60.0, 72.0, 75.0, 120.0, 300.0):
        win = CropWindow((372.0, 240.0), side_px, both.reader.out_px)
        got, n, f = (
            both.reader.read_crop(img, win),
            near.reader.read_crop(img, win),
            far.reader.read_crop(img, win),
        )
        assert not np.allclose(n.present, f.present)  # the two networks do differ on this crop
        want = f if both.reader.range_for_side_m(side_px) >= 5.0 else n
        read_far += want is f
        read_near += want is n
        assert np.array_equal(got.present, want.present)
        assert np.array_equal(got.uv_px, want.uv_px, equal_nan=True)
    assert read_far >= 2 and read_near >= 2  # the sides straddle the switch


def test_a_batch_of_near_and_far_windows_is_split_and_put_back_in_order(pair):
    """The cold search scores windows of every size in one batch (_fixture_likeness): each row
    must come from its own window's network, in the order given."""
    from oibar.nav.keypoints import CropWindow

    _, near, far, both = pair
    img = _frame()
    wins = [
        CropWindow((372.0 + 20 * i, 240.0), s, both.reader.out_px)
        for i, s in enumerate((40.0, 300.0, 60.0, 200.0, 45.0))
    ]
    got = both.reader.fixture_likeness(img, wins)
    want = [(far if both.reader.reads_far(w) else near).reader.fixture_likeness(img, [w])[0] for w in wins]
    assert [both.reader.reads_far(w) for w in wins] == [True, False, True, False, True]
    assert np.allclose(got, want, rtol=1e-4, atol=1e-7)
    assert not np.allclose(got, near.reader.fixture_likeness(img, wins), rtol=1e-4, atol=1e-7)


def test_the_pair_estimates_a_whole_frame(pair):
    _, _, _, both = pair
    est = both.estimate(_frame())
    assert est.R_cam_target.shape == (3, 3) and np.isfinite(est.confidence)


def _retag_meta(src: Path, dst: Path, **meta) -> Path:
    import onnx

    m = onnx.load(str(src))
    props = {p.key: p.value for p in m.metadata_props}
    for k, v in meta.items():
        props["oibar." + k] = json.dumps(v)
    del m.metadata_props[:]
    for k, v in props.items():
        p = m.metadata_props.add()
        p.key, p.value = k, v
    onnx.save(m, str(dst))
    return dst


@pytest.mark.parametrize(
    "spec, match",
    [
        ({"file": "oibarnet_far.onnx", "from_m": 0}, "from_m"),
        ({"file": "oibarnet_far.onnx", "from_m": "far"}, "from_m"),
        ({"file": "oibarnet_far.onnx", "from_m": True}, "from_m"),
        ({"file": "oibarnet_far.onnx"}, "must be"),
        ("oibarnet_far.onnx", "must be"),
        ({"file": "gone.onnx", "from_m": 5}, "missing"),
        ({"file": "../pair/oibarnet_far.onnx", "from_m": 5}, "missing"),
        ({"file": "oibarnet_lite.onnx", "from_m": 5}, "not the same kind"),  # a direct model
        ({"file": "other_crop.onnx", "from_m": 5}, "oibar.crop differs"),
    ],
)
def test_a_far_network_the_main_tables_cannot_read_is_refused_at_load(pair, spec, match):
    from oibar.nav.pose import KeypointPoseEstimator, ModelFileError, read_metadata

    d = pair[0]
    crop = dict(read_metadata(d / "oibarnet.onnx")["crop"], margin=9.9)
    _retag_meta(d / "oibarnet_far.onnx", d / "other_crop.onnx", crop=crop)
    bad = _retag_meta(d / "oibarnet.onnx", d / "bad_pair.onnx", far_network=spec)
    with pytest.raises(ModelFileError, match=match):
        KeypointPoseEstimator(bad, warmup_runs=0)


def test_a_main_file_at_fault_is_named_for_its_own_fault_not_for_its_far_network(pair):
    """A paired file whose own table is malformed is refused for that table, naming itself: its
    far network, now unlike it, is not the file to blame (the far network opens last)."""
    from oibar.nav.pose import KeypointPoseEstimator, ModelFileError, read_metadata

    d = pair[0]
    head = dict(read_metadata(d / "pair.onnx")["attitude_head"], R_ref="not a rotation")
    bad = _retag_meta(d / "pair.onnx", d / "bad_head.onnx", attitude_head=head)
    with pytest.raises(ModelFileError, match="attitude_head") as exc:
        KeypointPoseEstimator(bad, warmup_runs=0)
    assert str(exc.value).startswith(str(bad)) and "not the same kind" not in str(exc.value)


def test_retag_pairs_only_with_a_file_beside_it_and_both_options(pair, tmp_path):
    from oibar.nav.pose import read_metadata
    from oibar_models.kp_export import main as export_main

    d = pair[0]
    base = ["--retag", str(d / "oibarnet.onnx")]
    assert (
        export_main(
            base
            + ["--out", str(tmp_path / "p.onnx"), "--far-network", "oibarnet_far.onnx", "--far-from-m", "5"]
        )
        == 2
    )
    assert not (tmp_path / "p.onnx").exists()  # the far file is not beside it there
    assert export_main(base + ["--out", str(d / "p2.onnx"), "--far-network", "oibarnet_far.onnx"]) == 2
    assert export_main(base + ["--out", str(d / "p2.onnx"), "--far-from-m", "5"]) == 2
    assert not (d / "p2.onnx").exists()
    assert export_main(["--config", "x.yaml", "--far-network", "oibarnet_far.onnx", "--far-from-m", "5"]) == 2
    assert read_metadata(d / "pair.onnx")["far_network"] == {"file": "oibarnet_far.onnx", "from_m": 5.0}
    assert "far_network" not in read_metadata(d / "oibarnet.onnx")


def test_the_looks_cache_tells_pairs_apart_by_their_far_network(pair, tmp_path):
    """The closed-loop study caches runs per model file: a pair whose far network changed is
    another model even though its main file did not."""
    from oibar_hil.rig.looks import model_tag

    d = pair[0]
    for name in ("pair.onnx", "oibarnet_far.onnx"):
        shutil.copy(d / name, tmp_path / name)
    first = model_tag(str(tmp_path / "pair.onnx"))
    assert model_tag(str(d / "pair.onnx")) == first
    _nudged_copy(d / "oibarnet_far.onnx", tmp_path / "oibarnet_far.onnx", seed=1)
    assert model_tag(str(tmp_path / "pair.onnx")) != first
