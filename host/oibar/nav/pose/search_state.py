"""What a window search keeps: its fits so far (FitKeeper) and the cold search it carries from
frame to frame (ColdSearch)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from oibar.nav.keypoints import CropWindow, PnpResult
from oibar.nav.pose.fusion import STRONG_FIT_RMS_CROP_PX, fit_rms_crop_px

# one window's fit (None, None: no fit), and what the search offers each fit to (FitKeeper.consider)
Fit = tuple[PnpResult, CropWindow] | tuple[None, None]
Consider = Callable[[PnpResult | None, CropWindow | None], bool]


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
