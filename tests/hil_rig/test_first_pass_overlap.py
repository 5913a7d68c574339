"""The direct model runs on its own thread while the crop placed by the prediction is read
(KeypointPoseEstimator.overlap_first_pass): the same computations, so the same poses, read from
the same number of crops; only sooner."""

import threading
from pathlib import Path

import numpy as np
import pytest

from oibar.nav.pose import KeypointPoseEstimator
from oibar_hil.rig.camera import RigCamera, scene_spec

REPO = Path(__file__).resolve().parents[2]
MODEL = REPO / "models" / "oibarnet.onnx"


@pytest.fixture(scope="module")
def approach(headless_gl):
    """Eight frames of a slow approach from 6 m to 2 m, drifting sideways and turning a little."""
    cam = RigCamera(scene=scene_spec(f"{REPO / 'models/scenes/val.json'}:va003"))
    with cam:
        return [
            cam.render(
                np.array([0.05 * np.sin(k), -0.03 * k / 7, 6.0 - 4.0 * k / 7]),
                np.radians([0.5 * np.cos(k), -0.4, 0.1 * k]),
            ).image
            for k in range(8)
        ]


def _track(est, frames):
    """Each frame with the previous frame's pose as the prediction (as the daemon's filter gives
    it); -> the poses (T, R flattened) and the keypoint network's crops read per frame, and the
    threads the direct model ran on."""
    crops, threads = [], set()
    run, first = est.reader.run, est.first.estimate

    def counted(x):
        crops[-1] += len(x)
        return run(x)

    def traced(*a, **k):
        threads.add(threading.current_thread().name)
        return first(*a, **k)

    est.reader.run, est.first.estimate = counted, traced
    poses, prior = [], None
    for k, image in enumerate(frames):
        crops.append(0)
        e = est.estimate(image, 0.1 * (k + 1), prior=prior)
        assert e.finite
        poses.append(np.concatenate([e.T_cam_target_m, e.R_cam_target.ravel()]))
        prior = (e.R_cam_target, e.T_cam_target_m)
    return np.array(poses), crops, threads


def test_the_overlapped_first_pass_gives_the_same_poses_from_the_same_crops(approach):
    seq = _track(KeypointPoseEstimator(MODEL, overlap_first_pass=False), approach)
    ovl = _track(KeypointPoseEstimator(MODEL), approach)
    # bit for bit: the placed crop's early reading is of the window the fit then places
    np.testing.assert_array_equal(ovl[0], seq[0])
    # the early reading is used, not read again
    assert ovl[1] == seq[1] and min(seq[1]) >= 1
    # and the direct model did run beside it: on the main thread only for the first frame (no
    # prediction yet), on the estimator's own thread after
    assert seq[2] == {threading.current_thread().name}
    assert any(name.startswith("oibar-first-pass") for name in ovl[2])


def _estimate_in_child(est, image, prior, out):
    e = est.estimate(image, 1.0, prior=prior)
    out.put(e.T_cam_target_m.tolist())


def test_an_estimator_used_before_a_fork_still_answers_in_the_child(approach):
    """A process forked after the estimator has run its direct model on its thread inherits the
    executor but not the thread: the child makes its own instead of waiting forever."""
    import gc
    import multiprocessing as mp

    est = KeypointPoseEstimator(MODEL)
    e0 = est.estimate(approach[0], 0.1)
    e1 = est.estimate(approach[1], 0.2, prior=(e0.R_cam_target, e0.T_cam_target_m))  # the thread runs
    assert e1.finite
    est.forget()
    # Collect the earlier tests' garbage here, not in the child: a GC pass there runs the
    # finalizers of dead onnxruntime sessions and thread pools, which may wait on threads the
    # child does not have. After the whole rig suite the child hung so, inside the Thread() of
    # its first submit (3 runs of 3); with this collect the suite passes.
    gc.collect()
    ctx = mp.get_context("fork")
    out = ctx.Queue()
    child = ctx.Process(
        target=_estimate_in_child, args=(est, approach[2], (e1.R_cam_target, e1.T_cam_target_m), out)
    )
    child.start()
    child.join(timeout=60)
    if child.is_alive():
        child.kill()
        child.join()
        pytest.fail("the forked child never answered: it waited on its parent's first-pass thread")
    assert child.exitcode == 0
    assert np.all(np.isfinite(out.get(timeout=5)))
