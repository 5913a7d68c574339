"""The scan, the cold search's last stage: the whole frame read in fixed windows, the most
fixture-like solved (search.WindowSearch's cold search calls scan_pass after the zoom). It goes
on from where a ColdSearch stopped and stops where the frame's crop budget runs out.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from oibar.nav.keypoints import CropWindow
from oibar.nav.pose.reader import KeypointReader
from oibar.nav.pose.roll import OnePass
from oibar.nav.pose.search_state import ColdSearch, Consider, Fit

# The last resort of a cold start: when the prediction, SEARCH_STEPS and the zoom give no strong
# fit, the whole frame is read in windows of SCAN_SIDE_PX, SCAN_STRIDE sides apart (so some
# window holds the fixture within a quarter side of its centre, as in training), in batches of
# SCAN_BATCH, and the SCAN_TRY most fixture-like are solved. The zoom follows the first pass,
# whose scale can be wrong and whose place can be 0.5-2 windows off at once: on validation scene
# va012's look (shadowed, 9-10.5 m) the first pass read 0.45 m and the zoom never found the
# 35-40 px fixture (14 of 52 cold frames beyond 4 m weak; the rig's mission from 9 m never locked
# and aborted). Windows of 64 px (1.6-2.7x a far fixture's, 6-15 m) ranked the fixture's first
# on every one of the 16 cold frames of the validation scenes where the search failed (its score
# 0.04-0.21, the best elsewhere <= 0.04 but for its neighbours). Cost: ~320 crops, ~0.7 s on 2
# cores, on cold frames that found nothing else (nearer fixtures are the first pass's strength).
SCAN_SIDE_PX = 64.0
SCAN_STRIDE = 0.5
SCAN_BATCH = 64
SCAN_TRY = 3
# A ranked scan window that gives too few keypoints to solve is read again smaller (SCAN_SHRINK:
# its centre and a quarter side either way, at SCAN_SHRINK_FACTOR of its side, in one batch; the
# most fixture-like solved). 64 px holds a fixture at 9-12 m at about half the scale the keypoint
# network was trained on: on validation scene va012's look from 10.5 m (turned -2 / 1.5 deg, the
# fixture 28 px wide) stage 15's network ranked the fixture's window first (0.065, the next 0.001)
# but saw 3 of its 14 keypoints there, so the scan never solved it and the rig's mission aborted;
# 0.6 of the window found it to 0.29 crop px RMS (0.5: 0.41, 0.75: 0.28). 10 crops, only where
# the plain scan had nothing from that window.
SCAN_SHRINK_FACTOR = 0.6
SCAN_SHRINK = tuple((dx, dy) for dy in (-0.25, 0.0, 0.25) for dx in (-0.25, 0.0, 0.25))


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


def scan_pass(
    reader: KeypointReader,
    one_pass: OnePass,
    image: np.ndarray,
    c: ColdSearch,
    R_direct: np.ndarray,
    f: dict[str, Any] | None,
    consider: Consider,
    crops_left: float,
) -> bool:
    """The scan of the whole frame from where `c` stands: True when it is over (`consider` kept a
    strong fit, or nothing is left to try); False when the next read would take more than
    `crops_left` crops (`c` then says where to go on)."""
    h, w = image.shape[:2]
    wins = scan_windows((w, h), SCAN_SIDE_PX, SCAN_STRIDE, reader.out_px, c.angle_rad)
    read = sum(len(s) for s in c.scan_scores)
    while read < len(wins):
        n = int(min(SCAN_BATCH, len(wins) - read, crops_left))
        if n < 1:
            return False
        c.scan_scores.append(reader.fixture_likeness(image, wins[read : read + n]))
        read, crops_left = read + n, crops_left - n
    # ranked over every window scored, on this frame or the last ones: the fixture moves only
    # a few pixels in between (search.COLD_CARRY_MAX_AGE_S)
    ranked = [wins[i] for i in np.argsort(-np.concatenate(c.scan_scores), kind="stable")[:SCAN_TRY]]
    while c.tried < len(ranked):
        swin = ranked[c.tried]
        if crops_left < 1:
            return False
        crops_left -= 1
        r, rwin = one_pass(image, swin, R_direct, f, reader.range_for_side_m(swin.side_px))
        if consider(r, rwin):
            return True
        if r is None:  # too few keypoints: a far fixture seen too small (SCAN_SHRINK)
            if crops_left < len(SCAN_SHRINK) + 1:
                return False  # the next frame reads this window again, then shrinks it
            crops_left -= len(SCAN_SHRINK) + 1
            r, rwin = shrunk_scan_pass(reader, one_pass, image, swin, R_direct, f)
            if consider(r, rwin):
                return True
        if r is not None:
            # a weak fit from a window of a guessed size is close (validation: within 10 % of
            # the range): read again in the window its own pose draws
            around = reader.window_for(*r.pose())
            if around is not None:
                if crops_left < 1:
                    return False  # the next frame reads this window again, then redraws
                crops_left -= 1
                if consider(*one_pass(image, around, R_direct, f, float(np.linalg.norm(r.pose()[1])))):
                    return True
        c.tried += 1
    return True


def shrunk_scan_pass(
    reader: KeypointReader,
    one_pass: OnePass,
    image: np.ndarray,
    swin: CropWindow,
    R_direct: np.ndarray,
    f: dict[str, Any] | None,
) -> Fit:
    """SCAN_SHRINK's windows inside scan window `swin`, read in one batch; the most
    fixture-like solved."""
    if not SCAN_SHRINK:
        return None, None
    wins = [swin.stepped(dx, dy, SCAN_SHRINK_FACTOR) for dx, dy in SCAN_SHRINK]
    best = wins[int(np.argmax(reader.fixture_likeness(image, wins)))]
    return one_pass(image, best, R_direct, f, reader.range_for_side_m(best.side_px))
