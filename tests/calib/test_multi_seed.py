"""Statistical validation over many recordings of the documented calibration design.

The rendered recording (test_synthetic_validation.py) checks one recording end to end; this
checks that the limits of issue 9 (1 mm, 0.1 deg on both transforms) hold for *every* recording
of the design, not just a lucky one. No rendering: the pattern observations are the board
corners projected from the true poses plus the corner noise seen on the rendered frames
(synthetic.simulate_observations, 0.12 px per axis), then the same PnP and the same estimator
(pipeline.estimate_from_observations) with fresh mocap noise per seed."""

import time

import numpy as np

from oibar.calib import pipeline
from oibar.calib.pnp import Intrinsics
from oibar.geometry.transforms import pose_error
from oibar_hil.calib_synth import SynthConfig, frame_times, simulate_observations, simulated_tracks

SEEDS = range(101, 117)  # not the seeds the estimator was tuned on (1-20); ~2 s each


def _run(seed: int, intr: Intrinsics) -> dict:
    cfg = SynthConfig(seed=seed)
    housing, tmarkers = simulated_tracks(cfg)
    obs = simulate_observations(cfg, intr)
    frames = [{"frame": k, "file": f"{k:06d}.png", "time_s": t} for k, t in enumerate(frame_times(cfg))]
    inp = pipeline.EstimateInputs(None, None, None, "housing", "tmarkers")
    res = pipeline.estimate_from_observations(inp, housing, tmarkers, frames, obs, cfg.pattern, intr)
    hc = pose_error(res["T_housing_cam"], cfg.T_housing_cam)
    tt = pose_error(res["T_tmarkers_target"], cfg.T_tmarkers_target)
    return {
        "seed": seed,
        "hc_mm": hc[0] * 1e3,
        "hc_deg": hc[1],
        "tt_mm": tt[0] * 1e3,
        "tt_deg": tt[1],
        "offset_ms": (res["offset_s"] - cfg.offset_s) * 1e3,
        "chi2": res["residuals"]["chi2_per_dof"],
        "used": res["poses"]["used"],
        "n": cfg.n_frames,
    }


def test_every_recording_of_the_design_meets_the_limits(capsys):
    intr = Intrinsics.oibar_default()
    t0 = time.monotonic()
    rows = [_run(s, intr) for s in SEEDS]
    dt = time.monotonic() - t0
    keys = ("hc_mm", "hc_deg", "tt_mm", "tt_deg", "offset_ms")
    a = {k: np.array([r[k] for r in rows]) for k in keys}
    with capsys.disabled():
        print(
            f"\n[calib multi-seed] {len(rows)} recordings of {rows[0]['n']} poses in {dt:.0f} s; median / worst: "
            + "; ".join(f"{k} {np.median(a[k]):+.3f} / {a[k][np.argmax(np.abs(a[k]))]:+.3f}" for k in keys)
        )
    bad = [r for r in rows if max(r["hc_mm"], r["tt_mm"]) >= 1.0 or max(r["hc_deg"], r["tt_deg"]) >= 0.1]
    assert not bad, "recordings outside 1 mm / 0.1 deg: " + "; ".join(
        f"seed {r['seed']}: {r['hc_mm']:.3f} mm {r['hc_deg']:.4f} deg, {r['tt_mm']:.3f} mm {r['tt_deg']:.4f} deg, "
        f"offset {r['offset_ms']:+.2f} ms"
        for r in bad
    )
    # The offset: no bias left (was +0.6 ms median with interpolated mocap) and no stray estimate.
    assert abs(np.median(a["offset_ms"])) < 0.4 and np.max(np.abs(a["offset_ms"])) < 2.0
    assert all(0.7 < r["chi2"] < 1.4 and r["used"] >= r["n"] - 5 for r in rows)
