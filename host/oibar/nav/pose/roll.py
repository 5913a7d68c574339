"""Rolled views: which turn of a crop window shows the fixture upright. The shipped network was
trained on unrolled views and reads a fixture turned in its crop as unrolled; rolling the camera
about its boresight only turns the image, so the search turns its windows (search.WindowSearch.solve
calls upright_pass and turned_pass; reader.window_for turns the windows a pose places).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from oibar.nav.keypoints import CropWindow, PnpResult
from oibar.nav.pose.fusion import fit_rms_crop_px
from oibar.nav.pose.reader import CROP_REF_PX, CropReading, KeypointReader
from oibar.nav.pose.search_state import FitKeeper

# WindowSearch._one_pass: (image, window, R_direct, fusion, range_m) -> (fit, its window)
OnePass = Callable[..., tuple[PnpResult, CropWindow] | tuple[None, None]]

# Roll. The network reads a fixture turned in its crop by up to ~20 deg and no further: at 45 deg
# off upright its keypoints are gone (fixture likeness 0.001-0.007 against 0.22-0.24 upright, at
# 0.6-10.4 m on the roll sweep val_roll), at 90 deg it reads a weak fit 90 deg off (likeness
# 0.1-0.15), and upside down (180 deg) it reads a strong fit 180 deg off, since the plate maps onto
# itself and the drogue is on the axis. Windows placed by a pose are turned upright
# (reader.window_for); a strong fit the search found (no pose placed its window) is checked first:
# - UPRIGHT_TWIN: its window and that window turned half a turn are read; where the twin's
#   keypoints are tighter (mean heat-map spread) by UPRIGHT_MARGIN_PX and its fit is strong and
#   better by UPRIGHT_RMS_RATIO, the twin shows the fixture upright and its fit replaces the first.
#   On val_roll (windows on the truth) the needed flips won by 0.09-3.6 px (median 0.31), their
#   fits' RMS 0.2-1.1 of the first's. In the lab look (the Mitsuba stand-ins lb000-lb009: matte
#   grey print, one lamp) the heat maps are about as tight one way up as the other: the twin came
#   out tighter by 0.001-0.06 px on 98 of 341 frames whose fit was right, and a flip read once is
#   carried by the track; hence the margin and the RMS ratio. The quarter turns are not checked:
#   in the lab they won wrongly under 3 m, by 0.2-7.5 px. The fit's own window is read as the
#   refining pass reads it, and the refining pass takes that reading: one crop more, and at most
#   one pass.
# - TURN_STEPS_DEG: when SEARCH_STEPS give no strong fit on a cold frame, the direct model's window
#   turned by each is read in one batch and, where one looks much more like the fixture than the
#   unturned window, it is solved and the cold search (the zoom, the scan) goes on at its turn.
#   45 deg apart, so a fixture at any roll is within 22.5 deg of one (likeness 0.20-0.24 up to
#   20-25 deg off). Only a turn at least TURN_MIN_LIKENESS fixture-like counts: where the direct
#   model's window misses the fixture (10 m, far frames of val_roll's unrolled approach), all eight
#   read 0.000-0.001, and the noisiest of them sent the zoom off at its turn (1 of 2 such frames
#   answered 88 deg off, the other no fit, where the unturned zoom found both). Upright windows
#   over the fixture read 0.14-0.24 (0.6-10.4 m), 90 deg off 0.10-0.15. 8 crops and one pass, on
#   the first frame of a cold search only, outside its crop budget as SEARCH_STEPS are: counted,
#   they left too few crops for the zoom's first batch on 7 of 2499 validation frames (va012 at
#   7-10 m), which then answered a frame later instead of at once.
UPRIGHT_TWIN = np.pi  # rad
UPRIGHT_MARGIN_PX = 0.1
UPRIGHT_RMS_RATIO = 0.8
TURN_STEPS_DEG = (0.0, 45.0, 90.0, 135.0, 180.0, -135.0, -90.0, -45.0)
TURN_MIN_LIKENESS = 0.05
# ... and at least TURN_MIN_GAIN times the unturned window's: a fixture 45 deg or more off upright
# reads 0.001-0.007 unturned against 0.2-0.24 turned, while in the lab look (lb000-lb009) a turn
# that merely tied with the unturned window sent 2 of 382 frames at 3.7-4.3 m 90-180 deg off.
TURN_MIN_GAIN = 2.0


def upside_down_twin(
    reader: KeypointReader, image: np.ndarray, win: CropWindow, reading: CropReading
) -> CropWindow | None:
    """`win` turned half a turn (UPRIGHT_TWIN) when its keypoints are tighter than `reading`'s
    (the reading of `win`) by UPRIGHT_MARGIN_PX, else None. The caller still asks its fit to be
    strong and better by UPRIGHT_RMS_RATIO."""
    own = float(np.mean(reading.spread_crop_px)) * CROP_REF_PX / reader.out_px * reader.spread_scale
    twin = replace(win, angle_rad=win.angle_rad + UPRIGHT_TWIN)
    spread = reader.heat_spread(image, [twin])
    if spread is None or not float(spread[0]) < own - UPRIGHT_MARGIN_PX:
        return None
    return twin


def turned_window(reader: KeypointReader, image: np.ndarray, base: CropWindow) -> CropWindow | None:
    """The turn stage: `base` turned by each of TURN_STEPS_DEG, read in one batch; the most
    fixture-like when it reaches TURN_MIN_LIKENESS and TURN_MIN_GAIN times `base`'s own, else None."""
    wins = [replace(base, angle_rad=base.angle_rad + np.radians(a)) for a in TURN_STEPS_DEG]
    score = reader.fixture_likeness(image, wins)
    best = int(np.argmax(score))  # the first of equals: the unturned window
    if best == 0 or score[best] < max(TURN_MIN_LIKENESS, TURN_MIN_GAIN * score[0]):
        return None
    return wins[best]


def upright_pass(
    reader: KeypointReader,
    one_pass: OnePass,
    image: np.ndarray,
    fit: tuple[PnpResult, CropWindow],
    R_direct: np.ndarray,
    f: dict[str, Any] | None,
) -> tuple[tuple[PnpResult, CropWindow] | None, tuple[CropWindow, CropReading] | None]:
    """A strong fit the search found, checked upside down: (the twin's fit when it replaces `fit`,
    else None; `fit`'s window with the refining reading made of it here, which the refining pass
    then uses instead of reading it again)."""
    R, T = fit[0].pose()
    w0 = reader.window_for(R, T) if reader.upright else None
    if w0 is None:
        return None, None
    read = (w0, reader.read_crop(image, w0, refining=True))
    twin = upside_down_twin(reader, image, w0, read[1])
    if twin is None:
        return None, read
    r, win = one_pass(image, twin, R_direct, f, float(np.linalg.norm(T)))
    if r is None or win is None or not fit_rms_crop_px(r, win) < UPRIGHT_RMS_RATIO * fit_rms_crop_px(*fit):
        return None, read
    return (r, win), read


def turned_pass(
    reader: KeypointReader,
    one_pass: OnePass,
    image: np.ndarray,
    base: CropWindow,
    R_direct: np.ndarray,
    T_direct: np.ndarray,
    f: dict[str, Any] | None,
    keep: FitKeeper,
) -> CropWindow | None:
    """The turn stage on the direct model's window `base` (turned_window): the turned window,
    solved and offered to `keep`, or None."""
    turned = turned_window(reader, image, base) if reader.upright else None
    if turned is not None:
        keep.consider(*one_pass(image, turned, R_direct, f, float(np.linalg.norm(T_direct))))
    return turned
