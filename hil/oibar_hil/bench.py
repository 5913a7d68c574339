"""Render throughput benchmark: frames/s at 744x480 for a paper sequence, render only (GL draw +
read-back, no encoding or disk) and end-to-end (plus JPEG/PNG encode), across N processes with
one EGL context each.

python -m oibar_hil.bench [--seq 1] [--frames 400] [--workers 2]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import time

import numpy as np

from .dataset import PAPER_SEQUENCES, _renderer_for, _worker_init, encode_image, plan_sequence


def _bench_worker(args):
    spec, frames, encode, arrays = args
    r = _renderer_for(spec)
    r.render(arrays["R"][0], arrays["p"][0], arrays["sun"][0], arrays["Re"][0], arrays["ec"])   # warm-up
    t = time.perf_counter()
    for j in range(len(frames)):
        img = r.render(arrays["R"][j], arrays["p"][j], arrays["sun"][j], arrays["Re"][j], arrays["ec"])
        if encode:
            encode_image(img, spec)
    return len(frames), time.perf_counter() - t


def run(seq: int, n_frames: int, workers: int, encode: bool) -> float:
    spec = PAPER_SEQUENCES[seq]
    plan = plan_sequence(spec)
    # Four runs of consecutive frames (as the dataset renders them, so the Sun's shadow map is
    # reused for 10 frames) at far, mid and close range.
    block = max(1, n_frames // 4)
    starts = (np.array([0.05, 0.35, 0.65, 0.95]) * (plan.n_frames - block)).astype(int)
    idx = np.concatenate([np.arange(s0, s0 + block) for s0 in starts])
    parts = np.array_split(idx, workers)
    jobs = [(spec, p.tolist(), encode, {"R": plan.R_lvlh_cam[p], "p": plan.p_lvlh_cam[p], "sun": plan.sun_lvlh[p],
                                        "Re": plan.R_ecef_lvlh[p], "ec": plan.earth_center_lvlh_km}) for p in parts]
    cpu = os.cpu_count() or 1
    with mp.get_context("spawn").Pool(workers, initializer=_worker_init, initargs=(max(1, cpu // workers),)) as pool:
        res = pool.map(_bench_worker, jobs)
    # Aggregate rate: frames over the slowest worker's busy time.
    return sum(n for n, _ in res) / max(t for _, t in res)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_hil.bench")
    ap.add_argument("--seq", type=int, default=1)
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    a = ap.parse_args(argv)
    for encode in (False, True):
        fps = run(a.seq, a.frames, a.workers, encode)
        what = "render + JPEG encode" if encode else "render only        "
        print(f"seq{a.seq:02d} {PAPER_SEQUENCES[a.seq].background:6s} {what} {a.workers} worker(s): {fps:6.1f} frames/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
