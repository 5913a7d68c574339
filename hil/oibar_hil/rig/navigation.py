"""Navigation sources for the rig: the camera frame and the navigator the daemon's cycle uses.

The rig runs the host's own ``NavDaemon.cycle`` (oibar.nav.daemon) every guidance period; a
source gives it two things: ``frame(t_s, world)`` (the camera frame of this cycle, or None) and
``navigator`` (what the daemon calls ``step`` on).

- ``truth``: no camera; the navigator reports the world's ground truth (reference runs, the
  fault matrix and the soak: they test the mechanism, the link and the daemon, not the CNN);
- ``cnn``: the flight path. The rig's camera renders the scene for the world's current pose
  (oibar_hil.rig.camera), and the host's Navigator (oibar.nav.core: OibarNet on onnxruntime, the
  checks, the filter) turns the frame into the solution inside the daemon's cycle, with the
  vehicle's own relative velocity (the rig's vehicle interface: the world's
  ``relative_velocity``, truth plus the GNC's noise) and its relative attitude (the world's
  ``relative_attitude``, which the navigator checks the camera's against). Frames are rendered at
  the guidance rate.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from oibar.camera import Frame
from oibar.geometry.docking import camera_pose_from_docking
from oibar.geometry.rotations import matrix_to_quat
from oibar.nav.core import NavStep
from oibar.nav.guidance import NavSolution

REPO_ROOT = Path(__file__).resolve().parents[3]
_TOKEN_IMAGE = np.zeros((1, 1, 3), np.uint8)
DEFAULT_MODEL = REPO_ROOT / "models" / "oibarnet.onnx"


class TruthNav:
    """The world's ground truth as a navigator (``step`` as oibar.nav.core.Navigator's)."""

    name = "truth"
    estimator = None

    def __init__(self) -> None:
        self.last_timings_ms: dict[str, float] = {}
        self.world_of: Any = None  # set by the rig: () -> World (the soak swaps worlds)
        self._seq = 0
        self._last: NavSolution | None = None

    @property
    def navigator(self) -> TruthNav:
        return self

    max_frame_age_s = 0.25  # as oibar.nav.core.NavigatorParams: an older frame is stale

    def frame(self, t_s: float, world: Any) -> Frame:
        """A token frame (the truth needs no pixels): it says a camera frame arrived this cycle,
        so a rig fault can take it away (camera unplugged) or make it late (slow inference)."""
        self._seq += 1
        return Frame(image=_TOKEN_IMAGE, seq=self._seq, t_s=t_s, t_host=t_s, source="truth")

    def step(
        self,
        t_s: float,
        image: Any = None,
        frame_t_s: float | None = None,
        frame_seq: int | None = None,
        odometry: Any = None,
        attitude_ref: Any = None,
    ) -> NavStep:
        """The truth now when a fresh frame came; else, like a coasting filter, the last solution
        with the reason to hold (no new frame, stale frame) and no confidence. (``odometry`` and
        ``attitude_ref`` are the Navigator's arguments: the truth needs neither.)"""
        if image is not None and (frame_t_s is None or t_s - frame_t_s <= self.max_frame_age_s):
            self._last = self.solve(t_s, self.world_of())
            return NavStep(t_s, self._last)
        reason = (
            "no new frame"
            if image is None or frame_t_s is None
            else f"stale frame ({t_s - frame_t_s:.2f} s old)"
        )
        last = self._last or NavSolution(valid=False)
        sol = NavSolution(
            valid=last.valid,
            r_D_m=last.r_D_m,
            v_D_mps=last.v_D_mps,
            att_rad=last.att_rad,
            misalignment_deg=last.misalignment_deg,
            t_cam_target_m=last.t_cam_target_m,
            q_cam_target=last.q_cam_target,
            confidence=0.0,
            hold_reason=reason if last.valid else "filter not initialised",
        )
        return NavStep(t_s, sol, hold_reason=sol.hold_reason)

    def solve(self, t_s: float, world: Any) -> NavSolution:
        s = world.s
        T, R = camera_pose_from_docking(s.r_D_m, s.att_rad)
        return NavSolution(
            valid=True,
            r_D_m=s.r_D_m.copy(),
            v_D_mps=s.v_D_mps.copy(),
            att_rad=s.att_rad.copy(),
            misalignment_deg=world.misalignment_deg,
            t_cam_target_m=T,
            q_cam_target=matrix_to_quat(R),
            confidence=1.0,
        )

    def reset(self) -> None:
        """A new approach begins (nothing to forget: the truth has no memory)."""

    def close(self) -> None:
        pass


class CnnNav:
    """Rendered camera + the host's Navigator. ``camera_blackout`` (a callable t_s -> bool) lets
    a scenario take the camera away."""

    name = "cnn"

    def __init__(
        self,
        model_path: str | Path | None = None,
        scene: str = "seq01",
        seed: int = 0,
        threads: int = 2,
        camera_blackout=None,
        camera_options: dict | None = None,  # more RigCamera arguments (exposure, sensor_effects)
    ) -> None:
        from oibar.nav.core import Navigator
        from oibar.nav.pose import PoseEstimator
        from oibar_hil.rig.camera import RigCamera

        self.model_path = Path(model_path) if model_path else DEFAULT_MODEL
        # model first: a missing or corrupt model is reported before the GL context is made
        self.navigator = Navigator(PoseEstimator(self.model_path, threads=threads))
        self.camera = RigCamera(scene=scene, seed=seed, **(camera_options or {}))
        self.blackout = camera_blackout
        self.frames = 0
        self.last_timings_ms: dict[str, float] = {}
        self.last_step: NavStep | None = None

    def frame(self, t_s: float, world: Any) -> Frame | None:
        """This cycle's camera frame, rendered for the world's pose (None during a blackout)."""
        self.last_timings_ms = {}
        if self.blackout is not None and self.blackout(t_s):
            return None
        s = world.s
        t0 = time.perf_counter()
        image = self.camera.render(s.r_D_m, s.att_rad, t_s=t_s).image
        self.last_timings_ms["render_ms"] = (time.perf_counter() - t0) * 1e3
        self.frames += 1
        return Frame(image=image, seq=self.frames, t_s=t_s, t_host=t_s, source="rig-camera")

    def solve(self, t_s: float, world: Any) -> NavSolution:
        """Frame and navigator on their own, without the daemon (tests and studies of the
        navigation alone): what the daemon's cycle would compute for this world."""
        frame = self.frame(t_s, world)
        step = self.navigator.step(
            t_s,
            None if frame is None else frame.image,
            frame_t_s=t_s,
            frame_seq=self.frames,
            odometry=world.relative_velocity(t_s),
            attitude_ref=world.relative_attitude(t_s) if frame is not None else None,
        )
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
