"""The two jobs of the toolbox, end to end.

estimate: mocap CSV + frames of the pattern -> T_housing_cam, T_tmarkers_target, offset_s
          (PnP per frame, motion checks, time offset, closed form, least-squares refinement).
apply:    calibration + mocap CSV + frame index -> T_cam_target per frame, poses format:

    T_cam_target = inv(T_housing_cam) @ inv(T_mocap_housing(t + offset_s)) @ T_mocap_tmarkers(t + offset_s)
                   @ T_tmarkers_target
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from oibar.geometry.docking import MOUNT
from oibar.geometry.rotations import rotation_angle_deg
from oibar.geometry.transforms import adjoint, inv_T, make_T

from . import handeye, io, timing
from .errors import CalibError
from .pnp import Detector, Intrinsics, Observation, Pattern, project
from .refine import MocapNoise, RefineResult, refine

OFFSET_FINE_WINDOW_S = 0.010


@dataclass
class EstimateInputs:
    mocap_csv: Path
    frames_csv: Path
    pattern_json: Path
    housing_body: str
    target_body: str
    intrinsics_json: Path | None = None
    position_unit: str = "m"
    offset_s: float | None = None  # None: estimate it
    offset_search_s: float = 0.5
    mocap_sigma_mm: float = 0.2  # RMS position error per sample
    mocap_sigma_deg: float = 0.5  # RMS rotation angle error per sample
    corner_sigma_px: float | None = None  # None: pooled from the PnP residuals
    min_poses: int = handeye.MIN_POSES
    # Local quadratic fit of the mocap around each frame (+- this, s); None: interpolate
    # between the two neighbouring samples (timing.smooth explains why not).
    smooth_half_width_s: float | None = timing.SMOOTH_HALF_WIDTH_S


def _noise(sigma_mm: float, sigma_deg: float) -> MocapNoise:
    # The figures are RMS magnitudes (|dp|, rotation angle); per axis that is /sqrt(3).
    return MocapNoise(sigma_mm * 1e-3 / np.sqrt(3), np.radians(sigma_deg) / np.sqrt(3))


def _stats(x: np.ndarray) -> dict:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if not len(x):
        return {}
    return {
        "rms": float(np.sqrt(np.mean(x**2))),
        "median": float(np.median(x)),
        "p95": float(np.percentile(x, 95)),
        "max": float(x.max()),
    }


def _sigma(cov: np.ndarray) -> dict:
    s = np.sqrt(np.clip(np.diag(cov), 0, None))
    return {
        "t_mm": [round(float(v) * 1e3, 4) for v in s[:3]],
        "r_deg": [round(float(np.degrees(v)), 4) for v in s[3:]],
    }


def pooled_corner_sigma_px(obs: list[Observation]) -> float:
    """Corner noise per image axis from all PnP fits: sqrt(sum of squares / degrees of freedom)."""
    sse = sum(o.rms_px**2 * len(o.ids) for o in obs)
    dof = sum(2 * len(o.ids) - 6 for o in obs)
    return max(float(np.sqrt(sse / max(dof, 1))), 0.02)


def observe_frames(
    frames: list[dict], detector: Detector, progress: Callable[[int, int], None] | None = None
) -> list[Observation | None]:
    obs = []
    for k, f in enumerate(frames):
        img = cv2.imread(str(f["path"]), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise CalibError(f"{f['path']}: cannot read the image")
        h, w = img.shape
        if (w, h) != (detector.intr.width_px, detector.intr.height_px):
            raise CalibError(
                f"{f['path']}: image is {w}x{h}, the intrinsics say "
                f"{detector.intr.width_px}x{detector.intr.height_px}"
            )
        obs.append(detector.observe(img))
        if progress:
            progress(k + 1, len(frames))
    return obs


def estimate(
    inp: EstimateInputs,
    progress: Callable[[int, int], None] | None = None,
    images: list[np.ndarray] | None = None,
) -> dict:
    """Run the calibration; returns the result dict written by io.write_calibration (the two
    transforms as 4x4 matrices) plus `_details` for overlays and tests."""
    tracks = io.read_mocap_csv(inp.mocap_csv, inp.position_unit)
    housing, tmarkers = io.pick_tracks(tracks, inp.housing_body, inp.target_body, inp.mocap_csv)
    frames = io.read_frames_csv(inp.frames_csv, check_files=images is None)
    pattern = io.read_pattern(inp.pattern_json)
    intr = io.read_intrinsics(inp.intrinsics_json)
    det = Detector(pattern, intr)
    if images is None:
        obs = observe_frames(frames, det, progress)
    else:
        obs = [det.observe(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)) for im in images]

    return estimate_from_observations(inp, housing, tmarkers, frames, obs, pattern, intr)


def _start_offset(
    inp: EstimateInputs, t_f: np.ndarray, A: np.ndarray, housing: timing.Track, tmarkers: timing.Track
) -> tuple[float, float, float | None]:
    """The clock offset to start the refinement from: (by speed matching, by the closed-form
    hand-eye scan, the refinement's search window), or the user's --offset-s (no window)."""
    if t_f[-1] + inp.offset_search_s < housing.t_s[0] or t_f[0] - inp.offset_search_s > housing.t_s[-1]:
        raise CalibError(
            f"the mocap ({housing.t_s[0]:.2f}-{housing.t_s[-1]:.2f} s) and the frames "
            f"({t_f[0]:.2f}-{t_f[-1]:.2f} s) do not overlap; pass --offset-s with the clock difference"
        )
    if inp.offset_s is not None:
        return float(inp.offset_s), float(inp.offset_s), None
    hw = inp.smooth_half_width_s
    off_speed = timing.offset_by_speed(t_f, A[:, :3, :3], housing, tmarkers, inp.offset_search_s)
    off0 = timing.offset_by_handeye(t_f, A, housing, tmarkers, off_speed, smooth_half_width_s=hw)
    return off_speed, off0, OFFSET_FINE_WINDOW_S


def _chain_reprojection_px(
    found: list[Observation], inliers: np.ndarray, A_pred: np.ndarray, pattern: Pattern, intr: Intrinsics
) -> np.ndarray:
    """The detected corners' reprojection errors (px) through the calibrated mocap chain
    (A_pred: the camera-pattern poses it predicts), inlier poses only."""
    parts = [
        np.linalg.norm(project(pattern.corners_pattern_m()[o.ids], A_pred[j], intr) - o.uv_px, axis=1)
        for j, o in enumerate(found)
        if inliers[j]
    ]
    return np.concatenate(parts)


def _report(
    inp: EstimateInputs,
    res: RefineResult,
    pattern: Pattern,
    found: list[Observation],
    reproj_px: np.ndarray,
    sigma_px: float,
    poses: dict,
    offset_stages_s: dict,
) -> dict:
    """The calibration's result: the two transforms, the offset, their 1-sigma, the poses used,
    the residuals, the offset's stages and the settings."""
    r = res.residuals[res.inliers]
    P = pattern.T_target_pattern
    Ad_Z, Ad_PX = adjoint(res.Z), adjoint(P @ res.X)
    return {
        "housing_body": inp.housing_body,
        "target_body": inp.target_body,
        "T_housing_cam": inv_T(res.Z),
        "T_tmarkers_target": inv_T(res.X) @ inv_T(P),
        "offset_s": res.offset_s,
        "offset_convention": "mocap time = frame time_s + offset_s",
        "sigma_1": {
            "T_housing_cam": _sigma(Ad_Z @ res.cov_Z @ Ad_Z.T),
            "T_tmarkers_target": _sigma(Ad_PX @ res.cov_X @ Ad_PX.T),
            "offset_ms": None if not np.isfinite(res.sigma_offset_s) else round(res.sigma_offset_s * 1e3, 4),
        },
        "poses": poses,
        "residuals": {
            "chi2_per_dof": round(res.chi2_per_dof, 4),
            "pose_translation_mm": {
                k: round(v * 1e3, 4) for k, v in _stats(np.linalg.norm(r[:, :3], axis=1)).items()
            },
            "pose_rotation_deg": {
                k: round(float(np.degrees(v)), 4) for k, v in _stats(np.linalg.norm(r[:, 3:], axis=1)).items()
            },
            "chain_reprojection_px": {k: round(v, 4) for k, v in _stats(reproj_px).items()},
            "pnp_reprojection_px": {
                k: round(v, 4) for k, v in _stats(np.array([o.rms_px for o in found])).items()
            },
        },
        "offset_stages_s": offset_stages_s,
        "settings": {
            "mocap_sigma_mm": inp.mocap_sigma_mm,
            "mocap_sigma_deg": inp.mocap_sigma_deg,
            "corner_sigma_px": round(sigma_px, 4),
            "position_unit": inp.position_unit,
            "pattern": str(inp.pattern_json),
            "intrinsics": str(inp.intrinsics_json or "oibar default"),
        },
    }


def estimate_from_observations(
    inp: EstimateInputs,
    housing: timing.Track,
    tmarkers: timing.Track,
    frames: list[dict],
    obs: list[Observation | None],
    pattern: Pattern,
    intr: Intrinsics,
) -> dict:
    """The estimation proper, once the files are read and the pattern observed in every frame
    (`obs[k]` None where it was not found). Also used by the multi-recording validation, which
    simulates the observations instead of rendering frames."""
    seen = [k for k, o in enumerate(obs) if o is not None]
    found = [o for o in obs if o is not None]  # the observations of the frames in `seen`
    if len(seen) < inp.min_poses:
        raise CalibError(
            f"too few calibration poses: the pattern was found in {len(seen)} of {len(frames)} "
            f"frames, need at least {inp.min_poses}"
        )
    t_f = np.array([frames[k]["time_s"] for k in seen])
    A = np.stack([o.T_cam_pattern for o in found])
    # The PnP covariance must match the real corner noise: an overstated one biases the time
    # offset towards frames half-way between mocap samples (see timing.interpolate).
    sigma_px = inp.corner_sigma_px or pooled_corner_sigma_px(found)
    A_cov = np.stack([o.cov for o in found]) * sigma_px**2
    spread = handeye.check_motion(A, inp.min_poses)

    hw = inp.smooth_half_width_s
    off_speed, off0, window = _start_offset(inp, t_f, A, housing, tmarkers)

    B0, valid0 = timing.relative_at(housing, tmarkers, t_f + off0, smooth_half_width_s=hw)
    if valid0.sum() < inp.min_poses:
        raise CalibError(
            f"too few poses with mocap coverage at offset {off0:.3f} s: {int(valid0.sum())} "
            f"(need {inp.min_poses}); mocap gaps, or the wrong rigid bodies?"
        )
    X0, Z0 = handeye.closed_form(A[valid0], B0[valid0])
    noise = _noise(inp.mocap_sigma_mm, inp.mocap_sigma_deg)
    # The reference samples of the local fits stay those of the start offset, so that the mocap
    # poses are a smooth function of the offset (timing.smooth).
    res = refine(
        A,
        A_cov,
        lambda off: timing.relative_at(
            housing, tmarkers, t_f + off, with_variance=True, smooth_half_width_s=hw, ref_t_s=t_f + off0
        ),
        X0,
        Z0,
        off0,
        noise,
        noise,
        offset_window_s=window,
        min_poses=inp.min_poses,
    )

    B, _ = timing.relative_at(housing, tmarkers, t_f + res.offset_s, smooth_half_width_s=hw)
    A_pred = res.Z @ B @ inv_T(res.X)
    poses = {
        "frames": len(frames),
        "pattern_found": len(seen),
        "used": int(res.inliers.sum()),
        "outliers": int(len(seen) - res.inliers.sum()),
        **{k: round(v, 4) for k, v in spread.items()},
    }
    stages = {
        "speed_match": round(off_speed, 6),
        "closed_form_scan": round(off0, 6),
        "refined": round(res.offset_s, 6),
    }
    reproj_px = _chain_reprojection_px(found, res.inliers, A_pred, pattern, intr)
    result = _report(inp, res, pattern, found, reproj_px, sigma_px, poses, stages)
    result["_details"] = dict(
        seen=seen, obs=obs, A_pred=A_pred, inliers=res.inliers, frames=frames, pattern=pattern, intr=intr
    )
    return result


def distance_m(T_cam_target: np.ndarray) -> float:
    """The dataset's distance_m: -z of the chaser docking frame F_s in F_t, with the camera
    mount of docs/synthetic.md (oibar.geometry.docking.MOUNT)."""
    T_s_cam = make_T(np.asarray(MOUNT.R_s_cam, float), np.asarray(MOUNT.p_s_cam_m, float))
    T_target_s = inv_T(T_cam_target) @ inv_T(T_s_cam)
    return float(-T_target_s[2, 3])


def apply(
    calib: dict,
    tracks: dict,
    frames: list[dict],
    mocap_path: Path,
    max_gap_s: float | None = None,
    smooth_half_width_s: float | None = timing.SMOOTH_HALF_WIDTH_S,
) -> tuple[list[dict], list[int]]:
    """Ground-truth rows for every frame with mocap coverage; also the frames skipped.

    Each body's pose at a frame is a local quadratic fit of its samples within
    +-`smooth_half_width_s` (timing.smooth), or with None or 0 the interpolation between the two
    neighbouring samples. Why the fit: an interpolated label carries one or two samples' noise
    (the paper's mocap, 0.5 deg a sample, turns the whole camera-to-target vector: 0.47 % of
    range and 0.47 deg on the lab demonstration's runs), and a network fine-tuned on such labels
    learns heat maps as broad as that noise. The window must be short against the motion (the
    quadratic must hold over it): docs/calibration.md, "Labels: the mocap's noise"."""
    housing, tmarkers = io.pick_tracks(tracks, calib["housing_body"], calib["target_body"], mocap_path)
    t_f = np.array([f["time_s"] for f in frames]) + float(calib["offset_s"])
    if smooth_half_width_s:
        H, vh = timing.smooth(housing, t_f, smooth_half_width_s, max_gap_s)
        M, vm = timing.smooth(tmarkers, t_f, smooth_half_width_s, max_gap_s)
    else:
        H, vh = timing.interpolate(housing, t_f, max_gap_s)
        M, vm = timing.interpolate(tmarkers, t_f, max_gap_s)
    valid = vh & vm
    if not valid.any():
        raise CalibError(
            f"{mocap_path}: no frame has mocap coverage of both rigid bodies "
            f"({calib['housing_body']!r}, {calib['target_body']!r}); wrong file or clock?"
        )
    T = inv_T(calib["T_housing_cam"]) @ inv_T(H) @ M @ calib["T_tmarkers_target"]
    rows, skipped = [], []
    for k, f in enumerate(frames):
        if not valid[k]:
            skipped.append(f["frame"])
            continue
        rows.append(
            {
                "frame": f["frame"],
                "file": f["file"],
                "time_s": f["time_s"],
                "T_cam_target": T[k],
                "distance_m": distance_m(T[k]),
            }
        )
    return rows, skipped


def rotation_error_deg(T_a: np.ndarray, T_b: np.ndarray) -> float:
    return float(rotation_angle_deg(T_a[:3, :3].T @ T_b[:3, :3]))


__all__ = ["EstimateInputs", "estimate", "apply", "Pattern", "Intrinsics"]
