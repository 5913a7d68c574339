"""Camera sources and the LatestFrame wrapper (issue 8, item 1)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from oibar.camera import (  # noqa: E402
    CallableSource,
    CameraError,
    CameraLost,
    CameraOpenError,
    DeviceSource,
    EmptySource,
    EndOfStream,
    FolderSource,
    LatestFrame,
    SourceNotFound,
    SourceUnreadable,
    VideoFileSource,
    open_source,
)

H, W = 48, 64


def _img(k: int) -> np.ndarray:
    """RGB image whose red channel encodes k (survives PNG exactly, JPEG/MJPG roughly)."""
    img = np.zeros((H, W, 3), np.uint8)
    img[:, :, 0] = (k * 20) % 256
    img[:, :, 2] = 200
    return img


def _write_png(path, k):
    assert cv2.imwrite(str(path), cv2.cvtColor(_img(k), cv2.COLOR_RGB2BGR))


# --- folder --------------------------------------------------------------------------------
def test_folder_natural_order_and_nominal_rate(tmp_path):
    for k in (10, 2, 1, 0):
        _write_png(tmp_path / f"f{k}.png", k)
    (tmp_path / "notes.txt").write_text("ignored")
    with FolderSource(tmp_path, rate_hz=5.0) as src:
        frames = list(src)
    assert [f.seq for f in frames] == [0, 1, 2, 3]
    assert [f.t_s for f in frames] == pytest.approx([0.0, 0.2, 0.4, 0.6])
    assert [int(f.image[0, 0, 0]) for f in frames] == [0, 20, 40, 200]  # f0, f1, f2, f10; RGB order
    assert frames[0].image.shape == (H, W, 3) and frames[0].image.dtype == np.uint8
    assert all(b.t_host >= a.t_host for a, b in zip(frames, frames[1:], strict=False))


def test_folder_timestamps_from_dataset_poses_csv(tmp_path):
    frames_dir = tmp_path / "frames"
    frames_dir.mkdir()
    for k in range(3):
        _write_png(frames_dir / f"{k:06d}.png", k)
    (tmp_path / "poses.csv").write_text(
        "frame,file,time_s,phase\n0,000000.png,0.000,1\n1,000001.png,0.125,1\n2,000002.png,0.300,1\n3,000003.png,0.4,1\n"
    )
    src = FolderSource(frames_dir)
    with src:
        ts = [f.t_s for f in src]
    assert src.table == tmp_path / "poses.csv"
    assert ts == pytest.approx([0.0, 0.125, 0.300])


def test_folder_table_must_cover_files_and_increase(tmp_path):
    for k in range(2):
        _write_png(tmp_path / f"{k}.png", k)
    (tmp_path / "frames.csv").write_text("file,time_s\n0.png,0.5\n")
    with pytest.raises(SourceUnreadable, match="no row"):
        FolderSource(tmp_path).open()
    (tmp_path / "frames.csv").write_text("file,time_s\n0.png,0.5\n1.png,0.5\n")
    with pytest.raises(SourceUnreadable, match="does not increase"):
        FolderSource(tmp_path).open()
    with FolderSource(tmp_path, use_table=False) as src:  # the nominal rate instead
        assert [f.t_s for f in src] == pytest.approx([0.0, 0.1])


def test_folder_errors(tmp_path):
    with pytest.raises(SourceNotFound):
        FolderSource(tmp_path / "nope").open()
    (tmp_path / "empty").mkdir()
    with pytest.raises(EmptySource, match="no image"):
        FolderSource(tmp_path / "empty").open()
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "0.jpg").write_bytes(b"not a jpeg")
    # issue 60: a corrupt frame is skipped and counted, never an error that reopens the folder
    with FolderSource(bad) as src, pytest.raises(EndOfStream):
        src.read()
    assert src.corrupt_frames == 1 and "cannot decode" in src.last_corrupt
    with pytest.raises(CameraError):  # read before open
        FolderSource(bad).read()


def test_a_corrupt_frame_in_a_folder_is_skipped_and_counted(tmp_path):
    """Issue 60: one corrupt JPEG in a folder ended the source with an error, which the daemon
    took for a lost camera and reopened from frame 0, forever."""
    from PIL import Image

    for k in range(4):
        Image.fromarray(np.full((8, 10, 3), 40 * k, np.uint8)).save(tmp_path / f"{k}.png")
    (tmp_path / "2.png").write_bytes(b"\x89PNG truncated")
    with FolderSource(tmp_path) as src:
        frames = list(src)
    assert [int(f.image.mean()) for f in frames] == [0, 40, 120]
    assert [f.seq for f in frames] == [0, 1, 2]
    assert src.corrupt_frames == 1 and "2.png" in src.last_corrupt


# --- video file ----------------------------------------------------------------------------
def _write_video(path, n, fps=20.0):
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (W, H))
    assert vw.isOpened()
    for k in range(n):
        vw.write(cv2.cvtColor(_img(k), cv2.COLOR_RGB2BGR))
    vw.release()


def test_video_file_source(tmp_path):
    path = tmp_path / "clip.avi"
    _write_video(path, 6, fps=20.0)
    with VideoFileSource(path) as src:
        assert src.fps == pytest.approx(20.0)
        frames = list(src)
        with pytest.raises(EndOfStream):
            src.read()
    assert [f.seq for f in frames] == list(range(6))
    assert [f.t_s for f in frames] == pytest.approx([k / 20.0 for k in range(6)])
    red = [int(f.image[H // 2, W // 2, 0]) for f in frames]
    assert red == pytest.approx([k * 20 for k in range(6)], abs=6)  # MJPG is lossy
    assert all(int(f.image[H // 2, W // 2, 2]) > 180 for f in frames)  # converted to RGB


def test_video_file_realtime_pacing(tmp_path):
    path = tmp_path / "clip.avi"
    _write_video(path, 4, fps=20.0)
    t0 = time.monotonic()
    with VideoFileSource(path, realtime=True) as src:
        assert len(list(src)) == 4
    assert time.monotonic() - t0 >= 0.14  # 3 periods of 50 ms


def test_video_file_errors(tmp_path):
    with pytest.raises(SourceNotFound, match="does not exist"):
        VideoFileSource(tmp_path / "missing.avi").open()
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"\x00garbage" * 100)
    with pytest.raises(CameraOpenError):  # unreadable or empty, either way a clear open error
        VideoFileSource(junk).open()
    with pytest.raises(SourceUnreadable, match="not a file"):
        VideoFileSource(tmp_path).open()


def test_device_that_does_not_exist(tmp_path):
    with pytest.raises(SourceNotFound):
        DeviceSource(str(tmp_path / "video9")).open()
    with pytest.raises(CameraOpenError):
        DeviceSource(97).open()


def test_open_source_dispatch(tmp_path):
    _write_video(tmp_path / "c.avi", 2)
    assert isinstance(open_source(str(tmp_path / "c.avi")), VideoFileSource)
    assert isinstance(open_source(str(tmp_path)), FolderSource)
    assert isinstance(open_source("0"), DeviceSource)
    with pytest.raises(SourceNotFound):
        open_source(str(tmp_path / "nothing"))


# --- callable (simulated camera) -----------------------------------------------------------
def test_callable_source_lockstep():
    seen = []

    def render(t):
        seen.append(t)
        return _img(len(seen))

    with CallableSource(render, rate_hz=10.0, realtime=False, t0_s=5.0) as src:
        frames = [src.read() for _ in range(3)]
    assert seen == pytest.approx([5.0, 5.1, 5.2])
    assert [f.t_s for f in frames] == pytest.approx(seen)
    assert [f.seq for f in frames] == [0, 1, 2]
    assert int(frames[2].image[0, 0, 0]) == 60


def test_callable_source_realtime_rate_and_grey():
    with CallableSource(lambda t: np.full((H, W), 7, np.uint8), rate_hz=50.0) as src:
        t0 = time.monotonic()
        frames = [src.read() for _ in range(6)]
        elapsed = time.monotonic() - t0
    assert elapsed >= 0.09  # 5 periods of 20 ms
    ts = [f.t_s for f in frames]
    assert all(b > a for a, b in zip(ts, ts[1:], strict=False))
    assert frames[0].image.shape == (H, W, 3) and int(frames[0].image[0, 0, 1]) == 7


def test_callable_source_dropout_and_failure():
    src = CallableSource(lambda t: None, realtime=False, lost_timeout_s=0.2)
    with src:
        t0 = time.monotonic()
        with pytest.raises(CameraLost, match="no frame") as info:
            src.read()
        assert 0.15 <= time.monotonic() - t0 < 2.0
        assert info.value.seconds_without_frame >= 0.2

    def boom(t):
        raise RuntimeError("GL context lost")

    with CallableSource(boom, realtime=False) as src, pytest.raises(CameraLost, match="GL context lost"):
        src.read()
    with (
        CallableSource(lambda t: np.zeros((4, 4, 2), np.uint8), realtime=False) as src,
        pytest.raises(CameraError, match="shape"),
    ):
        src.read()


# --- LatestFrame ---------------------------------------------------------------------------
def test_latest_frame_drops_stale_frames_under_slow_consumer():
    src = CallableSource(lambda t: _img(int(t * 100)), rate_hz=100.0)
    seqs = []
    with LatestFrame(src, lost_timeout_s=1.0) as cam:
        for _ in range(6):
            f = cam.get()
            # The frame handed over is the newest one: at most about one period old.
            assert f.age_s < 0.1  # a queue would hand over frames ~0.05 s older each cycle
            seqs.append(f.seq)
            time.sleep(0.05)  # a consumer 5x slower than the camera
    stats = cam.stats  # after stop(): no frame can arrive any more
    assert all(b > a for a, b in zip(seqs, seqs[1:], strict=False))  # never an older (or the same) frame
    assert seqs[-1] - seqs[0] >= 15  # it skipped ahead
    assert cam.dropped == stats.dropped >= 15
    assert stats.delivered == 6
    assert stats.captured >= stats.delivered + stats.dropped
    assert not cam.running and not src.is_open


def test_latest_frame_never_returns_a_frame_twice():
    src = CallableSource(lambda t: _img(0), rate_hz=20.0)
    with LatestFrame(src) as cam:
        a = cam.get()
        assert cam.poll() is None  # nothing newer yet
        b = cam.get()
        assert b.seq > a.seq and b.t_s > a.t_s


def test_latest_frame_source_that_stops_raises_after_timeout():
    gate = threading.Event()
    count = [0]

    def render(t):
        count[0] += 1
        if count[0] > 3:
            gate.wait(5.0)  # the camera hangs (driver stuck / unplugged)
        return _img(count[0])

    cam = LatestFrame(CallableSource(render, rate_hz=50.0), lost_timeout_s=0.3, join_timeout_s=0.2)
    with cam:
        first = cam.get()
        assert first.seq <= 2
        last = first
        t0 = time.monotonic()
        with pytest.raises(CameraLost, match="no new frame") as info:
            while True:
                last = cam.get()
        assert time.monotonic() - t0 < 1.5
        assert info.value.seconds_without_frame >= 0.3
        assert last.seq <= 2
        gate.set()  # let the reader finish so stop() joins it


def test_latest_frame_reports_source_error_and_end(tmp_path):
    src = CallableSource(lambda t: None, realtime=False, lost_timeout_s=0.1)
    with LatestFrame(src, lost_timeout_s=5.0) as cam, pytest.raises(CameraLost, match="no frame"):
        cam.get()
    for k in range(3):
        _write_png(tmp_path / f"{k}.png", k)
    with LatestFrame(FolderSource(tmp_path, realtime=True, rate_hz=50.0)) as cam:
        got = []
        with pytest.raises(EndOfStream):
            while True:
                got.append(cam.get().seq)
    assert got and got == sorted(set(got)) and got[-1] == 2


def test_latest_frame_open_error_raised_at_start(tmp_path):
    cam = LatestFrame(FolderSource(tmp_path / "missing"))
    with pytest.raises(SourceNotFound):
        cam.start()
    assert not cam.running
    with pytest.raises(CameraError, match="not started"):
        cam.get()
