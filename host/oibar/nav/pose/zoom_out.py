"""The zoom-out: a strong fit the search found, read again in larger windows in case the
fixture it found is a part of a bigger, nearer one (search.WindowSearch.solve calls
bigger_fixture after the cold search, never on a tracked frame)."""

from __future__ import annotations

from typing import Any

import numpy as np

from oibar.geometry.camera import project_target_points as project
from oibar.nav.keypoints import CropWindow, PnpResult
from oibar.nav.pose.fusion import STRONG_FIT_RMS_CROP_PX, fit_rms_crop_px
from oibar.nav.pose.reader import KeypointReader
from oibar.nav.pose.roll import OnePass

# A strong fit the search found (not one a predicted pose placed) is read again larger, in case
# the fixture it found is a part of a bigger, nearer one: on the lab look (matte grey print, one
# lamp at the camera, black background: validation looks val_lab) the keypoint network takes
# the plate's right coupling for a whole fixture 3-5x farther away, a strong fit (0.4-0.7 crop
# px) that the direct model, fooled too, agrees with: 2.4 m read as 8.6 m at confidence 0.97.
# Windows ZOOM_OUT_FACTORS times the fit's, a quarter side either way, read in one batch; the
# ZOOM_OUT_TRY most fixture-like solved. A strong fit there replaces the first when it is nearer
# by at least ZOOM_OUT_MIN_RATIO and its fixture's outline holds the first one's keypoints (a
# fixture seen inside a bigger one is a part of it). Only fits beyond ZOOM_OUT_FROM_M (the parts
# read as a fixture read 6-15 m) and windows up to the frame's height. Cost: one batch of 27
# crops and up to 2 passes (~0.15 s on 2 cores) on a frame whose fit the search found beyond
# 4 m, not on tracked frames. On val_lab's scenes (Mitsuba, 8 spp, every frame alone) it took
# the gross failures read at confidence >= 0.5 from 85 to 68 of 456 frames (silent failures 256
# -> 239, mean position error 108 -> 94 %); on the same frames of our renderer nothing changed.
ZOOM_OUT_FACTORS = (2.0, 3.0, 4.0)
ZOOM_OUT_STEPS = tuple(
    (dx, dy, k) for k in ZOOM_OUT_FACTORS for dy in (-0.25, 0.0, 0.25) for dx in (-0.25, 0.0, 0.25)
)
ZOOM_OUT_TRY = 2
ZOOM_OUT_MIN_RATIO = 0.7
ZOOM_OUT_FROM_M = 4.0


def bigger_fixture(
    reader: KeypointReader,
    one_pass: OnePass,
    image: np.ndarray,
    fit: tuple[PnpResult, CropWindow],
    R_direct: np.ndarray,
    f: dict[str, Any] | None,
) -> tuple[PnpResult, CropWindow] | None:
    """A bigger, nearer fixture around the strong fit `fit` (ZOOM_OUT_*), or None."""
    r, win = fit
    range_m = float(np.linalg.norm(r.pose()[1]))
    if range_m < ZOOM_OUT_FROM_M:
        return None
    wins = [win.stepped(dx, dy, k) for dx, dy, k in ZOOM_OUT_STEPS]
    wins = [w for w in wins if w.side_px <= image.shape[0]]
    if not wins:
        return None
    score = reader.fixture_likeness(image, wins)
    uv_first = project(reader.K_frame, reader.points_m, *r.pose())
    for i in np.argsort(-score, kind="stable")[:ZOOM_OUT_TRY]:
        zwin = wins[int(i)]
        r2, w2 = one_pass(image, zwin, R_direct, f, range_m * win.side_px / zwin.side_px)
        if r2 is None or w2 is None or fit_rms_crop_px(r2, w2) > STRONG_FIT_RMS_CROP_PX:
            continue
        if float(np.linalg.norm(r2.pose()[1])) > ZOOM_OUT_MIN_RATIO * range_m:
            continue
        uv = project(reader.K_frame, reader.points_m, *r2.pose())
        if np.all((uv_first >= uv.min(axis=0)) & (uv_first <= uv.max(axis=0))):
            return r2, w2
    return None
