"""The export's per-range error tables for the keypoint fit (``oibar.fusion``): how well each
keypoint is found, how far the attitude prior is off, how much of a tilt the attitude head reads;
each binned by camera range and measured on the validation scenes (oibar_models.kp_fusion,
oibar_models.kp_head_gain) or on probe frames of training scenes (oibar_models.kp_head_crop_gain);
and where the prior is trusted less than measured (chosen on the
validation scenes' response probe)."""

from __future__ import annotations

from typing import Any

import numpy as np


def range_edges(table: dict[str, Any], what: str) -> np.ndarray:
    """A range-bin table's ``range_edges_m``, checked: two or more finite, rising edges (m). Every
    per-range table of the export (error models, head gain) is binned by it with range_bin."""
    edges_m = np.asarray(table["range_edges_m"], float)
    if (
        edges_m.ndim != 1
        or len(edges_m) < 2
        or not np.all(np.isfinite(edges_m))
        or np.any(np.diff(edges_m) <= 0)
    ):
        raise ValueError(
            f"{what}: range_edges_m must be two or more finite rising edges, got {edges_m.tolist()}"
        )
    return edges_m


class KeypointErrorModel:
    """How well each keypoint is found, by camera range: RMS error (crop pixels) per keypoint and
    range bin, measured on the validation scenes (oibar_models.kp_fusion) and shipped in the
    export's ``oibar.fusion``. The fit weighs each keypoint by it: the drogue's throat, say, is
    sharp at 3-8 m and four times worse under 1.5 m, where a fixed weight would let it tilt the
    pose by degrees. Relative weights only: ``scale(range)`` is the RMS over the overall RMS."""

    def __init__(self, table: dict[str, Any]):
        self.edges_m = range_edges(table, "error model")
        self.rms_crop_px = np.asarray(table["rms_crop_px"], float)  # (K, bins)
        if self.rms_crop_px.ndim != 2 or self.rms_crop_px.shape[1] != len(self.edges_m) - 1:
            raise ValueError(
                f"error model: rms_crop_px must be (keypoints, {len(self.edges_m) - 1}), "
                f"got {self.rms_crop_px.shape}"
            )
        if not np.all(np.isfinite(self.rms_crop_px)) or np.any(self.rms_crop_px <= 0):
            raise ValueError("error model: every rms_crop_px must be finite and > 0")
        self.ref_crop_px = float(np.sqrt(np.mean(self.rms_crop_px**2)))

    def scale(self, range_m: float) -> np.ndarray:
        """(K,) per-keypoint sigma relative to the overall one, at this camera range."""
        return self.rms_crop_px[:, range_bin(self.edges_m, range_m)] / self.ref_crop_px


class PriorErrorModel:
    """How far the attitude prior is off, by camera range: RMS error (deg) per range bin,
    measured on the validation scenes (oibar_models.kp_fusion) and shipped in the export's
    ``oibar.fusion.prior_error_model``. The attitude head reads a degree well at 3-8 m and worse
    at 10 m and close in; a fixed prior weight would trust it as much everywhere. Relative:
    ``scale(range)`` is the bin's RMS over the overall RMS, so ``sigma_prior_deg`` keeps its
    meaning as the typical weight."""

    def __init__(self, table: dict[str, Any]):
        self.edges_m = range_edges(table, "prior error model")
        self.rms_deg = np.asarray(table["rms_deg"], float)
        if self.rms_deg.ndim != 1 or len(self.rms_deg) != len(self.edges_m) - 1:
            raise ValueError(
                f"prior error model: rms_deg must have {len(self.edges_m) - 1} entries, got {self.rms_deg.shape}"
            )
        if not np.all(np.isfinite(self.rms_deg)) or np.any(self.rms_deg <= 0):
            raise ValueError("prior error model: every rms_deg must be finite and > 0")
        self.ref_deg = float(np.sqrt(np.mean(self.rms_deg**2)))

    def scale(self, range_m: float) -> float:
        return float(self.rms_deg[range_bin(self.edges_m, range_m)] / self.ref_deg)


HEAD_GAIN_LIMITS = (0.5, 2.0)  # a tilt gain outside these is a measurement gone wrong, not a reading


class HeadGainModel:
    """How much of a tilt the attitude head reads, by camera range: per range bin, the slope of
    the head's tilt (guidance's attitude error about x and y) on the truth's, measured on the
    validation scenes (oibar_models.kp_head_gain) and shipped in the export's
    ``oibar.fusion.head_gain``. A head trained mostly on aligned approaches reads a 3 deg tilt as
    2.5 close in; as the fit's prior it pulls every answer toward "aligned" by that much, which no
    weight can undo. ``gain(range)`` is what the head's tilt is divided by before it is used."""

    def __init__(self, table: dict[str, Any]):
        self.edges_m = range_edges(table, "head gain")
        self.tilt_gain = np.asarray(table["tilt_gain"], float)
        if self.tilt_gain.shape != (len(self.edges_m) - 1,):
            raise ValueError(
                f"head gain: tilt_gain must have {len(self.edges_m) - 1} entries, got {self.tilt_gain.shape}"
            )
        lo, hi = HEAD_GAIN_LIMITS
        if not np.all(np.isfinite(self.tilt_gain)) or np.any((self.tilt_gain < lo) | (self.tilt_gain > hi)):
            raise ValueError(
                f"head gain: every tilt_gain must be within {lo}-{hi}, got {self.tilt_gain.tolist()}"
            )

    def gain(self, range_m: float) -> float:
        return float(self.tilt_gain[range_bin(self.edges_m, range_m)])


# A crop gain outside these is a measurement gone wrong (below 0.4 the head's noise would be
# amplified more than 2.5x); a leak beyond 0.5 of the bearing is no keystone, a head reading the
# window's place instead of the fixture.
HEAD_CROP_GAIN_LIMITS = (0.4, 2.0)
HEAD_CROP_LEAK_LIMITS = (-0.5, 0.5)


class HeadCropGainModel:
    """How the attitude head reads an out-of-plane rotation in its own crop, by camera range: per
    range bin, the gain g and the bearing leak k of

        head's x, y = g * truth's x, y + k * window's bearing x, y     (crop frame, deg)

    fitted on probe frames of training scenes (the vehicle moved sideways and turned, in windows
    cut on the true pose: oibar_models.kp_head_crop_gain) and shipped in the export's
    ``oibar.fusion.head_crop_gain``. Why both: the crop is an affine cut, so a fixture off the
    image centre shows a keystone that the head takes for a change of view (k); and a head
    fine-tuned on looks where a view is hard to see reads every view short (g: 0.64 at 3 m for
    0.35.6, 0.88 for 0.34.0). A docking-frame gain (HeadGainModel) cannot part the two: a turn
    moves the bearing, a sideways step the view. ``correct`` inverts the model."""

    def __init__(self, table: dict[str, Any]):
        self.edges_m = range_edges(table, "head crop gain")
        n = len(self.edges_m) - 1
        self.gain = np.asarray(table["gain"], float)
        self.bearing_leak = np.asarray(table["bearing_leak"], float)
        for name, v, (lo, hi) in (
            ("gain", self.gain, HEAD_CROP_GAIN_LIMITS),
            ("bearing_leak", self.bearing_leak, HEAD_CROP_LEAK_LIMITS),
        ):
            if v.shape != (n,):
                raise ValueError(f"head crop gain: {name} must have {n} entries, got {v.shape}")
            if not np.all(np.isfinite(v)) or np.any((v < lo) | (v > hi)):
                raise ValueError(f"head crop gain: every {name} must be within {lo}-{hi}, got {v.tolist()}")

    def correct(self, head_xy_deg: np.ndarray, bearing_xy_deg: np.ndarray, range_m: float) -> np.ndarray:
        """The out-of-plane rotation (x, y, deg, crop frame) the head's reading stands for."""
        b = range_bin(self.edges_m, range_m)
        out: np.ndarray = (
            np.asarray(head_xy_deg, float) - self.bearing_leak[b] * np.asarray(bearing_xy_deg, float)
        ) / self.gain[b]
        return out


PRIOR_SIGMA_SCALE_LIMITS = (0.01, 1e4)  # beyond: a typo, not a choice (1e3 already lets the keypoints decide)


class PriorSigmaScale:
    """Where the attitude prior is trusted less than its error model says, by camera range: a
    factor on the prior's sigma per range bin, chosen on the validation scenes' response probe
    (oibar_hil.rig.probe) and shipped in the export's ``oibar.fusion.prior_sigma_scale``. The
    error model is measured on near-aligned frames, where a head that reads every tilt a little
    short still looks accurate; the probe turns the vehicle and sees it pull the answer toward
    "aligned" (0.35.2 at 3 m: attitude slope 0.944 with it, 0.965 with the keypoints alone). 1
    keeps the error model's weight; 1000 leaves the fit to the keypoints (the prior still starts
    it, which keeps a far frame off its mirrored pose)."""

    def __init__(self, table: dict[str, Any]):
        self.edges_m = range_edges(table, "prior sigma scale")
        self.sigma_scale = np.asarray(table["sigma_scale"], float)
        if self.sigma_scale.shape != (len(self.edges_m) - 1,):
            raise ValueError(
                f"prior sigma scale: sigma_scale must have {len(self.edges_m) - 1} entries, "
                f"got {self.sigma_scale.shape}"
            )
        lo, hi = PRIOR_SIGMA_SCALE_LIMITS
        if not np.all(np.isfinite(self.sigma_scale)) or np.any(
            (self.sigma_scale < lo) | (self.sigma_scale > hi)
        ):
            raise ValueError(
                f"prior sigma scale: every sigma_scale must be within {lo:g}-{hi:g}, "
                f"got {self.sigma_scale.tolist()}"
            )

    def scale(self, range_m: float) -> float:
        return float(self.sigma_scale[range_bin(self.edges_m, range_m)])


def range_bin(edges_m: np.ndarray, range_m: float) -> int:
    """The bin of `range_m` among `edges_m` (N + 1 rising edges -> 0..N-1; outside: the end bins)."""
    return int(np.clip(np.searchsorted(edges_m, range_m, side="right") - 1, 0, len(edges_m) - 2))
