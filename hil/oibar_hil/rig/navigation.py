"""Navigation sources for the rig: what the host's guidance is told about the relative pose.

- ``truth``: the world's ground truth (reference runs, the fault matrix and the soak: they
  test the mechanism and the link, not the CNN);
- ``cnn``: the flight path. The rig's camera renders the scene for the world's current pose
  (oibar_hil.rig.camera), and the host's Navigator (oibar.nav.core: OibarNet on onnxruntime, the
  checks, the filter) turns the frame into the solution, exactly as the daemon does on a real
  camera, with the vehicle's own relative velocity (the world's ``relative_velocity``: truth plus
  the GNC's noise) as the daemon gets it from the vehicle interface. Frames are rendered at the
  guidance rate only.

Both record their estimate beside the truth so the report can plot navigation errors.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from oibar.nav.frames import camera_pose_from_docking
from oibar.nav.guidance import NavSolution
from oibar.rotations import matrix_to_quat

REPO_ROOT = Path(__file__).resolve().parents[3]
DEFAULT_MODEL = REPO_ROOT / "models" / "oibarnet_lite.onnx"


class TruthNav:
    name = "truth"

    def __init__(self) -> None:
        self.last_timings_ms: dict[str, float] = {}

    def solve(self, t_s: float, world: Any) -> NavSolution:
        s = world.s
        T, R = camera_pose_from_docking(s.r_D_m, s.att_rad)
        return NavSolution(valid=True, r_D_m=s.r_D_m.copy(), v_D_mps=s.v_D_mps.copy(), att_rad=s.att_rad.copy(),
                           misalignment_deg=world.misalignment_deg, t_cam_target_m=T,
                           q_cam_target=matrix_to_quat(R), confidence=1.0)

    def reset(self) -> None:
        """A new approach begins (nothing to forget: the truth has no memory)."""

    def close(self) -> None:
        pass


class CnnNav:
    """Rendered camera + the host's Navigator. ``camera_blackout`` (a callable t_s -> bool) lets
    a scenario take the camera away."""

    name = "cnn"

    def __init__(self, model_path: str | Path | None = None, scene: str = "seq01", seed: int = 0,
                 threads: int = 2, camera_blackout=None) -> None:
        from oibar.nav.core import Navigator
        from oibar.nav.pose import PoseEstimator
        from oibar_hil.rig.camera import RigCamera

        self.model_path = Path(model_path) if model_path else DEFAULT_MODEL
        # model first: a missing or corrupt model is reported before the GL context is made
        self.navigator = Navigator(PoseEstimator(self.model_path, threads=threads))
        self.camera = RigCamera(scene=scene, seed=seed)
        self.blackout = camera_blackout
        self.frames = 0
        self.last_timings_ms: dict[str, float] = {}
        self.last_step = None

    def solve(self, t_s: float, world: Any) -> NavSolution:
        s = world.s
        frame = None
        t0 = time.perf_counter()
        if self.blackout is None or not self.blackout(t_s):
            frame = self.camera.render(s.r_D_m, s.att_rad, t_s=t_s).image
            self.frames += 1
        render_ms = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        odometry = world.relative_velocity(t_s)   # None when the scenario turns it off
        step = self.navigator.step(t_s, frame, frame_t_s=t_s, frame_seq=self.frames, odometry=odometry)
        nav_ms = (time.perf_counter() - t0) * 1e3
        self.last_timings_ms = {"render_ms": render_ms, "nav_ms": nav_ms, **step.timings_ms}
        self.last_step = step
        return step.solution

    def reset(self) -> None:
        """A new approach begins: forget the last one's track, or the first frames of the new
        one (the vehicle back at its start) would be gated as outliers of the old state."""
        self.navigator.reset()
        self.last_step = None

    def close(self) -> None:
        self.camera.close()


def make_nav(kind: str, **kw) -> Any:
    if kind == "truth":
        return TruthNav()
    if kind == "cnn":
        return CnnNav(**kw)
    raise ValueError(f"unknown navigation {kind!r}: truth or cnn")
