"""Where the fixture is: the crop windows tried in turn until the keypoints give a strong fit.

In order: the window a prediction places (the navigation filter's, or the estimator's own latest
strong fit); SEARCH_STEPS around the direct model's window; then, on a cold start or a lost track
only, the turn stage (the direct model's window turned, TURN_STEPS_DEG), the zoom (smaller windows
inside it, level after level) and the scan of the whole frame. The zoom and the scan (the cold
search) stop at a per-frame crop budget and go on in the next frames (ColdSearch), so that no
cycle nears the MCU's link timeout. A strong fit the search found is read upside down too
(UPRIGHT_TWIN): the network reads a rolled fixture as unrolled.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from oibar.nav.keypoints import CropWindow, PnpResult
from oibar.nav.pose.finder import FixtureFinder
from oibar.nav.pose.finder_place import finder_window
from oibar.nav.pose.fusion import STRONG_FIT_RMS_CROP_PX, Fusion, fit_rms_crop_px, turn_in_window_deg
from oibar.nav.pose.model_file import ModelFileError, export_flag
from oibar.nav.pose.reader import UPRIGHT_FROM_DEG, CropReading, KeypointReader
from oibar.nav.pose.roll import turned_pass, upright_pass
from oibar.nav.pose.scan import scan_pass
from oibar.nav.pose.search_state import ColdSearch, Consider, Fit, FitKeeper
from oibar.nav.pose.zoom_out import bigger_fixture

# Windows tried in turn until the keypoints give a consistent pose: (shift x, shift y) in window
# sides and a size factor, around the direct model's window. The network was trained with the
# fixture up to ~0.25 side off centre and +-25 % in size, so half-side steps leave no gap. Only
# frames where the first window fails pay for the search (~6 % of far validation frames): up to
# 11 passes, about 0.4 s on 2 busy cores. Measured on the validation scenes (every 16th frame):
# mean position error 1.82 % with the first window only, 1.26 % without the diagonal steps,
# 0.95 % with all 11.
SEARCH_STEPS = (
    (0, 0, 1.0),
    (-0.5, 0, 1.0),
    (0.5, 0, 1.0),
    (0, -0.5, 1.0),
    (0, 0.5, 1.0),
    (-0.5, -0.5, 1.0),
    (0.5, -0.5, 1.0),
    (-0.5, 0.5, 1.0),
    (0.5, 0.5, 1.0),
    (0, 0, 0.7),
    (0, 0, 1.4),
)
# When neither the prediction's window nor SEARCH_STEPS give a strong fit, smaller windows inside
# the first pass's one are read in one batch (a half-size 3x3 grid and a quarter-size 5x5 grid,
# steps in the first pass's window sides) and the ZOOM_TRY most keypoint-like (presence, tight
# heat maps) are solved: the first pass can take a far fixture for a near one and put a window
# 5-25x too large around it. Cost: one batch of 34 crops (~0.15-0.25 s on 2 cores), only on
# frames with nothing better and no predicted pose (a cold start or a lost track).
ZOOM_STEPS = tuple(
    (dx, dy, k)
    for k, offs in ((0.5, (-0.25, 0.0, 0.25)), (0.25, (-0.3, -0.15, 0.0, 0.15, 0.3)))
    for dy in offs
    for dx in offs
)
ZOOM_TRY = 3
# The zoom's first level also reads windows twice the first pass's size around it, out to two
# of its sides away (5x5): on an unseen look (validation scene va003's, the demo's approach from
# 10 m) the first pass put the fixture 1.65 window sides off, beyond SEARCH_STEPS' reach, and
# every cold-start frame came out weak until the mission timed out. A fixture-holding double
# window ranks first by its tight heat maps (0.046 vs <= 0.014 for its neighbours and 0.001 for
# background), and the next level zooms into it. 25 more crops in that batch, on cold starts only,
# and only while the double windows stay within WIDE_MAX_SIDE_PX (the frame's height): a first
# pass that took a far fixture for a near one (va012: windows of 250-900 px around a 35-55 px
# fixture) has the scale wrong, not the place, and double windows there ranked the station's
# structure first (va012 tracking 3.4 -> 19 % before this bound).
WIDE_STEPS = tuple((dx, dy, 2.0) for dy in (-2.0, -1.0, 0.0, 1.0, 2.0) for dx in (-2.0, -1.0, 0.0, 1.0, 2.0))
WIDE_MAX_SIDE_PX = 480.0
# When the zoom's windows still give no strong fit, the most fixture-like of them is zoomed into
# the same way, never into windows smaller than ZOOM_MIN_SIDE_PX: the first pass can put a 10 m
# fixture at 0.4 m, a window 10-25x too large (validation scene va012, whose keypoints are read to
# 0.3-0.7 crop px in the right window), which one level (4x) misses.
ZOOM_LEVELS = 3
ZOOM_MIN_SIDE_PX = 24.0  # no zoom window smaller (the fixture's window at ~15 m)
# Crops one cold frame may read through the keypoint network (the hint's and SEARCH_STEPS' count
# but are never cut short; past the budget the zoom and the scan stop and go on in the next
# frames, ColdSearch), so that no cycle nears the MCU's 1 s link timeout: the whole cold search
# reads up to ~480 crops (1 + 11, three zoom levels of 34-59 + 3, the scan's 322 + 6); a frame
# that reaches the scan took 1.8-2.0 s (376 crops, 3 noise frames). A crop costs about the same
# read alone or in a batch: 4.6 ms a single pass (read + PnP), 4.8 ms a crop in a batch of 64
# (307 ms, p90 340), and the first pass 5.6 ms (medians; 2 vCPU Debian, no GPU, onnxruntime 2
# threads, the cores shared with training: upper bounds). With 60 crops the same frames took 7
# cycles each of 290 ms (median; p90 328, at most 336). Fewer would never fit the zoom's first
# batch (59) beside the hint's crop (MIN_COLD_CROP_BUDGET). A frame that runs only SEARCH_STEPS
# (12 crops, ~60 ms) is not affected; nor is the refining pass after a strong fit (outside the
# budget: 1 crop for the shipped model).
COLD_CROP_BUDGET = 60
# The search's stages, in the order a frame may reach them; WindowSearch.last_crops counts the
# crops each read (the window a pose placed; the finder's window and SEARCH_STEPS, after either of
# them the best weak fit read turned upright, for keypoints that read any turn; the turn stage; the
# zoom and the scan, the cold search under its budget; the upside-down check, the zoom-out and the
# refining pass after a strong fit, outside it). What a slow frame spent its time on
# (docs/benchmarks.md).
STAGES = ("placed", "found", "weak_turned", "steps", "turn", "zoom", "scan", "upright", "zoom_out", "refine")
MIN_COLD_CROP_BUDGET = len(ZOOM_STEPS) + len(WIDE_STEPS) + 1  # the largest batch, the hint's crop
# A carried cold search is dropped this long (frame time) after its first frame. Its scores and
# windows stay valid while the fixture barely moves in the image: on the validation scenes it
# moves at most 7 px/s at 6-15 m (median 0.5 px/s), and a scan window holds it within a quarter
# of its 64 px side of its centre, as the keypoint network was trained. The longest search takes
# 10 frames at COLD_CROP_BUDGET, 2.7 s at the ~0.3 s a cold cycle takes in the daemon; the scan's
# scores are then at most 7 frames (1.8 s, 13 px) old when its windows are solved.
COLD_CARRY_MAX_AGE_S = 3.0
# ``oibar.placed_pass_refines``: when tracking, the crop placed by the filter's prediction (or the
# estimator's own latest strong fit) is read as the refining pass is (turned readings, the corner
# step), and a strong fit there ends the frame when its window was well placed (below), instead of
# a plain read followed by a second crop cut around its fit: one network run a tracked frame
# instead of two. Well placed: the window the refining pass would cut around the fit is centred
# within WELL_PLACED_CROP_PX of the placed one (crop px) and its side within
# WELL_PLACED_SIDE_FRAC. On validation a window up to 4 frame px off (13 crop px at 10 m) read as
# well as one on the truth, and one 10-20 px off lost 1 deg beyond 8 m (candidate 0.15.8);
# elsewhere the usual refining pass follows.
WELL_PLACED_CROP_PX = 8.0
WELL_PLACED_SIDE_FRAC = 0.10
WELL_PLACED_ANGLE_DEG = 3.0  # and its turn (reader.UPRIGHT_FROM_DEG) within this of the placed one's


def zoom_steps(wide: bool) -> tuple[tuple[float, float, float], ...]:
    """(dx, dy in base window sides, size factor) of one zoom level's batch."""
    return ZOOM_STEPS + (WIDE_STEPS if wide else ())


class WindowSearch:
    """The search for a strong fit in one frame (`solve`), and the cold search it carries from
    frame to frame (`cold`). Options: `refine_passes` (crops cut around the newest fit, the first
    included), `zoom_search` and `scan_search` (the cold search's two stages),
    `cold_crop_budget` (crops a cold frame may read; None: no budget, for tools that judge frames
    one by one), `zoom_out` (a found fit read again larger: zoom_out.bigger_fixture) and
    `placed_pass_refines` (``oibar.placed_pass_refines``, as the export says unless told)."""

    def __init__(
        self,
        reader: KeypointReader,
        fusion: Fusion,
        range_limits_m: tuple[float, float],
        refine_passes: int = 2,
        zoom_search: bool = True,
        scan_search: bool = True,
        cold_crop_budget: int | None = COLD_CROP_BUDGET,
        placed_pass_refines: bool | None = None,
        zoom_out: bool = True,
        finder: FixtureFinder | None = None,
    ):
        if cold_crop_budget is not None and cold_crop_budget < MIN_COLD_CROP_BUDGET:
            raise ValueError(
                f"cold_crop_budget must be at least {MIN_COLD_CROP_BUDGET} crops (the zoom's first "
                f"batch and the hint's crop), or None; got {cold_crop_budget}"
            )
        self.reader, self.fusion, self.range_limits_m = reader, fusion, range_limits_m
        self.refine_passes = max(1, int(refine_passes))
        self.zoom_search, self.scan_search = bool(zoom_search), bool(scan_search)
        self.cold_crop_budget = cold_crop_budget
        self.zoom_out = bool(zoom_out)
        self.finder = finder
        placed = export_flag(reader.path, reader.meta, "placed_pass_refines", placed_pass_refines)
        if placed and reader.mirror is not None:
            raise ModelFileError(
                f"{reader.path}: oibar.placed_pass_refines cannot go with oibar.mirror_reading: a "
                "predicted window may not hold the fixture, and a crop of anything averaged with its "
                "mirror makes a symmetric pattern that PnP fits well"
            )
        self.placed_pass_refines = placed
        self.cold: ColdSearch | None = None  # a cold search that goes on in the next frames
        # crops each stage read for the frame under way (STAGES)
        self.last_crops: dict[str, int] = {}

    def solve(
        self,
        image: np.ndarray,
        R_direct: np.ndarray,
        T_direct: np.ndarray,
        fusion: dict[str, Any] | None = None,
        prior: tuple[np.ndarray, np.ndarray] | None = None,
        hint: tuple[np.ndarray, np.ndarray] | None = None,
        placed_reading: tuple[CropWindow, CropReading] | None = None,
    ) -> Fit:
        """Crop around the current pose, keypoints, pose (Fusion.fit: PnP, and with the export's
        ``oibar.fusion``, or `fusion` when given, an attitude prior); then `refine_passes - 1`
        more times from the newest pose. The first window is the predicted pose's (`prior`, from
        the navigation filter) when there is one; with `placed_pass_refines` it is read as a
        refining pass, and a strong fit there is final when its window was well placed
        (`_well_placed`). When that gives no strong fit (STRONG_FIT_RMS_CROP_PX), the windows of
        SEARCH_STEPS around the direct model's pose are tried in turn (the direct model can be
        1 m off sideways at 10 m on an unseen scene), then the cold search (`_cold_search`).
        Without a prediction, `hint` (the estimator's own latest strong fit, when the filter has
        not taken it yet) places the first crop instead. The prediction and the hint only place
        a crop, never the attitude prior, so a wrong one cannot feed itself back. The cold
        search stops where the frame's crops would pass `cold_crop_budget` and leaves where it
        stopped (`cold`) for the next call to go on from, without SEARCH_STEPS: a caller that
        solves unrelated frames calls forget() between them, or builds the search without a
        budget. `placed_reading`: (the window the prediction places, its reading), made already
        (the estimator reads it while the direct model runs), so neither is computed again here.
        Returns (PnpResult, its window): the first strong fit, else the best weak one
        (`_weak_rank`), else (None, None)."""
        f = self.fusion.table if fusion is None else fusion
        keep = FitKeeper(self._weak_rank)
        # a cold search carried from earlier frames goes on here; a prediction ends it
        cold = self.cold if prior is None else None
        self.cold = None
        placed = prior if prior is not None else hint
        crops, refined = 0, False  # crops read for this frame (the cold search's budget counts them)
        if placed is not None:
            with self.tally("placed"):
                crops, refined = self._placed_pass(image, placed, placed_reading, R_direct, f, keep)
        # a strong fit in the window a pose placed is upright already (reader.window_for)
        upright_done = keep.best is not None
        # a carried search skips SEARCH_STEPS: they found nothing on its first frame, and the
        # fixture has barely moved since
        if keep.best is None and cold is None:
            steps, cold = self._first_windows(image, R_direct, T_direct, f, keep, cold_start=prior is None)
            crops += steps
        placed_found = keep.best is not None
        if keep.best is None and cold is not None:
            budget = np.inf if self.cold_crop_budget is None else self.cold_crop_budget
            if not self._cold_search(image, cold, R_direct, T_direct, f, keep.consider, budget - crops):
                self.cold = cold  # out of crops: the next frames go on (the estimator flags `searching`)
        if keep.best is None:
            return keep.weak if keep.weak is not None else (None, None)
        # outside the cold search's crop budget, as the refining pass is: at most 1 + 27 crops and
        # 3 passes more (a frame of 60 budgeted crops then takes ~0.5 s, within the link's 1 s)
        read: tuple[CropWindow, CropReading] | None = None  # the refining pass's first, read already
        if not upright_done:
            with self.tally("upright"):
                upright, read = upright_pass(self.reader, self._one_pass, image, keep.best, R_direct, f)
            if upright is not None:
                keep.best, refined = upright, False
        if self.zoom_out and not placed_found:
            with self.tally("zoom_out"):
                bigger = bigger_fixture(self.reader, self._one_pass, image, keep.best, R_direct, f)
            if bigger is not None:
                keep.best, refined = bigger, False
        if refined:
            return keep.best
        with self.tally("refine"):
            return self._refined(image, keep.best, R_direct, f, read)

    @contextmanager
    def tally(self, stage: str) -> Iterator[None]:
        """Count the crops read inside the block as `stage`'s, in `last_crops` (which the
        estimator clears at each frame's start: the placed window can be read before solve)."""
        crops0 = self.reader.crops_read
        try:
            yield
        finally:
            n = self.reader.crops_read - crops0
            if n:
                self.last_crops[stage] = self.last_crops.get(stage, 0) + n

    def _first_windows(
        self,
        image: np.ndarray,
        R_direct: np.ndarray,
        T_direct: np.ndarray,
        f: dict[str, Any] | None,
        keep: FitKeeper,
        cold_start: bool,
    ) -> tuple[int, ColdSearch | None]:
        """The finder's window and SEARCH_STEPS around the direct model's (never cut short: they
        run with a prediction too), each followed by `_weak_turned_pass`, and, on a cold start or
        a lost track (`cold_start`: no prediction), the turn stage: (the crops read before the
        turn stage, the cold search to go on with when none found a strong fit, else None). The
        turn stage's crops are outside the cold search's budget."""
        # the direct model reads every view unrolled: its window stays unturned
        base = self.reader.window_for(R_direct, T_direct, upright=False)
        crops = 0
        read: list[tuple[PnpResult, CropWindow]] = []  # the weak fits read turned upright
        found = finder_window(
            self.finder, image, base, self.reader.margin, ZOOM_MIN_SIDE_PX, self.reader.out_px
        )
        if found is not None:
            with self.tally("found"):
                crops += 1
                keep.consider(
                    *self._one_pass(image, found, R_direct, f, self.reader.range_for_side_m(found.side_px))
                )
            crops += self._weak_turned_pass(image, keep, R_direct, f, read)
            if keep.best is not None:
                return crops, None
        if base is not None:
            with self.tally("steps"):
                crops += self._steps_pass(image, base, R_direct, T_direct, f, keep)
            crops += self._weak_turned_pass(image, keep, R_direct, f, read)
        # the turn stage, the zoom and the scan only on a cold start or a lost track: with a
        # prediction their cost would come out of the 100 ms frame budget on every weak far
        # frame of a healthy track
        if keep.best is not None or not cold_start:
            return crops, None
        if base is not None:
            with self.tally("turn"):
                turned = turned_pass(self.reader, self._one_pass, image, base, R_direct, T_direct, f, keep)
            base = turned if turned is not None else base
        if keep.best is not None:
            return crops, None
        turn_rad = base.angle_rad if base is not None else 0.0  # the scan's too
        if base is not None and self.zoom_search:
            return crops, ColdSearch(level=0, base=base, angle_rad=turn_rad)
        return crops, ColdSearch(level=ZOOM_LEVELS, angle_rad=turn_rad) if self.scan_search else None

    def _placed_pass(
        self,
        image: np.ndarray,
        placed: tuple[np.ndarray, np.ndarray],
        placed_reading: tuple[CropWindow, CropReading] | None,
        R_direct: np.ndarray,
        f: dict[str, Any] | None,
        keep: FitKeeper,
    ) -> tuple[int, bool]:
        """The window a predicted pose (or the hint) places: (crops read, whether its strong,
        well-placed refining read is final)."""
        win_p = placed_reading[0] if placed_reading is not None else self.reader.window_for(*placed)
        if win_p is None:
            return 0, False
        r, pwin = self._one_pass(
            image,
            win_p,
            R_direct,
            f,
            float(np.linalg.norm(placed[1])),
            refining=self.placed_pass_refines,
            reading=placed_reading[1] if placed_reading is not None else None,
        )
        return 1, keep.consider(r, pwin) and self.placed_pass_refines and self._well_placed(r, pwin)

    def _steps_pass(
        self,
        image: np.ndarray,
        base: CropWindow,
        R_direct: np.ndarray,
        T_direct: np.ndarray,
        f: dict[str, Any] | None,
        keep: FitKeeper,
    ) -> int:
        """SEARCH_STEPS' windows around the direct model's, in turn until a strong fit: crops read."""
        crops = 0
        for dx, dy, k in SEARCH_STEPS:
            crops += 1
            r, win = self._one_pass(
                image, base.stepped(dx, dy, k), R_direct, f, float(np.linalg.norm(T_direct)) / k
            )
            if keep.consider(r, win):
                break
        return crops

    def _weak_turned_pass(
        self,
        image: np.ndarray,
        keep: FitKeeper,
        R_direct: np.ndarray,
        f: dict[str, Any] | None,
        read: list[tuple[PnpResult, CropWindow]],
    ) -> int:
        """Keypoints that read any turn (``oibar.keypoints_any_turn``) place a turned fixture
        right in a window not turned to it, but less tightly than upright: on the roll sweep
        val_roll, 0.35.18's fits there at 60-180 deg of roll and 7-10 m came out 0.2-2.9 % / 1-6 deg
        off yet weak, and each such cold frame then ran the turn stage and the zoom (50-100 crops,
        0.4-0.5 s). With no strong fit yet, the best weak fit, where it shows the fixture turned
        beyond UPRIGHT_FROM_DEG in its window, has the window it turns upright read once, as the
        refining pass reads it (`read`: the weak fits so read, for this frame): crops read."""
        if keep.best is not None or keep.weak is None or not self.fusion.keypoints_any_turn:
            return 0
        if any(w is keep.weak for w in read):
            return 0
        read.append(keep.weak)
        r, win = keep.weak
        R, T = r.pose()
        if turn_in_window_deg(self.reader.K_frame, R, T, win) <= UPRIGHT_FROM_DEG:
            return 0
        upright = self.reader.window_for(R, T)
        if upright is None:
            return 0
        with self.tally("weak_turned"):
            keep.consider(
                *self._one_pass(image, upright, R_direct, f, float(np.linalg.norm(T)), refining=True)
            )
        return 1

    def _refined(
        self,
        image: np.ndarray,
        best: tuple[PnpResult, CropWindow],
        R_direct: np.ndarray,
        f: dict[str, Any] | None,
        read: tuple[CropWindow, CropReading] | None = None,
    ) -> tuple[PnpResult, CropWindow]:
        """`refine_passes - 1` crops cut around the newest strong fit, while they stay strong;
        `read`: a window and its refining reading made already (the upright check's), used when
        the first of them is that window."""
        reader = self.reader
        for _ in range(self.refine_passes - 1):
            R_best, T_best = best[0].pose()
            around = reader.window_for(R_best, T_best)
            if around is None:
                break
            reading = read[1] if read is not None and read[0] == around else None
            read = None
            r, rwin = self._one_pass(
                image, around, R_direct, f, float(np.linalg.norm(T_best)), refining=True, reading=reading
            )
            if r is None or rwin is None or fit_rms_crop_px(r, rwin) > STRONG_FIT_RMS_CROP_PX:
                break
            best = (r, rwin)
        return best

    def forget(self) -> None:
        """Drop a carried cold search."""
        self.cold = None

    def _one_pass(
        self,
        image: np.ndarray,
        win: CropWindow,
        R_direct: np.ndarray,
        f: dict[str, Any] | None,
        range_m: float,
        refining: bool = False,
        reading: CropReading | None = None,
    ) -> Fit:
        """One window to a fit; `reading`: this window's read_crop(image, win, refining), if
        made already."""
        reader = self.reader
        if reading is None:
            reading = reader.read_crop(image, win, refining)
        uv = reading.uv_px
        if refining:
            uv = reader.refined_corners(image, win, uv)
        r = self.fusion.fit(uv, win, R_direct, reading.R_cam_target_head, range_m, f)
        if not r.ok:
            return None, None
        untouched = reading.untouched_uv_px  # set only by a refining pass's turned reading
        if self.fusion.turned_reading_measurement == "untouched" and untouched is not None and f:
            # a fit with the prior: its prior-free twin (the filter's measurement) from the untouched
            # window's keypoints, with the same corner step (TURNED_READING_MEASUREMENTS)
            r.no_prior = self.fusion.fit_without_prior(reader.refined_corners(image, win, untouched), win)
        return r, win

    def _well_placed(self, r: PnpResult | None, win: CropWindow | None) -> bool:
        """Whether `win` is where the refining pass would have cut it around the fit `r`
        (WELL_PLACED_CROP_PX, WELL_PLACED_SIDE_FRAC): then its refining read is final."""
        if r is None or win is None:
            return False
        around = self.reader.window_for(*r.pose())
        if around is None:
            return False
        off_crop_px = float(np.hypot(*np.subtract(around.center_px, win.center_px))) * win.scale
        turn_rad = float(np.angle(np.exp(1j * (around.angle_rad - win.angle_rad))))
        return (
            off_crop_px <= WELL_PLACED_CROP_PX
            and abs(around.side_px / win.side_px - 1.0) <= WELL_PLACED_SIDE_FRAC
            and abs(turn_rad) <= np.radians(WELL_PLACED_ANGLE_DEG)
        )

    def _weak_rank(self, r: PnpResult, win: CropWindow) -> tuple[bool, float]:
        """Which weak fit to return when no strong one is found: one inside the range envelope
        before any outside it (a tiny zoom window can fit noise at 40 m with a lower RMS), then
        the lowest RMS."""
        range_m = float(np.linalg.norm(r.pose()[1]))
        inside = self.range_limits_m[0] <= range_m <= self.range_limits_m[1]
        return (not inside, fit_rms_crop_px(r, win))

    def _zoom_windows(
        self, image: np.ndarray, base: CropWindow, wide: bool = False
    ) -> list[tuple[CropWindow, float]]:
        """ZOOM_STEPS' windows (and WIDE_STEPS' with `wide`) read in one batch; the ZOOM_TRY
        that look most like the fixture (KeypointReader.fixture_likeness) with their size
        factors, best first."""
        wins = self._zoom_candidates(base, wide)
        if not wins:
            return []
        score = self.reader.fixture_likeness(image, [w for w, _ in wins])
        return [wins[i] for i in np.argsort(-score)[:ZOOM_TRY]]

    def _zoom_candidates(self, base: CropWindow, wide: bool) -> list[tuple[CropWindow, float]]:
        """The windows (with their size factors) one zoom level reads around `base`."""
        return [
            (base.stepped(dx, dy, k), k)
            for dx, dy, k in zoom_steps(wide)
            if base.side_px * k >= ZOOM_MIN_SIDE_PX  # smaller than a fixture within the envelope
        ]

    def _cold_search(
        self,
        image: np.ndarray,
        c: ColdSearch,
        R_direct: np.ndarray,
        T_direct: np.ndarray,
        f: dict[str, Any] | None,
        consider: Consider,
        crops_left: float,
    ) -> bool:
        """Go on with the cold search `c`: the zoom's levels (`_zoom_windows`), then the scan
        (oibar.nav.pose.scan: fixed windows over the whole frame, the most fixture-like solved).
        True when it is over (`consider` kept a strong fit, or nothing is left to try); False
        when the next read would take more than `crops_left` crops: `c` then says where to go
        on."""
        if c.level < ZOOM_LEVELS:
            with self.tally("zoom"):
                done, crops_left = self._zoom(image, c, R_direct, T_direct, f, consider, crops_left)
            if done is not None:
                return done
        if not self.scan_search:
            return True
        with self.tally("scan"):
            return scan_pass(self.reader, self._one_pass, image, c, R_direct, f, consider, crops_left)

    def _zoom(
        self,
        image: np.ndarray,
        c: ColdSearch,
        R_direct: np.ndarray,
        T_direct: np.ndarray,
        f: dict[str, Any] | None,
        consider: Consider,
        crops_left: float,
    ) -> tuple[bool | None, float]:
        """The zoom's levels from where `c` stands: (True: a strong fit; False: out of crops;
        None: the zoom is over, on to the scan, with the crops left)."""
        range_m = float(np.linalg.norm(T_direct))
        while c.level < ZOOM_LEVELS:
            assert c.base is not None
            if c.ranked is None:
                wide = c.level == 0 and c.base.side_px * 2.0 <= WIDE_MAX_SIDE_PX
                n = len(self._zoom_candidates(c.base, wide))
                if n > crops_left:
                    return False, crops_left
                crops_left -= n
                c.ranked = self._zoom_windows(image, c.base, wide=wide)
            while c.tried < len(c.ranked):
                if crops_left < 1:
                    return False, crops_left
                crops_left -= 1
                zwin, k = c.ranked[c.tried]
                c.tried += 1
                if consider(*self._one_pass(image, zwin, R_direct, f, range_m / (c.k_base * k))):
                    return True, crops_left
            if c.ranked and c.level + 1 < ZOOM_LEVELS:  # zoom again, into the most fixture-like
                c.level, c.base, c.k_base = c.level + 1, c.ranked[0][0], c.k_base * c.ranked[0][1]
                c.ranked, c.tried = None, 0
            else:  # on to the scan
                c.level, c.base, c.ranked, c.tried = ZOOM_LEVELS, None, None, 0
        return None, crops_left
