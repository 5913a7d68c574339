"""The keypoint estimator (issue 15): the direct model (the first pass, a file beside the keypoint
model named by ``oibar.first_pass``) places a crop at full resolution around the fixture; the
keypoint network finds the fixture's known points in it (reader); PnP turns them into the pose
(fusion); windows are tried until one gives a strong fit (search). A second crop around that pose
refines it. The direct answer stays as the cross-check (gross disagreement lowers confidence) and
the fallback (when PnP finds no consistent pose, with low confidence and a flag saying so).
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from oibar.geometry.rotations import matrix_to_quat, rotation_angle_deg
from oibar.nav.fit_history import FitHistory
from oibar.nav.keypoints import CropWindow, PnpResult
from oibar.nav.pose.direct import DEFAULT_DEFECT_SCALE, PoseEstimator
from oibar.nav.pose.finder import FixtureFinder
from oibar.nav.pose.frames import FrameError, check_time, is_blank
from oibar.nav.pose.fusion import STRONG_FIT_RMS_CROP_PX, Fusion, fit_rms_crop_px, measurement_without_prior
from oibar.nav.pose.model_file import ModelFileError, range_limits, read_metadata
from oibar.nav.pose.reader import CropReading, KeypointReader
from oibar.nav.pose.result import PoseEstimate, no_answer
from oibar.nav.pose.search import COLD_CARRY_MAX_AGE_S, COLD_CROP_BUDGET, WindowSearch

# The PnP answer and the direct model's must agree this well (position difference / range,
# attitude difference); the direct model's own error is ~10-15 % on unseen scenes, so only a
# gross disagreement (a PnP on the wrong points) is flagged.
DISAGREE_POS_FRACTION = 0.5
DISAGREE_ATT_DEG = 20.0
# Reprojection RMS (crop pixels) at which confidence falls to exp(-1/2): a few times the
# keypoints' typical error on validation scenes.
REPROJ_SCALE_CROP_PX = 3.0
# Confidence factor of an answer the search could not make strong: the direct model's when PnP
# has none, a weak fit, a fit the direct model grossly disagrees with.
FALLBACK_FACTOR = 0.3
REQUIRED_METADATA = ("keypoints_3d_m", "crop", "pnp", "camera", "first_pass")


def _checked_prior(prior: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """A usable predicted pose or None: a rotation and a finite translation in front of the camera."""
    if prior is None:
        return None
    try:
        R = np.asarray(prior[0], float).reshape(3, 3)
        T = np.asarray(prior[1], float).reshape(3)
    except (TypeError, ValueError, IndexError) as exc:
        raise ValueError(f"prior must be (R_cam_target 3x3, T_cam_target_m 3), got {prior!r}") from exc
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(T))) or T[2] <= 0:
        return None
    if abs(np.linalg.det(R) - 1.0) > 1e-3 or not np.allclose(R.T @ R, np.eye(3), atol=1e-3):
        return None
    return R, T


class KeypointPoseEstimator(PoseEstimator):
    """Keypoints + PnP: ``estimate(frame, t_s, prior)`` as for any PoseEstimator. Its parts:
    `first` (the direct model), `reader` (KeypointReader), `fusion` (Fusion), `search`
    (WindowSearch) and `fit_history` (recent strong fits: a run of them can overrule the direct
    model). The options below override what the export chose, for studies."""

    uses_prior = True

    def __init__(
        self,
        path: str | Path,
        threads: int = 2,
        warmup_runs: int = 3,
        range_limits_m: tuple[float, float] | None = None,
        defect_scale: float = DEFAULT_DEFECT_SCALE,
        allow_spinning: bool = False,
        mirror: bool | None = None,
        turned_reading_deg: float | None = None,
        turned_reading_head: bool | None = None,
        turned_reading_measurement: str | None = None,
        cold_crop_budget: int | None = COLD_CROP_BUDGET,
        corner_refine_side_px: float | None = None,
        placed_pass_refines: bool | None = None,
        overlap_first_pass: bool = True,
        upright: bool = True,
        finder: bool | None = None,
    ):
        self.path = Path(path)
        # When a prediction (or the latest strong fit) places the first crop, the direct model
        # runs on a second thread while that crop is read: each network leaves most of the second
        # core idle at batch 1 (no spinning workers), and the crop does not need the direct answer
        # to be cut. The same computations, so the same pose; only sooner.
        self.overlap_first_pass = bool(overlap_first_pass)
        self._first_pass_thread: tuple[int, ThreadPoolExecutor] | None = None  # (its process id, the thread)
        self.meta = read_metadata(self.path)
        for key in REQUIRED_METADATA:
            if key not in self.meta:
                raise ModelFileError(f"{self.path}: keypoint model without oibar.{key} metadata")
        first = self.path.parent / self.meta["first_pass"]
        if not first.is_file():
            raise ModelFileError(
                f"{self.path}: its first-pass model {first.name} is missing (it must lie beside it)"
            )
        self.first = PoseEstimator(first, threads, warmup_runs, range_limits_m, defect_scale, allow_spinning)
        if isinstance(self.first, KeypointPoseEstimator):
            raise ModelFileError(f"{first}: a first-pass model must be a direct model")
        self.size_wh = tuple(self.meta["input_size_wh"])
        cam = self.meta["camera"]
        self.frame_wh = (int(cam["width_px"]), int(cam["height_px"]))
        self.K_frame = np.array(cam["K_frame"], float)
        self.range_limits_m = range_limits(self.meta, range_limits_m)
        self.defect_scale = float(defect_scale)
        self.fit_history = FitHistory()
        self.reader = KeypointReader(
            self.path,
            self.meta,
            threads,
            allow_spinning,
            mirror=mirror,
            turned_reading_deg=turned_reading_deg,
            turned_reading_head=turned_reading_head,
            corner_refine_side_px=corner_refine_side_px,
            upright=upright,
        )
        self.fusion = Fusion(
            self.path,
            self.meta,
            self.reader.points_m,
            self.reader.K_frame,
            self.reader.reproj_crop_px,
            has_head=self.reader.R_att_ref is not None,
            turned_reading_measurement=turned_reading_measurement,
            R_att_ref=self.reader.R_att_ref,
        )
        self.search = WindowSearch(
            self.reader,
            self.fusion,
            self.range_limits_m,
            cold_crop_budget=cold_crop_budget,
            placed_pass_refines=placed_pass_refines,
            finder=self._open_finder(finder, threads, allow_spinning),
        )
        self.reader.open_far_network(threads, allow_spinning)
        self.reader.warm_up(warmup_runs)

    def run(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Prepared crops (N, 3, S, S) float32 in [0, 1] -> the keypoint network's outputs by name."""
        return self.reader.run(x)

    def check_frame(self, image: Any) -> None:
        self.first.check_frame(image)
        h, w = image.shape[:2]
        if (w, h) != self.frame_wh:
            raise FrameError(
                f"frame {w}x{h}: the keypoint model works in the camera's own pixels, "
                f"{self.frame_wh[0]}x{self.frame_wh[1]}"
            )

    def forget(self) -> None:
        self.fit_history.forget()
        self.search.forget()

    def _open_finder(self, use: bool | None, threads: int, allow_spinning: bool) -> FixtureFinder | None:
        """``oibar.finder`` ({"file": NAME}): the fixture finder, a file beside this one, that
        places one crop before SEARCH_STEPS (finder_place.FINDER_*). `use` False leaves it closed
        (studies); True requires one."""
        spec = self.meta.get("finder")
        if use is False or (spec is None and use is None):
            return None
        if spec is None:
            raise ModelFileError(f"{self.path}: no oibar.finder to use")
        name = spec.get("file") if isinstance(spec, dict) else None
        if not isinstance(name, str) or Path(name).name != name or not (self.path.parent / name).is_file():
            raise ModelFileError(
                f"{self.path}: its fixture finder {spec!r} is missing (oibar.finder {{'file': NAME}}, "
                "a file beside it)"
            )
        finder = FixtureFinder(self.path.parent / name, threads, allow_spinning)
        if finder.frame_wh != self.frame_wh:
            raise ModelFileError(
                f"{finder.path}: reads {finder.frame_wh} frames, this model's camera gives {self.frame_wh}"
            )
        return finder

    def _first_pass_pool(self) -> ThreadPoolExecutor:
        """The direct model's thread, made on first use in this process: a process forked from
        one that used it inherits the executor but not its thread, and would wait forever."""
        if self._first_pass_thread is None or self._first_pass_thread[0] != os.getpid():
            pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="oibar-first-pass")
            self._first_pass_thread = (os.getpid(), pool)
        return self._first_pass_thread[1]

    def estimate(
        self,
        image_rgb_uint8: np.ndarray,
        t_s: float = 0.0,
        prior: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> PoseEstimate:
        """One frame -> pose; `prior` (R_cam_target, T_cam_target_m), the pose predicted for this
        frame (the daemon passes its filter's), places the first crop (WindowSearch.solve). The
        answer's `crops` counts the crops it read; `last_crops` says which stage read them."""
        crops0 = self.reader.crops_read
        self.search.last_crops = {}
        est = self._estimate(image_rgb_uint8, t_s, prior)
        est.crops = self.reader.crops_read - crops0
        return est

    @property
    def last_crops(self) -> dict[str, int]:
        """The crops each stage of the search (search.STAGES) read for the latest frame."""
        return dict(self.search.last_crops)

    def _estimate(
        self,
        image_rgb_uint8: np.ndarray,
        t_s: float,
        prior: tuple[np.ndarray, np.ndarray] | None,
    ) -> PoseEstimate:
        check_time(t_s)
        image_rgb_uint8 = self.canonical_frame(image_rgb_uint8)
        self.check_frame(image_rgb_uint8)
        prior = _checked_prior(prior)
        t0 = time.perf_counter()
        self.fit_history.advance(float(t_s))
        # a cold search carried from earlier frames goes on while its scores still hold, and never
        # across a frame whose time does not advance (a new sequence)
        cold = self.search.cold
        if cold is not None and not cold.t_last_s < t_s <= cold.t_first_s + COLD_CARRY_MAX_AGE_S:
            self.search.forget()
        if is_blank(image_rgb_uint8):
            return no_answer(t_s, (time.perf_counter() - t0) * 1e3, "blank_frame")
        # without a prediction, the estimator's own latest strong fit places the first crop: the
        # filter waits for a run of them (fit_history) when the direct model disagrees, and each
        # cold frame would otherwise pay for the whole search again
        hint = self.fit_history.latest() if prior is None else None
        direct, placed_reading = self._first_pass(image_rgb_uint8, t_s, prior if prior is not None else hint)
        if not direct.finite or direct.confidence <= 0.0:
            direct.latency_ms = (time.perf_counter() - t0) * 1e3
            direct.flags = tuple(direct.flags) + ("no_first_pass",)
            return direct
        r, win = self.search.solve(
            image_rgb_uint8,
            direct.R_cam_target,
            direct.T_cam_target_m,
            prior=prior,
            hint=hint,
            placed_reading=placed_reading,
        )
        # the cold search ran out of this frame's crops and goes on in the next frames: the answer
        # (no strong fit, so its confidence is already low) is provisional
        searching: tuple[str, ...] = ()
        if self.search.cold is not None:
            searching = ("searching",)
            if np.isnan(self.search.cold.t_first_s):
                self.search.cold.t_first_s = float(t_s)
            self.search.cold.t_last_s = float(t_s)
        if r is None or win is None:
            direct.latency_ms = (time.perf_counter() - t0) * 1e3
            direct.confidence *= FALLBACK_FACTOR
            direct.flags = tuple(direct.flags) + ("pnp_failed", "fallback_direct") + searching
            return direct
        return self._answer(r, win, direct, float(t_s), t0, searching)

    def _first_pass(
        self, image: np.ndarray, t_s: float, placed: tuple[np.ndarray, np.ndarray] | None
    ) -> tuple[PoseEstimate, tuple[CropWindow, CropReading] | None]:
        """The direct model's answer and, when a pose places the first crop, that crop's reading,
        made on the direct model's thread meanwhile (`overlap_first_pass`)."""
        pool = self._first_pass_pool() if self.overlap_first_pass else None
        win_p = self.reader.window_for(*placed) if pool is not None and placed is not None else None
        if pool is None or win_p is None:
            return self.first.estimate(image, t_s), None
        job = pool.submit(self.first.estimate, image, t_s)
        try:
            with self.search.tally("placed"):  # the placed crop, read while the direct model runs
                placed_reading = (win_p, self.reader.read_crop(image, win_p, self.search.placed_pass_refines))
        finally:
            direct = job.result()  # never leave it running into the next frame
        return direct, placed_reading

    def _answer(
        self,
        r: PnpResult,
        win: CropWindow,
        direct: PoseEstimate,
        t_s: float,
        t0: float,
        searching: tuple[str, ...],
    ) -> PoseEstimate:
        """The search's fit as the frame's answer: its confidence lowered by the plausibility
        checks, the reprojection, a weak fit and a gross disagreement with the direct model
        (unless a run of strong fits overrules it), each flagged."""
        R, T = r.pose()
        latency_ms = (time.perf_counter() - t0) * 1e3
        conf, rng_m, _, checks = self.plausibility(T, R, None)
        flags = list(checks)
        rms_crop = fit_rms_crop_px(r, win)
        conf *= float(np.exp(-0.5 * (rms_crop / REPROJ_SCALE_CROP_PX) ** 2))
        if rms_crop > REPROJ_SCALE_CROP_PX:
            flags.append("reprojection")
        if rms_crop > STRONG_FIT_RMS_CROP_PX:  # the search found nothing better
            conf *= FALLBACK_FACTOR
            flags.append("weak_fit")
        flags += searching
        dpos = float(np.linalg.norm(T - direct.T_cam_target_m)) / max(rng_m, 1e-6)
        datt = rotation_angle_deg(R.T @ direct.R_cam_target)
        strong = rms_crop <= STRONG_FIT_RMS_CROP_PX
        if dpos > DISAGREE_POS_FRACTION or datt > DISAGREE_ATT_DEG:
            # one frame cannot tell which is wrong; a run of strong fits that agree can (fit_history)
            if strong and self.fit_history.confirmed(t_s, T, R):
                flags.append("direct_overruled")
            else:
                conf *= FALLBACK_FACTOR
                flags.append("direct_disagrees")
        if strong:
            self.fit_history.add(t_s, T, R)
        T_meas, R_meas = (
            measurement_without_prior(r, T, R)
            if self.fusion.filter_measurement == "prior_free"
            else (None, None)
        )
        return PoseEstimate(
            T_cam_target_m=T,
            q_cam_target=matrix_to_quat(R),
            R_cam_target=R,
            t_s=t_s,
            latency_ms=latency_ms,
            confidence=float(np.clip(conf, 0.0, 1.0)),
            camera_range_m=rng_m,
            ortho_defect=0.0,
            flags=tuple(flags),
            T_meas_cam_target_m=T_meas,
            R_meas_cam_target=R_meas,
        )

    def __call__(self, frame: Image.Image | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        e = self.estimate(np.asarray(frame))
        return e.T_cam_target_m, e.q_cam_target

    def predict_batch(self, frames_uint8_small: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise TypeError("a keypoint model has no batch interface on resized frames; use estimate(frame)")
