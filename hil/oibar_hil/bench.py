"""Render throughput benchmark: frames/s at 744x480 for a paper sequence, render only (GL draw +
read-back, no encoding or disk) and end-to-end (plus JPEG/PNG encode), across N processes with
one EGL context each.

python -m oibar_hil.bench [--seq 1] [--frames 400] [--workers 2]
python -m oibar_hil.bench --all [--frames 160]      # every paper sequence + the 12-sequence estimate

Besides wall-clock frames/s it reports the CPU time per frame (process time of the workers, all
their threads). On a shared machine the wall-clock figure depends on the other jobs; the CPU
figure does not, and `workers * 1000 / cpu_ms` is the rate the same work reaches on that many
otherwise idle cores. The load average is printed with every result.
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
    r.render(arrays["R"][0], arrays["p"][0], arrays["sun"][0], arrays["Re"][0], arrays["ec"])  # warm-up
    r.ctx.finish()
    t, c = time.perf_counter(), time.process_time()
    for j in range(len(frames)):
        img = r.render(arrays["R"][j], arrays["p"][j], arrays["sun"][j], arrays["Re"][j], arrays["ec"])
        if encode:
            encode_image(img, spec)
    return len(frames), time.perf_counter() - t, time.process_time() - c


def _jobs(seq: int, n_frames: int, workers: int, encode: bool, plan=None):
    spec = PAPER_SEQUENCES[seq]
    plan = plan or plan_sequence(spec)
    # Four runs of consecutive frames (as the dataset renders them, so the Sun's shadow map is
    # reused for 10 frames) at far, mid and close range.
    block = max(1, n_frames // 4)
    starts = (np.array([0.05, 0.35, 0.65, 0.95]) * (plan.n_frames - block)).astype(int)
    idx = np.concatenate([np.arange(s0, s0 + block) for s0 in starts])
    parts = np.array_split(idx, workers)
    return [
        (
            spec,
            p.tolist(),
            encode,
            {
                "R": plan.R_lvlh_cam[p],
                "p": plan.p_lvlh_cam[p],
                "sun": plan.sun_lvlh[p],
                "Re": plan.R_ecef_lvlh[p],
                "ec": plan.earth_center_lvlh_km,
            },
        )
        for p in parts
    ]


def run_detailed(seq: int, n_frames: int, workers: int, encode: bool, pool=None, plan=None) -> dict:
    """{'fps': aggregate wall-clock rate, 'cpu_ms': CPU ms per frame, 'frames': n}."""
    jobs = _jobs(seq, n_frames, workers, encode, plan)
    if pool is None:
        cpu = os.cpu_count() or 1
        with mp.get_context("spawn").Pool(
            workers, initializer=_worker_init, initargs=(max(1, cpu // workers),)
        ) as p:
            res = p.map(_bench_worker, jobs)
    else:
        res = pool.map(_bench_worker, jobs)
    n = sum(r[0] for r in res)
    # Aggregate rate: frames over the slowest worker's busy time.
    return {"fps": n / max(r[1] for r in res), "cpu_ms": 1e3 * sum(r[2] for r in res) / n, "frames": n}


def run(seq: int, n_frames: int, workers: int, encode: bool) -> float:
    return run_detailed(seq, n_frames, workers, encode)["fps"]


def _load() -> str:
    try:
        return "load " + " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "load n/a"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_hil.bench")
    ap.add_argument("--seq", type=int, default=1)
    ap.add_argument(
        "--all", action="store_true", help="all 12 paper sequences (render + encode) and the set's estimate"
    )
    ap.add_argument(
        "--frames", type=int, default=None, help="frames per measurement (default 400, 160 with --all)"
    )
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    a = ap.parse_args(argv)
    cpu = os.cpu_count() or 1
    print(f"{a.workers} worker(s), LP_NUM_THREADS={max(1, cpu // a.workers)} each, {cpu} CPU(s); {_load()}")
    if not a.all:
        for encode in (False, True):
            r = run_detailed(a.seq, a.frames or 400, a.workers, encode)
            what = "render + JPEG encode" if encode else "render only        "
            print(
                f"seq{a.seq:02d} {PAPER_SEQUENCES[a.seq].background:6s} {what}: {r['fps']:6.1f} frames/s wall, "
                f"{r['cpu_ms']:5.1f} CPU ms/frame (= {a.workers * 1e3 / r['cpu_ms']:6.1f} frames/s on "
                f"{a.workers} idle cores); {_load()}"
            )
        return 0
    tot_wall = tot_cpu = 0.0
    frames_total = 0
    threads = max(1, cpu // a.workers)
    with mp.get_context("spawn").Pool(a.workers, initializer=_worker_init, initargs=(threads,)) as pool:
        for seq, spec in PAPER_SEQUENCES.items():
            plan = plan_sequence(spec)
            r = run_detailed(seq, a.frames or 160, a.workers, True, pool=pool, plan=plan)
            idle_fps = a.workers * 1e3 / r["cpu_ms"]
            tot_wall += plan.n_frames / r["fps"]
            tot_cpu += plan.n_frames / idle_fps
            frames_total += plan.n_frames
            print(
                f"seq{seq:02d} {spec.approach:6s} {spec.background:6s} {plan.n_frames:5d} frames: "
                f"{r['fps']:6.1f} frames/s wall, "
                f"{r['cpu_ms']:5.1f} CPU ms/frame (= {idle_fps:6.1f} frames/s idle); {_load()}",
                flush=True,
            )
    print(
        f"12 sequences, {frames_total} frames (render + encode only): {tot_wall / 60:.1f} min at the "
        f"measured wall-clock rates, {tot_cpu / 60:.1f} min on {a.workers} idle cores; {_load()}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
