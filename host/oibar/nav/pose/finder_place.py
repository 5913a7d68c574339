"""Where the fixture finder's answer places a crop in the search (search stage "found"), if
anywhere: one crop before SEARCH_STEPS, when the finder is sure enough (FINDER_MIN_SCORE, its best
cell's probability) and puts the fixture elsewhere than the direct model's window does (its centre
more than FINDER_SAME_FRAC of that window's side away, or its side beyond FINDER_SAME_SIDE of it;
otherwise SEARCH_STEPS' first crop is the same window). A strong fit there ends the search as one
of SEARCH_STEPS' would; a wrong place costs that one crop.

Chosen on validation (2026-12-05, finder 0.1.0, every 16th frame alone,
`python -m oibar_models.finder_sweep`, which sets these constants here per run): scores 0.2-0.3
and 0.15-0.3 of a side gave the same accuracy and p95 (31-32 ms); 0.5 doubled the far frames'
p95. 0.3 of a side reads the finder's crop on 40 % of cold frames instead of 50 % for the same
answers.
"""

from __future__ import annotations

import numpy as np

from oibar.nav.keypoints import CropWindow
from oibar.nav.pose.finder import FixtureFinder

FINDER_MIN_SCORE = 0.3
FINDER_SAME_FRAC = 0.3
FINDER_SAME_SIDE = 1.25


def finder_window(
    finder: FixtureFinder | None,
    image: np.ndarray,
    base: CropWindow | None,
    margin: float,
    min_side_px: float,
    out_px: int,
) -> CropWindow | None:
    """The crop window around the box `finder` sees in `image` (its side times the keypoint
    reader's `margin`, never under `min_side_px`), or None: no finder, not sure enough, or where
    `base` (the direct model's window) already is."""
    if finder is None:
        return None
    ans = finder.find(image)
    if not ans.score >= FINDER_MIN_SCORE:
        return None
    win = CropWindow(ans.center_px, max(ans.side_px * margin, min_side_px), out_px)
    if base is not None:
        off = float(np.hypot(*np.subtract(win.center_px, base.center_px)))
        ratio = win.side_px / base.side_px
        if off <= FINDER_SAME_FRAC * base.side_px and 1 / FINDER_SAME_SIDE <= ratio <= FINDER_SAME_SIDE:
            return None
    return win
