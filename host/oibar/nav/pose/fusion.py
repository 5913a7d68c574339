"""Keypoints to a pose: PnP, leaning on an attitude prior (the direct model's, or the crop's own
attitude head) as the export's ``oibar.fusion`` says, with its error tables; the quality of a fit;
what the navigation filter is handed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from oibar.geometry.docking import tilt_scaled
from oibar.geometry.rotations import rotation_angle_deg
from oibar.nav.error_models import (
    HeadCropGainModel,
    HeadGainModel,
    KeypointErrorModel,
    PriorErrorModel,
    PriorSigmaScale,
)
from oibar.nav.keypoints import (
    CropWindow,
    PnpResult,
    attitude_from_crop,
    attitude_in_crop_deg,
    bearing_in_crop_deg,
    image_roll_rad,
    map_pose,
    solve_pnp,
)
from oibar.nav.pose.model_file import ModelFileError
from oibar.nav.pose.reader import CROP_REF_PX

MIN_INLIERS = 5
# A fit whose keypoints miss their reprojection by more than this (RMS, crop px) is weak: on the
# validation scenes (every 31st frame, 228 fits) every fit within 5 % of the truth had an RMS of
# at most 0.90 crop px (p99 0.84) and every fit off by more than 5 % had at least 1.38 (a shadowed
# scene where the first pass takes a 10 m fixture for a 0.5 m one and the keypoint network draws
# a "fixture" on the station's structure). A weak fit does not stop the search; if no strong fit
# is found it is returned with lowered confidence and the flag `weak_fit`.
STRONG_FIT_RMS_CROP_PX = 1.2
ATTITUDE_PRIORS = ("direct", "head")  # oibar.fusion.attitude_prior: whose attitude the fit leans on
# The prior-free fit is handed to the filter only while it stays near the fused one: beyond these
# it is a gross PnP failure (a far frame's mirrored pose), not the prior's bias, which is ~0.5-2
# deg and ~1 % of the range on the validation scenes.
MEAS_MAX_ATT_DEV_DEG = 10.0
MEAS_MAX_POS_DEV_FRACTION = 0.10
# What the filter is fed (``oibar.filter_measurement``, chosen per network on the closed loop):
# "prior_free" (the default: the attitude head pulls every frame's tilt toward aligned alike) or
# "fused" (the pose itself: a network whose head is better than PnP alone at range).
FILTER_MEASUREMENTS = ("prior_free", "fused")
# Whose keypoints the filter's prior-free fit is solved from when the refining pass reads turned
# windows (``oibar.turned_reading_measurement``): "mean", the averaged ones the answer is fitted to,
# or "untouched", the untouched window's alone. At range that fit's tilt rests on hundredths of a
# pixel, and the average shifts every keypoint's bias by a few: 0.15.6 moved the measurement's
# signed attitude bias by 0.07-0.10 deg on validation and lost the loop on one turn, while its
# answer gained.
TURNED_READING_MEASUREMENTS = ("mean", "untouched")
# Keypoints that read any turn (``oibar.keypoints_any_turn``: a network fine-tuned with a share of
# its crops turned by any angle, oibar_models' roll_share). In a window not turned to a rolled
# fixture its keypoints are right, but its attitude head, and the direct model, read every view
# as near upright: their prior pulls the fit toward the wrong roll and its keypoints out of their
# reprojection gate. On the roll sweep val_roll (cold, each frame alone), candidate 0.35.16 read
# keypoints within 1.0-1.4 crop px of the truth in unturned windows at 30-180 deg of roll, yet
# ended PnP failed or weak on most frames from 90 deg. So where PnP alone has the fixture turned
# in its window by more than PRIOR_MAX_TURN_DEG, the fit is PnP alone, and the refining pass reads
# a window that this pose turns upright (reader.window_for), where the prior holds. 30 deg: the
# head was trained on turns of +-15 deg and reads to ~20 (docs/model_card.md, "Rolled approaches").
PRIOR_MAX_TURN_DEG = 30.0


def turn_in_window_deg(
    K: np.ndarray, R_cam_target: np.ndarray, T_cam_target_m: np.ndarray, win: CropWindow
) -> float:
    """How far a fixture at this pose shows turned from upright in the window `win` (deg, 0..180;
    0 where it projects nowhere): its image roll plus the window's own turn."""
    roll = image_roll_rad(K, R_cam_target, T_cam_target_m)
    if not np.isfinite(roll):
        return 0.0
    return float(abs(np.degrees(np.angle(np.exp(1j * (roll + win.angle_rad))))))


def fit_rms_crop_px(r: PnpResult, win: CropWindow) -> float:
    """A fit's reprojection RMS over its inliers, in pixels of a CROP_REF_PX crop (for the shipped
    128 px models: the crop's own pixels)."""
    return float(r.rms_px) * win.scale * CROP_REF_PX / win.out_px


def measurement_without_prior(
    r: PnpResult, T: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The fit's prior-free pose (r.no_prior) for a filter, or (None, None) when the fit had no
    prior, PnP alone failed, or it lies grossly off the fused pose (MEAS_MAX_*)."""
    alone = r.no_prior
    if alone is None or not alone.ok:
        return None, None
    R_a, T_a = alone.pose()
    range_m = float(np.linalg.norm(T))
    if float(np.linalg.norm(T_a - T)) > MEAS_MAX_POS_DEV_FRACTION * range_m:
        return None, None
    if rotation_angle_deg(R_a.T @ R) > MEAS_MAX_ATT_DEV_DEG:
        return None, None
    return np.asarray(T_a, float), np.asarray(R_a, float)


class Fusion:
    """The export's fusion (``oibar.fusion``: the keypoints' and the prior's sigmas, their error
    tables by range, whose attitude is the prior, the head's gain (in the docking frame, or in
    its crop), the prior's chosen scale) and what the filter is fed (``oibar.filter_measurement``,
    ``oibar.turned_reading_measurement``), checked when the estimator is built. `fit` also takes
    another fusion table (a study's), read the same way. `R_att_ref`: the attitude head's
    reference (KeypointReader.R_att_ref), which a crop gain needs to read the head in its crop."""

    def __init__(
        self,
        path: Path,
        meta: dict[str, Any],
        points_m: np.ndarray,
        K_frame: np.ndarray,
        reproj_crop_px: float,
        has_head: bool,
        turned_reading_measurement: str | None = None,
        R_att_ref: np.ndarray | None = None,
    ):
        self.path, self.points_m, self.K_frame = path, points_m, K_frame
        self.R_att_ref = None if R_att_ref is None else np.asarray(R_att_ref, float)
        self.reproj_crop_px = reproj_crop_px
        self._tables: dict[str, tuple[Any, Any]] = {}
        f = meta.get("fusion") or {}
        self.table: dict[str, Any] | None = meta.get("fusion")
        # a malformed table fails here, not in flight
        if f.get("kp_error_model"):
            self.error_model(f)
        if f.get("prior_error_model"):
            self.prior_error_model(f)
        if f.get("head_gain"):
            self.head_gain(f)
        if f.get("prior_sigma_scale"):
            if f.get("sigma_prior_deg") is None:
                raise ModelFileError(f"{path}: its fusion scales the prior's sigma but has no prior")
            self.prior_sigma_scale(f)
        meas = (
            meta.get("turned_reading_measurement", "mean")
            if turned_reading_measurement is None
            else turned_reading_measurement
        )
        if meas not in TURNED_READING_MEASUREMENTS:
            raise ModelFileError(
                f"{path}: oibar.turned_reading_measurement must be one of "
                f"{TURNED_READING_MEASUREMENTS}, got {meas!r}"
            )
        self.turned_reading_measurement = meas
        any_turn = meta.get("keypoints_any_turn", False)
        if not isinstance(any_turn, bool):
            raise ModelFileError(f"{path}: oibar.keypoints_any_turn must be true or false, got {any_turn!r}")
        self.keypoints_any_turn = any_turn
        self.filter_measurement = meta.get("filter_measurement", "prior_free")
        if self.filter_measurement not in FILTER_MEASUREMENTS:
            raise ModelFileError(
                f"{path}: oibar.filter_measurement must be one of {FILTER_MEASUREMENTS}, "
                f"got {self.filter_measurement!r}"
            )
        if f.get("attitude_prior", "direct") not in ATTITUDE_PRIORS:
            raise ModelFileError(
                f"{path}: oibar.fusion.attitude_prior must be one of {ATTITUDE_PRIORS}, "
                f"got {f['attitude_prior']!r}"
            )
        if f.get("attitude_prior") == "head" and not has_head:
            raise ModelFileError(f"{path}: its fusion asks for the attitude head, which it lacks")
        if f.get("head_gain") and f.get("attitude_prior") != "head":
            raise ModelFileError(f"{path}: its fusion has a head gain but its prior is not the attitude head")
        if f.get("head_crop_gain"):
            if f.get("attitude_prior") != "head":
                raise ModelFileError(
                    f"{path}: its fusion has a head crop gain but its prior is not the attitude head"
                )
            if f.get("head_gain"):
                raise ModelFileError(
                    f"{path}: its fusion has both a head gain and a head crop gain: one correction of the head, not two"
                )
            if self.R_att_ref is None:
                raise ModelFileError(
                    f"{path}: its fusion has a head crop gain but no attitude head reference"
                )
            self.head_crop_gain(f)

    # ------------------------------------------------------------------ the tables
    def _fusion_table(self, f: dict[str, Any], key: str, build: Any) -> Any:
        """`build(f[key])`, made once per table and held (holding the table keeps its identity
        from being reused); a malformed table is a ModelFileError naming the file."""
        table = f[key]
        if key not in self._tables or self._tables[key][0] is not table:
            try:
                self._tables[key] = (table, build(table))
            except (KeyError, TypeError, ValueError) as exc:
                raise ModelFileError(f"{self.path}: oibar.fusion.{key} is malformed ({exc})") from exc
        return self._tables[key][1]

    def error_model(self, f: dict[str, Any]) -> KeypointErrorModel:
        """The fusion's KeypointErrorModel (one row per keypoint of this model)."""
        model: KeypointErrorModel = self._fusion_table(f, "kp_error_model", KeypointErrorModel)
        if model.rms_crop_px.shape[0] != len(self.points_m):
            raise ModelFileError(
                f"{self.path}: oibar.fusion.kp_error_model has {model.rms_crop_px.shape[0]} "
                f"keypoints, the model {len(self.points_m)}"
            )
        return model

    def prior_error_model(self, f: dict[str, Any]) -> PriorErrorModel:
        """The fusion's PriorErrorModel."""
        model: PriorErrorModel = self._fusion_table(f, "prior_error_model", PriorErrorModel)
        return model

    def head_gain(self, f: dict[str, Any]) -> HeadGainModel:
        """The fusion's HeadGainModel."""
        model: HeadGainModel = self._fusion_table(f, "head_gain", HeadGainModel)
        return model

    def head_crop_gain(self, f: dict[str, Any]) -> HeadCropGainModel:
        """The fusion's HeadCropGainModel."""
        model: HeadCropGainModel = self._fusion_table(f, "head_crop_gain", HeadCropGainModel)
        return model

    def head_prior(
        self, R_head: np.ndarray, win: CropWindow, range_m: float, f: dict[str, Any]
    ) -> np.ndarray:
        """The head's attitude as the fit's prior: as read, or given back what it shrank by (the
        fusion's head gain in the docking frame, or its crop gain in the crop it was read in)."""
        if f.get("head_gain"):
            return tilt_scaled(R_head, 1.0 / self.head_gain(f).gain(range_m))
        if f.get("head_crop_gain") and self.R_att_ref is not None:
            att = attitude_in_crop_deg(win, self.K_frame, R_head, self.R_att_ref)
            att[:2] = self.head_crop_gain(f).correct(
                att[:2], bearing_in_crop_deg(win, self.K_frame)[:2], range_m
            )
            return attitude_from_crop(win, self.K_frame, att, self.R_att_ref)
        return R_head

    def prior_sigma_scale(self, f: dict[str, Any]) -> PriorSigmaScale:
        """The fusion's PriorSigmaScale."""
        model: PriorSigmaScale = self._fusion_table(f, "prior_sigma_scale", PriorSigmaScale)
        return model

    # ------------------------------------------------------------------ fits
    def fit(
        self,
        uv_px: np.ndarray,
        win: CropWindow,
        R_direct: np.ndarray,
        R_head: np.ndarray | None,
        range_m: float,
        f: dict[str, Any] | None,
    ) -> PnpResult:
        """One window's keypoints (frame px, NaN where absent) -> PnP, with the fusion `f`'s
        attitude prior: the crop's head (`R_head`) when it says so, else the direct model's;
        without a fusion, PnP alone; PnP alone too where keypoints that read any turn show the
        fixture turned in `win` beyond PRIOR_MAX_TURN_DEG. `range_m` is where the error tables
        are read."""
        pnp = None
        if f and self.keypoints_any_turn:
            pnp = solve_pnp(
                uv_px, self.points_m, self.K_frame, self.reproj_crop_px / win.scale, min_points=MIN_INLIERS
            )
            if pnp.ok and turn_in_window_deg(self.K_frame, *pnp.pose(), win) > PRIOR_MAX_TURN_DEG:
                return pnp
        R_prior = R_direct
        if f and f.get("attitude_prior") == "head" and R_head is not None:
            R_prior = self.head_prior(R_head, win, range_m, f)
        s_px: float | np.ndarray | None = float(f["sigma_crop_px"]) / win.scale if f else None
        if s_px is not None and f and f.get("kp_error_model"):
            s_px = s_px * self.error_model(f).scale(range_m)
        s_rad = np.radians(float(f["sigma_prior_deg"])) if f else None
        if s_rad is not None and f and f.get("prior_error_model"):
            s_rad *= self.prior_error_model(f).scale(range_m)
        if s_rad is not None and f and f.get("prior_sigma_scale"):
            s_rad *= self.prior_sigma_scale(f).scale(range_m)
        return map_pose(
            uv_px,
            self.points_m,
            self.K_frame,
            self.reproj_crop_px / win.scale,
            R_prior,
            s_px,
            s_rad,
            MIN_INLIERS,
            pnp,
        )

    def fit_without_prior(self, uv_px: np.ndarray, win: CropWindow) -> PnpResult | None:
        """PnP alone on a window's keypoints; None when it fails."""
        alone = solve_pnp(
            uv_px, self.points_m, self.K_frame, self.reproj_crop_px / win.scale, min_points=MIN_INLIERS
        )
        return alone if alone.ok else None
