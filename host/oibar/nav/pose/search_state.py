"""What a window search keeps: its fits so far (FitKeeper), the cold search it carries from frame
to frame (ColdSearch), and the scan's windows over the whole frame."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from oibar.nav.keypoints import CropWindow, PnpResult
from oibar.nav.pose.fusion import STRONG_FIT_RMS_CROP_PX, fit_rms_crop_px


def scan_windows(
    frame_wh: tuple[int, int], side_px: float, stride: float, out_px: int, angle_rad: float = 0.0
) -> list[CropWindow]:
    """Square windows of side_px covering the frame, centres `stride` sides apart (row-major),
    the outer ones flush with the frame's edges, each turned by `angle_rad`."""
    w, h = frame_wh
    step = side_px * stride
    windows = []
    for cy in _spaced(h, side_px, step):
        for cx in _spaced(w, side_px, step):
            windows.append(CropWindow((cx, cy), side_px, out_px, angle_rad))
    return windows


def _spaced(length_px: float, side_px: float, step_px: float) -> np.ndarray:
    """Window centres along one axis: from side/2 to length - side/2, at most step_px apart."""
    if length_px <= side_px:
        return np.array([length_px / 2.0])
    n = int(np.ceil((length_px - side_px) / step_px - 1e-9)) + 1
    return np.linspace(side_px / 2.0, length_px - side_px / 2.0, n)


@dataclass
class ColdSearch:
    """Where a cold search (the zoom, then the scan) stopped when its frame's crop budget ran out
    (COLD_CROP_BUDGET), for the next frames to go on from: the zoom level under way, its base
    window and, once read, its windows to solve; the scan's scores so far. Which of the ranked
    windows have been solved (`tried`) holds for either."""

    level: int  # the zoom level under way; ZOOM_LEVELS: the scan
    base: CropWindow | None = None  # the zoom level's base window
    k_base: float = 1.0  # its size factor against the first pass's window
    ranked: list[tuple[CropWindow, float]] | None = None  # the level's windows to solve (None: unread)
    scan_scores: list[np.ndarray] = field(default_factory=list)  # the scan's, batch by batch
    tried: int = 0  # ranked windows solved so far
    angle_rad: float = 0.0  # the turn the scan's windows read at (the first frame's turn stage's)
    # its first frame's time and the latest one's (the estimator stamps them; NaN: never stamped)
    t_first_s: float = float("nan")
    t_last_s: float = float("nan")


class FitKeeper:
    """The search's fits so far: the first strong one (`best`), else the best weak one (`weak`,
    by `weak_rank`)."""

    def __init__(self, weak_rank: Callable[[PnpResult, CropWindow], tuple[bool, float]]):
        self.weak_rank = weak_rank
        self.best: tuple[PnpResult, CropWindow] | None = None
        self.weak: tuple[PnpResult, CropWindow] | None = None

    def consider(self, r: PnpResult | None, win: CropWindow | None) -> bool:
        """Keep a strong fit (True: stop searching); remember the best weak one."""
        if r is None or win is None:
            return False
        if fit_rms_crop_px(r, win) <= STRONG_FIT_RMS_CROP_PX:
            self.best = (r, win)
            return True
        if self.weak is None or self.weak_rank(r, win) < self.weak_rank(*self.weak):
            self.weak = (r, win)
        return False
