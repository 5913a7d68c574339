"""The BiLSTM temporal study (oibar_models.temporal) on the tiny synthetic dataset: one epoch per
head, output files and shapes, clips never crossing a sub-sequence boundary, sliding-window
assembly, and the CNN-alone path reproducing the CNN's own predictions."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from models_helpers import tiny_config

from oibar_models import temporal as tm
from oibar_models.data import PoseDataset, build_splits, open_sequences
from oibar_models.engine import load_checkpoint, predict, train

SETTINGS = dict(
    layers=(1, 2),
    hidden=8,
    clip_len=6,
    clip_stride=3,
    eval_stride=3,
    epochs=1,
    batch_size=4,
    feature_batch=16,
    threads=1,
)


@pytest.fixture(scope="module")
def study(tiny_dataset, tmp_path_factory):
    run = tmp_path_factory.mktemp("cnn_run")
    # one thread: two would oversubscribe the cores whenever anything else runs beside the tests
    cfg = tiny_config(
        tiny_dataset, run, epochs=1, max_steps_per_epoch=1, pos_loss="range_normalised", threads=1
    )
    train(cfg, progress=False, log=lambda *_: None)
    out = tmp_path_factory.mktemp("temporal")
    res = tm.run_study(
        cfg, run / "best.pt", out, tm.StudySettings(**SETTINGS), progress=False, log=lambda *_: None
    )
    return cfg, run, out, res


def test_study_writes_table_json_plot_and_predictions(study):
    cfg, run, out, res = study
    for f in (
        "temporal.md",
        "temporal.json",
        "seq01_temporal_errors.png",
        "predictions.npz",
        "bilstm_L1.pt",
        "bilstm_L2.pt",
    ):
        assert (out / f).is_file(), f
    assert json.loads((out / "temporal.json").read_text())["best_bilstm_on_val"] in ("BiLSTM-1", "BiLSTM-2")
    assert res["loss"] == "range_normalised"
    for model in ("CNN alone", tm.SMOOTHED, "BiLSTM-1", "BiLSTM-2"):
        for split in ("seq01", "val"):
            s = res["results"][model][split]
            assert np.isfinite(s["dt_mean_pct"]) and np.isfinite(s["dq_mean_deg"])
        assert res["results"][model]["seq01"]["frames"] == 48  # every test frame predicted once
    assert [len(h) for h in res["history"].values()] == [1, 1]
    pred = np.load(out / "predictions.npz")
    assert pred["seq01/BiLSTM-2/T_cam_target_m"].shape == (48, 3)
    assert pred["seq01/BiLSTM-2/rot6d"].shape == (48, 6)
    feats = sorted(out.glob("features_seq*_n48_ck*.npy"))
    assert len(feats) == 3 and np.load(feats[0]).shape == (48, 96)  # width 0.5: 96 features
    table = (out / "temporal.md").read_text()
    assert "| seq01 | CNN alone |" in table and "| val | BiLSTM-2 |" in table


def test_cnn_alone_path_reproduces_the_cnn(study, tiny_dataset):
    """Heads on the cached features == the CNN run on images through the ordinary loader."""
    cfg, run, out, _ = study
    net, _ = load_checkpoint(run / "best.pt")
    seq = open_sequences(tiny_dataset, ["seq01"])
    ds = PoseDataset(seq, [np.arange(48)], (93, 60), cfg.path(cfg.data.cache_dir))
    direct = predict(net, torch.utils.data.DataLoader(ds, batch_size=7), torch.device("cpu"))
    pred = np.load(out / "predictions.npz")
    np.testing.assert_allclose(pred["seq01/CNN alone/T_cam_target_m"], direct["T_hat"], atol=1e-5)
    q = tm.quats_from_rot6d(pred["seq01/CNN alone/rot6d"])
    np.testing.assert_allclose(np.abs(np.sum(q * direct["q_hat"], 1)), 1.0, atol=1e-5)


def test_clips_never_cross_a_subsequence_boundary(study):
    cfg, _, _, _ = study
    splits = build_splits(cfg)
    names = [s.name for s in splits.train.seqs]
    segs = tm.split_segments(
        splits.split_info, names, {"train": splits.train.items, "val": splits.val.items}, [48, 48]
    )
    assert sum(len(g.frames) for g in segs) == 96  # every frame in exactly one segment
    clips = tm.make_clips([g for g in segs if g.split == "train"], 6, 3)
    assert len(clips)
    for row in clips:
        seg = segs[[i for i, g in enumerate(segs) if g.split == "train"][row[0]]]
        a, b = splits.split_info[names[seg.seq]]["chunks"][seg.chunk]
        frames = row[2:]
        assert row[1] == seg.seq and seg.split == "train"
        assert np.all(np.diff(frames) == 1) and a <= frames[0] and frames[-1] < b


def test_clip_builder_on_a_known_split():
    info = {"seqA": {"chunks": [[0, 8], [8, 20], [20, 24], [24, 40]], "val_chunks": [1]}}
    all_frames = np.arange(40)
    val = (all_frames >= 8) & (all_frames < 20)
    items = {
        "train": np.stack([np.zeros(28, int), all_frames[~val]], 1),
        "val": np.stack([np.zeros(12, int), all_frames[val]], 1),
    }
    segs = tm.split_segments(info, ["seqA"], items, [40])
    assert [(g.split, g.frames[0], g.frames[-1]) for g in segs] == [
        ("train", 0, 7),
        ("val", 8, 19),
        ("train", 20, 23),
        ("train", 24, 39),
    ]
    train = [g for g in segs if g.split == "train"]
    clips = tm.make_clips(train, 6, 4)
    # chunk [20, 24) is shorter than a clip: no clip; [0, 8) and [24, 40) end flush
    starts = [int(r[2]) for r in clips]
    assert starts == [0, 2, 24, 28, 32, 34]
    # the train chunks [0, 8) and [20, 24) are not adjacent, but [20, 24) and [24, 40) are:
    # still no clip may join them
    assert not any(r[2] < 24 <= r[-1] for r in clips)


def test_sliding_windows_predict_each_frame_once_from_its_most_central_window():
    n, L, stride = 23, 6, 4
    starts = tm.window_starts(n, L, stride)
    assert list(starts) == [0, 4, 8, 12, 16, 17]
    w = tm.nearest_window(n, starts, L)
    pos = np.arange(n) - starts[w]
    assert np.all((pos >= 0) & (pos < L))
    centres = starts + (L - 1) / 2
    assert np.all(np.abs(np.arange(n) - centres[w]) <= np.abs(np.arange(n)[:, None] - centres).min(1))
    assert list(tm.window_starts(4, L, stride)) == [0]  # shorter than a window: one window


def test_moving_average_control_is_centred_and_truncated_at_the_ends():
    x = np.arange(10, dtype=float)[:, None] * np.ones((1, 3))
    y = tm.moving_average(x, 4)  # window [k - 1, k + 2]
    assert y.shape == (10, 3)
    np.testing.assert_allclose(y[:, 0], [1.0, 1.5, 2.5, 3.5, 4.5, 5.5, 6.5, 7.5, 8.0, 8.5])
    np.testing.assert_allclose(tm.moving_average(np.full((5, 6), 2.0), 32), 2.0)


def test_bilstm_sequence_prediction_matches_a_single_clip(study):
    _, run, out, _ = study
    cnn, _ = load_checkpoint(run / "best.pt")
    ck = torch.load(out / "bilstm_L1.pt", weights_only=False)
    head = tm.TemporalHead(cnn.feature_dim, 1, 8, np.zeros(96), np.ones(96), np.zeros(6))
    head.load_state_dict(ck["state_dict"])
    f = np.random.default_rng(0).random((6, 96)).astype(np.float32)
    T, r6 = tm.predict_sequence_bilstm(head, cnn, f, 6, 3)
    with torch.no_grad():
        T1, r1 = tm.predict_clips(head.eval(), cnn, torch.from_numpy(f)[None])
    np.testing.assert_allclose(T, T1[0].numpy(), atol=1e-6)
    np.testing.assert_allclose(r6, r1[0].numpy(), atol=1e-6)


def test_rerun_reuses_cached_features(study):
    cfg, run, out, _ = study
    res = tm.run_study(
        cfg,
        run / "best.pt",
        out,
        tm.StudySettings(**(SETTINGS | {"layers": (1,)})),
        progress=False,
        log=lambda *_: None,
    )
    assert res["timing_s"]["features_reused"] is True


def test_checkpoint_with_another_split_is_refused(study, tiny_dataset, tmp_path):
    _, run, _, _ = study
    other = tiny_config(tiny_dataset, tmp_path, epochs=1)
    other.data.split_seed = 7
    with pytest.raises(tm.StudyError, match="split_seed"):
        tm.run_study(other, run / "best.pt", tmp_path / "t", tm.StudySettings(**SETTINGS), progress=False)


def test_progress_in_a_log_has_no_carriage_returns(tiny_dataset, tmp_path, capsys):
    """Training and the study with their progress on: in a log (stderr is no terminal here)
    plain lines, never the carriage-return redraws a terminal gets."""
    cfg = tiny_config(tiny_dataset, tmp_path / "run", epochs=1, max_steps_per_epoch=2, threads=1)
    train(cfg, progress=True, log=lambda *_: None)
    tm.run_study(
        cfg,
        tmp_path / "run" / "best.pt",
        tmp_path / "t",
        tm.StudySettings(**(SETTINGS | {"layers": (1,)})),
        progress=True,
        log=lambda *_: None,
    )
    err = capsys.readouterr().err
    assert "\r" not in err
    assert "epoch 1/1: 2/2 batch (100%)" in err and "BiLSTM-1 epoch 1/1:" in err
