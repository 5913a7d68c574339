"""Track-level confirmation of PnP fits (issue 15).

A strong PnP fit that disagrees grossly with the direct model is, on one frame, as likely a fit
on the wrong points as a direct model that is wrong: the estimator lowers its confidence and
says so (`direct_disagrees`). On the validation scenes the second case dominates where the loss
is largest: the first pass takes a 10 m fixture for a 0.5 m one for seconds on end (va012,
va017) while the zoom search keeps finding the true fixture with strong fits; at confidence x0.3
the navigation filter never takes them, so the track never locks and every frame starts cold.

A run of strong fits that agree with one another, frame after frame, is evidence the direct
model does not have: the fixture's keypoints do not land on a consistent wrong pose by chance
in successive frames. So when the current strong fit agrees with at least CONFIRM_EARLIER
earlier strong fits of the last CONFIRM_WINDOW_S, the disagreement is reported
(`direct_overruled`) but no longer costs confidence.

Only frames with advancing times can confirm each other: a frame whose time does not advance
(a caller that gives none, t_s = 0) or that comes after a gap longer than the window starts the
history afresh.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from oibar.geometry.rotations import rotation_angle_deg

CONFIRM_EARLIER = 2  # earlier strong fits that must agree: three in a row, ~0.3 s at 10 Hz
# How far back an earlier fit still counts: long enough for the evaluation's frames (the scenes
# are rendered at 1.25 Hz and read every second frame, 1.6 s apart), the motion term below keeps
# the agreement honest over it.
CONFIRM_WINDOW_S = 5.0
# Agreement between two fits dt apart: position within this share of the range plus what the
# chaser can move in dt (the approach runs at 0.09-0.12 m/s), attitude within this angle. The
# confusions this guards against are gross (a 10 m fixture read at 0.5 m: 95 % of the range).
CONFIRM_POS_FRACTION = 0.1
CONFIRM_SPEED_MPS = 0.15
CONFIRM_ATT_DEG = 10.0
HISTORY_LEN = 8


@dataclass
class FitHistory:
    """The recent strong fits (time, T_cam_target_m, R_cam_target), oldest first."""

    window_s: float = CONFIRM_WINDOW_S
    fits: list[tuple[float, np.ndarray, np.ndarray]] = field(default_factory=list)
    t_last_s: float | None = None  # the last frame's time

    def forget(self) -> None:
        self.fits.clear()
        self.t_last_s = None

    def advance(self, t_s: float) -> None:
        """A new frame at t_s: drop the fits it cannot be compared with (time not advancing
        since the last frame, or older than the window)."""
        if self.t_last_s is not None and t_s <= self.t_last_s:
            self.fits.clear()
        self.t_last_s = t_s
        self.fits[:] = [f for f in self.fits if t_s - f[0] <= self.window_s]

    def agreeing(self, t_s: float, T_m: np.ndarray, R: np.ndarray) -> int:
        """How many remembered fits agree with the pose (T_m, R) at t_s."""
        range_m = float(np.linalg.norm(T_m))
        n = 0
        for t0, T0, R0 in self.fits:
            near_m = min(range_m, float(np.linalg.norm(T0)))  # the stricter of the two
            tol_m = CONFIRM_POS_FRACTION * near_m + CONFIRM_SPEED_MPS * abs(t_s - t0)
            if float(np.linalg.norm(T_m - T0)) <= tol_m and rotation_angle_deg(R.T @ R0) <= CONFIRM_ATT_DEG:
                n += 1
        return n

    def latest(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(R_cam_target, T_cam_target_m) of the newest remembered fit, or None."""
        if not self.fits:
            return None
        _, T_m, R = self.fits[-1]
        return R.copy(), T_m.copy()

    def confirmed(self, t_s: float, T_m: np.ndarray, R: np.ndarray) -> bool:
        return self.agreeing(t_s, T_m, R) >= CONFIRM_EARLIER

    def add(self, t_s: float, T_m: np.ndarray, R: np.ndarray) -> None:
        self.fits.append((float(t_s), np.array(T_m, float), np.array(R, float)))
        del self.fits[:-HISTORY_LEN]
