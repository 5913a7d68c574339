"""Golden vectors of the shipped estimator (issue 61, item 5): a handful of frames, every network
call's input and raw outputs on them, and the final poses.

The ONNX files need thousands of lines of Python after them (oibar.nav.pose: windows, crops,
readings, PnP and its priors, confidence) to become a pose. tests/host/test_pose_golden.py feeds
the stored raw outputs back through that post-processing, with no onnxruntime run (so no
CPU-to-CPU rounding), and checks the poses to a tight tolerance; separately it checks what
onnxruntime answers on this machine against the stored outputs, to a looser one.

    python -m oibar_models.golden_pose [--model models/oibarnet.onnx] [--out tests/golden/pose]

Run it again, and commit its files, when the shipped model or the post-processing changes on
purpose; the test then says which call or which pose moved.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[2]
# (name, probe tip in the docking frame D (m), attitude error (rad), frame time (s), tracked):
# cold frames at three ranges, then two frames tracked from the previous answer, as the daemon
# feeds it the filter's prediction
FRAMES = (
    ("cold_0p7m", (0.03, -0.02, 0.7), (0.02, -0.015, 0.01), 1.0, False),
    ("cold_3m", (-0.06, 0.04, 3.0), (-0.01, 0.02, -0.03), 2.0, False),
    ("cold_8m", (0.2, -0.1, 8.0), (0.01, 0.01, 0.02), 3.0, False),
    ("track_5m_a", (0.05, 0.02, 5.0), (0.015, -0.01, 0.0), 4.0, False),
    ("track_5m_b", (0.05, 0.02, 4.97), (0.015, -0.01, 0.0), 4.1, True),
)
SCENE = "seq01"


def sessions(est: Any) -> dict[str, Any]:
    """The onnxruntime sessions an estimator holds, by role."""
    out = {"first": est.first.session, "near": est.reader.session}
    if est.reader.far_session is not None:
        out["far"] = est.reader.far_session
    return out


class Recorder:
    """Wraps each session's run: every call's input (uint8: inputs are frames / 255) and outputs,
    numbered per session (the first pass may run on its own thread beside the crop reads, so
    only each session's own order is fixed)."""

    def __init__(self, est: Any):
        self.calls: dict[str, int] = {}
        self.arrays: dict[str, np.ndarray] = {}
        for role, sess in sessions(est).items():
            self.calls[role] = 0
            sess.run = self._wrap(role, sess.run)

    def _wrap(self, role: str, run: Any) -> Any:
        def recorded(names: Any, feed: dict[str, np.ndarray]) -> list[np.ndarray]:
            (x,) = feed.values()
            out = run(names, feed)
            i = self.calls[role]
            self.calls[role] += 1
            self.arrays[f"{role}{i}_in"] = np.rint(np.asarray(x) * 255.0).astype(np.uint8)
            for k, v in enumerate(out):
                self.arrays[f"{role}{i}_out{k}"] = np.asarray(v)
            return out

        return recorded


def estimate_frames(est: Any, frames: list[np.ndarray]) -> list[dict]:
    """The estimator on the golden frames, in order, as the daemon would: cold frames alone
    (forget() first), tracked ones with the previous answer as the prediction."""
    poses, last = [], None
    for (name, _, _, t_s, tracked), img in zip(FRAMES, frames, strict=True):
        if not tracked:
            est.forget()
        prior = (last.R_cam_target, last.T_cam_target_m) if tracked and last is not None else None
        e = est.estimate(img, t_s, prior=prior)
        last = e
        poses.append(
            {
                "frame": name,
                "T_cam_target_m": e.T_cam_target_m.tolist(),
                "q_cam_target": e.q_cam_target.tolist(),
                "confidence": e.confidence,
                "flags": list(e.flags),
                "T_meas_cam_target_m": None
                if e.T_meas_cam_target_m is None
                else e.T_meas_cam_target_m.tolist(),
            }
        )
    return poses


def main(argv: list[str] | None = None) -> int:
    from PIL import Image

    from oibar.nav.pose import KeypointPoseEstimator, ModelFileError, PoseEstimator
    from oibar_hil.rig.camera import RigCamera, RigCameraError
    from oibar_hil.sequence import sha256_file

    ap = argparse.ArgumentParser(
        prog="python -m oibar_models.golden_pose", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--model", type=Path, default=REPO_ROOT / "models/oibarnet.onnx")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "tests/golden/pose")
    a = ap.parse_args(argv)
    try:
        est = PoseEstimator(a.model, threads=1, warmup_runs=0)
    except ModelFileError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not isinstance(est, KeypointPoseEstimator):
        print(f"error: {a.model} is not a keypoint model", file=sys.stderr)
        return 2
    try:
        with RigCamera(SCENE, sensor_effects=True) as cam:
            frames = [cam.render(np.array(r), np.array(att), t_s).image for _, r, att, t_s, _ in FRAMES]
    except RigCameraError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    a.out.mkdir(parents=True, exist_ok=True)
    for (name, *_), img in zip(FRAMES, frames, strict=True):
        Image.fromarray(img).save(a.out / f"{name}.png", optimize=True)
    rec = Recorder(est)
    poses = estimate_frames(est, frames)
    np.savez_compressed(a.out / "raw.npz", **rec.arrays)
    meta = {
        "model": a.model.name,
        "model_sha256": sha256_file(a.model),
        "scene": SCENE,
        "threads": 1,
        "frames": [
            {"name": n, "r_D_m": r, "att_rad": att, "t_s": t, "tracked": tr} for n, r, att, t, tr in FRAMES
        ],
        "calls": rec.calls,
        "poses": poses,
    }
    (a.out / "golden.json").write_text(json.dumps(meta, indent=1) + "\n")
    print(f"{len(frames)} frames, network calls {rec.calls}, written to {a.out}")
    for p in poses:
        print(
            f"  {p['frame']}: T {np.round(p['T_cam_target_m'], 4)} confidence {p['confidence']:.3f} {p['flags']}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
