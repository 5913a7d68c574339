"""Synthetic dataset writer: the paper's 12 sequences (SPEC section 6) or any sequence spec.

Layout of one sequence directory (e.g. OUT/seq01):
  spec.json      the sequence spec, written first (resume refuses a different spec)
  frames/NNNNNN.jpg (or .png)   744x480 RGB frames at 10 Hz
  poses.csv      one row per frame: time, phase, labels (see docs/synthetic.md)
  manifest.json  written last: generator version, seed, full config, SHA-256 of every file.
                 Its presence marks the sequence complete.

Frames default to JPEG (quality 95, 4:4:4 chroma): ~5x smaller than PNG and ~3x faster to
encode on our CPUs, which matters for ~44k frames; the loss is far below the photometric
augmentation the training applies. `--format png` gives lossless frames.

Frames are written atomically (temporary file + rename), so after an interruption every frame
file present is complete unless something else damaged it; resume also checks the image trailer
and re-renders any frame that fails. `verify_sequence` checks every hash against the manifest.

CLI:  python -m oibar_hil.dataset --out DIR [--seqs 1,8] [--frames-limit N] [--workers N]
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import multiprocessing as mp
import os
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from oibar.dataset_format import POSES_COLUMNS
from oibar.geometry.camera import PinholeCamera
from oibar.geometry.docking import MOUNT
from oibar.geometry.fixture import FIXTURE

from . import __version__
from .orbit import DEFAULT_EPOCH_UTC, DEFAULT_TLE, TargetOrbit, julian_date, parse_utc
from .ports import PORTS
from .randomize import LOOK_VERSION, LookParams, look_for
from .relpose import camera_poses
from .render import RenderSettings
from .sequence import (  # noqa: F401  (DatasetError re-exported)
    DatasetError,
    check_image_trailer,
    read_manifest,
    read_pose_table,
    sha256_file,
    verify_files,
)
from .trajectory import PHASE_NAMES, TrajectoryParams, generate

GENERATOR = "oibar_hil.dataset"
SUN_UPDATE_S = 1.0  # Sun direction is sampled once a second (0.065 deg steps): lets the
# shadow map be reused for 10 frames, deterministically per frame
CHUNK_FRAMES = 25


@dataclass(frozen=True)
class SequenceSpec:
    name: str
    port: int
    approach: str
    sun_elevation_deg: float
    background: str  # iss | perlin
    seed: int
    envelope: bool = False
    epoch_utc: str = DEFAULT_EPOCH_UTC  # search for the Sun elevation starts here
    image_format: str = "jpg"  # jpg | png
    jpeg_quality: int = 95
    png_compress_level: int = 1
    noise_sigma_dn: float = 0.0
    blur_sigma_px: float = 0.0
    # Render every n-th frame of the 10 Hz trajectory: consecutive frames are nearly identical,
    # so a training set gains more from more scenes than from every frame of a few.
    frame_stride: int = 1
    # A chaser that stays misaligned by this much from 10 m to contact (trajectory.generate).
    turned_deg: float = 0.0
    # A chaser that wanders up to this far off the docking axis below 10 m (trajectory.generate).
    offaxis_m: float = 0.0
    # A chaser rolled by this much about its docking axis throughout (trajectory.generate).
    rolled_deg: float = 0.0
    # Who draws the frames: "raster" (render.Renderer, our training renderer) or "mitsuba" (the
    # path tracer of render_mitsuba: validation and test looks only, issue 58), and its look:
    # "matched" (our materials and lights), "lab" (Mitsuba only: grey print, a lamp beside the
    # camera, black) or "randomized" (raster only: materials, lamps, backdrop and optics drawn
    # once per sequence by oibar_hil.randomize.look_for(look_seed), issue 58 part 3).
    renderer: str = "raster"
    look: str = "matched"
    mitsuba_spp: int = 64
    # The randomised look's seed; None: the trajectory's `seed` (its own stream of it).
    look_seed: int | None = None

    def validate(self) -> None:
        if self.frame_stride < 1:
            raise ValueError(f"{self.name}: frame_stride must be >= 1")
        if self.port not in PORTS:
            raise ValueError(f"{self.name}: port {self.port} not in 1..6")
        if PORTS[self.port].approach != self.approach:
            raise ValueError(
                f"{self.name}: port {self.port} is a {PORTS[self.port].approach} port, not {self.approach}"
            )
        if self.background not in ("iss", "perlin"):
            raise ValueError(f"{self.name}: background must be iss or perlin")
        if self.image_format not in ("jpg", "png"):
            raise ValueError(f"{self.name}: image_format must be jpg or png")
        if not 0.0 <= self.turned_deg <= 10.0:
            raise ValueError(
                f"{self.name}: turned_deg must be 0-10 deg (the mechanism's capture limit), "
                f"got {self.turned_deg}"
            )
        if not 0.0 <= self.offaxis_m <= 1.0:
            raise ValueError(f"{self.name}: offaxis_m must be 0-1 m, got {self.offaxis_m}")
        if not -180.0 <= self.rolled_deg <= 180.0:
            raise ValueError(f"{self.name}: rolled_deg must be -180-180 deg, got {self.rolled_deg}")
        if self.renderer not in ("raster", "mitsuba"):
            raise ValueError(f"{self.name}: renderer must be raster or mitsuba, got {self.renderer!r}")
        if (
            self.look not in ("matched", "lab", "randomized")
            or (self.look == "lab" and self.renderer != "mitsuba")
            or (self.look == "randomized" and self.renderer != "raster")
        ):
            raise ValueError(
                f"{self.name}: look must be matched, lab with the mitsuba renderer, "
                f"or randomized with the raster renderer; got {self.look!r}"
            )
        if self.mitsuba_spp < 1:
            raise ValueError(f"{self.name}: mitsuba_spp must be >= 1")


def spec_dict(spec: SequenceSpec) -> dict:
    """The spec as stored in spec.json and the manifest. Fields added after a dataset was written
    are left out at their default, so existing datasets keep their identity."""
    d = asdict(spec)
    if d.get("frame_stride") == 1:
        del d["frame_stride"]
    if d.get("turned_deg") == 0.0:
        del d["turned_deg"]
    if d.get("offaxis_m") == 0.0:
        del d["offaxis_m"]
    if d.get("rolled_deg") == 0.0:
        del d["rolled_deg"]
    if d.get("renderer") == "raster":
        del d["renderer"], d["mitsuba_spp"]
        if d.get("look") == "matched":
            del d["look"]
    if d.get("look_seed") is None:
        del d["look_seed"]
    return d


def spec_look(spec: SequenceSpec) -> LookParams | None:
    """The randomised look a spec draws (None for the others)."""
    if spec.look != "randomized":
        return None
    return look_for(spec.seed if spec.look_seed is None else spec.look_seed)


def _paper(n: int, port: int, approach: str, sun: float, bg: str) -> SequenceSpec:
    return SequenceSpec(
        name=f"seq{n:02d}", port=port, approach=approach, sun_elevation_deg=sun, background=bg, seed=1000 + n
    )


# SPEC section 6 (the paper's table); seeds are ours.
PAPER_SEQUENCES = {
    1: _paper(1, 1, "+V-bar", 37, "iss"),
    2: _paper(2, 1, "+V-bar", 75, "perlin"),
    3: _paper(3, 2, "-R-bar", 56, "iss"),
    4: _paper(4, 2, "-R-bar", 146, "perlin"),
    5: _paper(5, 3, "-V-bar", 127, "perlin"),
    6: _paper(6, 3, "-V-bar", 165, "iss"),
    7: _paper(7, 4, "-R-bar", 56, "perlin"),
    8: _paper(8, 4, "-R-bar", 146, "iss"),
    9: _paper(9, 5, "+R-bar", 56, "iss"),
    10: _paper(10, 5, "+R-bar", 146, "perlin"),
    11: _paper(11, 6, "+R-bar", 56, "perlin"),
    12: _paper(12, 6, "+R-bar", 146, "iss"),
}


# ----------------------------------------------------------------------------- planning
@dataclass
class SequencePlan:
    spec: SequenceSpec
    n_frames: int
    t_s: np.ndarray
    phase: np.ndarray
    distance_m: np.ndarray
    T_cam_target: np.ndarray
    q_cam_target: np.ndarray
    R_lvlh_cam: np.ndarray
    p_lvlh_cam: np.ndarray
    sun_lvlh: np.ndarray
    R_ecef_lvlh: np.ndarray
    earth_center_lvlh_km: np.ndarray
    orbit_info: dict = field(default_factory=dict)
    trajectory_info: dict = field(default_factory=dict)

    @property
    def range_m(self) -> np.ndarray:
        return np.linalg.norm(self.T_cam_target, axis=1)


def plan_sequence(
    spec: SequenceSpec, frames_limit: int | None = None, params: TrajectoryParams | None = None
) -> SequencePlan:
    spec.validate()
    traj = generate(
        spec.seed,
        envelope=spec.envelope,
        params=params,
        turned_deg=spec.turned_deg,
        offaxis_m=spec.offaxis_m,
        rolled_deg=spec.rolled_deg,
    )
    port = PORTS[spec.port]
    cp = camera_poses(traj, port)
    keep = np.arange(0, len(traj), spec.frame_stride)
    if frames_limit is not None:
        keep = keep[:frames_limit]
    n = len(keep)
    orbit = TargetOrbit(DEFAULT_TLE)
    start = orbit.time_for_sun_elevation(parse_utc(spec.epoch_utc), spec.sun_elevation_deg)
    jd0 = julian_date(start)
    sun = np.empty((n, 3))
    R_ecef = np.empty((n, 3, 3))
    cache: dict[float, np.ndarray] = {}
    for j, k in enumerate(keep):
        t = float(traj.t_s[k])
        tq = np.floor(t / SUN_UPDATE_S + 1e-9) * SUN_UPDATE_S
        if tq not in cache:
            cache[tq] = orbit.state(jd0 + tq / 86400.0).sun_lvlh
        sun[j] = cache[tq]
        R_ecef[j] = orbit.state(jd0 + t / 86400.0).R_ecef_lvlh
    st0 = orbit.state(jd0)
    orbit_info = {
        "tle": list(DEFAULT_TLE),
        "start_utc": start.isoformat(),
        "altitude_km": round(st0.altitude_km, 3),
        "beta_deg": round(st0.beta_deg, 4),
        "sun_update_s": SUN_UPDATE_S,
        "lvlh": "ISS/NASA: +X V-bar (velocity), +Z R-bar (to Earth centre), +Y negative orbit normal",
    }
    return SequencePlan(
        spec=spec,
        n_frames=n,
        t_s=traj.t_s[keep],
        phase=traj.phase[keep],
        distance_m=traj.distance_m[keep],
        T_cam_target=cp.T_cam_target[keep],
        q_cam_target=cp.q_cam_target[keep],
        R_lvlh_cam=cp.R_lvlh_cam[keep],
        p_lvlh_cam=cp.p_lvlh_cam[keep],
        sun_lvlh=sun,
        R_ecef_lvlh=R_ecef,
        earth_center_lvlh_km=st0.earth_center_lvlh_km,
        orbit_info=orbit_info,
        trajectory_info={**traj.info, "frames_total": len(traj), "params": asdict(traj.params)},
    )


# ----------------------------------------------------------------------------- files
def frame_name(k: int, fmt: str) -> str:
    return f"frames/{k:06d}.{fmt}"


def encode_image(img: np.ndarray, spec: SequenceSpec) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    im = Image.fromarray(img)
    if spec.image_format == "jpg":
        im.save(buf, format="JPEG", quality=spec.jpeg_quality, subsampling=0)
    else:
        im.save(buf, format="PNG", compress_level=spec.png_compress_level)
    return buf.getvalue()


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
    os.replace(tmp, path)


def write_poses_csv(path: Path, plan: SequencePlan) -> None:
    R_cam_lvlh = np.transpose(plan.R_lvlh_cam, (0, 2, 1))
    sun_cam = np.einsum("nij,nj->ni", R_cam_lvlh, plan.sun_lvlh)
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(POSES_COLUMNS)
    for k in range(plan.n_frames):
        t, q = plan.T_cam_target[k], plan.q_cam_target[k]
        w.writerow(
            [
                k,
                frame_name(k, plan.spec.image_format),
                f"{plan.t_s[k]:.3f}",
                int(plan.phase[k]),
                PHASE_NAMES[int(plan.phase[k])],
                f"{plan.distance_m[k]:.6f}",
                *(f"{x:.6f}" for x in t),
                *(f"{x:.9f}" for x in q),
                f"{plan.range_m[k]:.6f}",
                *(f"{x:.6f}" for x in sun_cam[k]),
            ]
        )
    _write_atomic(path, out.getvalue().encode())


def read_poses_csv(path: Path) -> list[dict]:
    """The pose table's rows as dicts of strings (oibar_hil.sequence.read_pose_table)."""
    return read_pose_table(path, ())[0]


# ----------------------------------------------------------------------------- rendering workers
_WORKER: dict = {}


def _worker_init(lp_threads: int) -> None:
    # Mesa's llvmpipe reads this when the context is created: one thread per worker process
    # scales better than threads inside one process.
    os.environ["LP_NUM_THREADS"] = str(lp_threads)


def load_spec_scene(r, spec: SequenceSpec) -> None:
    """Load `spec`'s scene into renderer `r` (render.Renderer or render_mitsuba's), as every frame
    of the spec is drawn with: its parts, backdrop, Perlin seed and, for a randomised look, the
    LookParams of spec_look (materials, lamps, backdrop and optics, placed in the port's axes).
    The rig's rendered camera (oibar_hil.rig.camera) loads its scene with this too."""
    from .meshes import scene_parts

    # the lab's mock-up is the fixture alone
    parts = scene_parts("perlin" if spec.look == "lab" else spec.background, spec.port)
    port = PORTS[spec.port]
    look = spec_look(spec)
    if look is None:
        r.load_scene(parts, spec.background, port.p_lvlh_t, perlin_seed=spec.seed)
    else:
        r.load_scene(
            parts,
            spec.background,
            port.p_lvlh_t,
            perlin_seed=spec.seed,
            look=look,
            R_lvlh_t=port.R_lvlh_t,
        )


def _renderer_for(spec: SequenceSpec):
    from .render import Renderer

    settings = RenderSettings(noise_sigma_dn=spec.noise_sigma_dn, blur_sigma_px=spec.blur_sigma_px)
    kind = (spec.renderer, spec.look, spec.mitsuba_spp, spec.seed) if spec.renderer == "mitsuba" else "raster"
    r = _WORKER.get("renderer")
    if r is None or r.settings != settings or _WORKER.get("kind") != kind:
        if r is not None and hasattr(r, "release"):
            r.release()
        if spec.renderer == "mitsuba":
            from .render_mitsuba import MitsubaRenderer, MitsubaSettings

            r = MitsubaRenderer(
                PinholeCamera(), settings, MitsubaSettings(spp=spec.mitsuba_spp), spec.seed, spec.look
            )
        else:
            r = Renderer(PinholeCamera(), settings)
        _WORKER["renderer"], _WORKER["kind"] = r, kind
        _WORKER["scene"] = None
    key = (spec.background, spec.port, spec.seed, spec.look, spec.look_seed)
    if _WORKER.get("scene") != key:
        load_spec_scene(r, spec)
        _WORKER["scene"] = key
    return r


def _render_chunk(task: dict) -> int:
    spec: SequenceSpec = task["spec"]
    r = _renderer_for(spec)
    seq_dir = Path(task["seq_dir"])
    for j, k in enumerate(task["frames"]):
        rng = np.random.default_rng([spec.seed, k]) if spec.noise_sigma_dn > 0 else None
        # a path tracer's samples are seeded per frame, whichever worker draws it
        extra = {"seed": k} if spec.renderer == "mitsuba" else {}
        img = r.render(
            task["R_lvlh_cam"][j],
            task["p_lvlh_cam"][j],
            task["sun_lvlh"][j],
            task["R_ecef_lvlh"][j],
            task["earth_center_lvlh_km"],
            rng=rng,
            **extra,
        )
        _write_atomic(seq_dir / frame_name(k, spec.image_format), encode_image(img, spec))
    return len(task["frames"])


# A render worker that dies (Mesa has been seen to crash with SIGSEGV inside libc, once in ~20k
# frames) must not hang the writer, as multiprocessing.Pool does when a worker vanishes: the
# executor reports a broken pool, and the chunks not yet done go to a fresh pool.
POOL_RESTARTS = 3


def _render_in_pool(tasks: list[dict], workers: int, cpu: int, bar, fn=None) -> str:
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    ctx = mp.get_context("spawn")  # never fork a process that may hold a GL context
    todo = list(range(len(tasks)))
    for attempt in range(POOL_RESTARTS + 1):
        done = set()
        try:
            with ProcessPoolExecutor(
                workers, mp_context=ctx, initializer=_worker_init, initargs=(max(1, cpu // workers),)
            ) as pool:
                futures = {pool.submit(fn or _render_chunk, tasks[i]): i for i in todo}
                for fut in as_completed(futures):
                    n = fut.result()
                    done.add(futures[fut])
                    if bar:
                        bar.update(n)
                return pool.submit(gl_renderer_name).result()
        except BrokenProcessPool:
            todo = [i for i in todo if i not in done]
            print(
                f"\nwarning: a render worker died; restarting the pool for the {len(todo)} chunk(s) left "
                f"(attempt {attempt + 1} of {POOL_RESTARTS})",
                file=sys.stderr,
            )
    raise DatasetError(
        f"render workers kept dying ({POOL_RESTARTS + 1} pools); {len(todo)} chunk(s) not rendered. "
        "Run the same command again to resume."
    )


def gl_renderer_name() -> str:
    r = _WORKER.get("renderer")
    return r.gl_renderer if r is not None else "unknown"


# ----------------------------------------------------------------------------- sequence bookkeeping
def _spec_identity(spec: SequenceSpec) -> dict:
    look = {"look_version": LOOK_VERSION} if spec.look == "randomized" else {}
    return {"generator_version": __version__, **look, **spec_dict(spec)}


def prepare_sequence_dir(seq_dir: Path, spec: SequenceSpec, force: bool = False) -> None:
    seq_dir.mkdir(parents=True, exist_ok=True)
    (seq_dir / "frames").mkdir(exist_ok=True)
    spec_path = seq_dir / "spec.json"
    ident = _spec_identity(spec)
    if spec_path.exists() and not force:
        old = json.loads(spec_path.read_text())
        if old != ident:
            raise DatasetError(
                f"{seq_dir}: holds a different sequence spec ({spec_path}); use a new --out folder or --force"
            )
    if force:
        for p in (seq_dir / "frames").glob("*"):
            p.unlink()
        for name in ("manifest.json", "poses.csv"):
            (seq_dir / name).unlink(missing_ok=True)
    spec_path.write_text(json.dumps(ident, indent=2, sort_keys=True) + "\n")


def pending_frames(seq_dir: Path, plan: SequencePlan) -> list[int]:
    """Frames that still need rendering: missing, or failing the trailer check."""
    todo = []
    for k in range(plan.n_frames):
        if check_image_trailer(seq_dir / frame_name(k, plan.spec.image_format)) is not None:
            todo.append(k)
    return todo


def write_manifest(seq_dir: Path, plan: SequencePlan, frames_limit: int | None, gl_renderer: str) -> dict:
    files = {"poses.csv": sha256_file(seq_dir / "poses.csv")}
    for k in range(plan.n_frames):
        name = frame_name(k, plan.spec.image_format)
        reason = check_image_trailer(seq_dir / name)
        if reason is not None:
            raise DatasetError(f"{seq_dir / name}: {reason}")
        files[name] = sha256_file(seq_dir / name)
    s = plan.spec
    manifest = {
        "generator": GENERATOR,
        "generator_version": __version__,
        "seed": s.seed,
        "spec": spec_dict(s),
        "frames": plan.n_frames,
        "frames_limit": frames_limit,
        "frames_total_in_trajectory": plan.trajectory_info["frames_total"],
        "frame_rate_hz": 1.0 / plan.trajectory_info["params"]["dt_s"],
        "config": {
            "camera": PinholeCamera().as_dict(),
            "camera_mount": asdict(MOUNT),
            "render": asdict(RenderSettings(noise_sigma_dn=s.noise_sigma_dn, blur_sigma_px=s.blur_sigma_px)),
            "trajectory": plan.trajectory_info,
            "orbit": plan.orbit_info,
            "fixture": asdict(FIXTURE),
            # what a randomised look drew (oibar_hil.randomize); absent for the others
            **({"look": look.as_dict()} if (look := spec_look(s)) is not None else {}),
        },
        "labels": "T_cam_target = fixture origin in camera frame (OpenCV axes), m; "
        "q_cam_target = (w,x,y,z) of R_cam_target (F_t -> camera); see docs/synthetic.md",
        "gl_renderer": gl_renderer,
        "files": files,
    }
    _write_atomic(seq_dir / "manifest.json", (json.dumps(manifest, indent=1, sort_keys=True) + "\n").encode())
    return manifest


def verify_sequence(seq_dir: Path) -> dict:
    """Check every file listed in the manifest: present, complete, same SHA-256. Raises
    DatasetError naming the bad files. Returns the manifest."""
    manifest = read_manifest(seq_dir)
    verify_files(seq_dir, manifest)
    return manifest


# ----------------------------------------------------------------------------- driver
@dataclass
class GenerateReport:
    rendered: int = 0
    skipped: int = 0
    sequences_complete: int = 0
    seconds: float = 0.0
    per_sequence: dict = field(default_factory=dict)

    @property
    def fps(self) -> float:
        return self.rendered / self.seconds if self.seconds > 0 else 0.0


def generate_dataset(
    out_dir: Path,
    specs: list[SequenceSpec],
    frames_limit: int | None = None,
    workers: int = 2,
    force: bool = False,
    progress: bool = True,
) -> GenerateReport:
    out_dir = Path(out_dir)
    report = GenerateReport()
    t_start = time.perf_counter()
    tasks, plans = [], {}
    for spec in specs:
        seq_dir = out_dir / spec.name
        plan = plan_sequence(spec, frames_limit)
        plans[spec.name] = (seq_dir, plan)
        if not force and (seq_dir / "manifest.json").exists():
            try:
                m = verify_sequence(seq_dir)
                if m["spec"] == spec_dict(spec) and m["frames"] == plan.n_frames:
                    report.skipped += plan.n_frames
                    report.per_sequence[spec.name] = {"rendered": 0, "skipped": plan.n_frames}
                    continue
            except DatasetError:
                pass  # fall through: re-render what is bad
            (seq_dir / "manifest.json").unlink()
        prepare_sequence_dir(seq_dir, spec, force=force)
        write_poses_csv(seq_dir / "poses.csv", plan)
        todo = pending_frames(seq_dir, plan)
        report.skipped += plan.n_frames - len(todo)
        report.per_sequence[spec.name] = {"rendered": len(todo), "skipped": plan.n_frames - len(todo)}
        for i in range(0, len(todo), CHUNK_FRAMES):
            idx = np.array(todo[i : i + CHUNK_FRAMES])
            tasks.append(
                {
                    "spec": spec,
                    "seq_dir": str(seq_dir),
                    "frames": idx.tolist(),
                    "R_lvlh_cam": plan.R_lvlh_cam[idx],
                    "p_lvlh_cam": plan.p_lvlh_cam[idx],
                    "sun_lvlh": plan.sun_lvlh[idx],
                    "R_ecef_lvlh": plan.R_ecef_lvlh[idx],
                    "earth_center_lvlh_km": plan.earth_center_lvlh_km,
                }
            )

    total = sum(len(t["frames"]) for t in tasks)
    bar = None
    if progress:
        from oibar.progress import Progress

        bar = Progress("rendering", total=total, unit="frame")
    t_render = time.perf_counter()
    gl_name = "unknown"
    if total:
        cpu = os.cpu_count() or 1
        if workers <= 1:
            os.environ.setdefault("LP_NUM_THREADS", str(cpu))
            for task in tasks:
                n = _render_chunk(task)
                if bar:
                    bar.update(n)
            gl_name = gl_renderer_name()
        else:
            gl_name = _render_in_pool(tasks, workers, cpu, bar)
    if bar:
        bar.close()
    report.rendered = total
    report.seconds = time.perf_counter() - t_render

    for name, (seq_dir, plan) in plans.items():
        if report.per_sequence[name]["rendered"] == 0 and (seq_dir / "manifest.json").exists():
            report.sequences_complete += 1
            continue
        write_manifest(seq_dir, plan, frames_limit, gl_name)
        report.sequences_complete += 1
    report.per_sequence["_wall_s"] = round(time.perf_counter() - t_start, 2)
    return report


def parse_seqs(text: str | None) -> list[int]:
    if not text:
        return sorted(PAPER_SEQUENCES)
    out: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part:
            a, b = part.split("-")
            out.extend(range(int(a), int(b) + 1))
        elif part:
            out.append(int(part))
    bad = [n for n in out if n not in PAPER_SEQUENCES]
    if bad:
        raise SystemExit(f"unknown sequence(s) {bad}: the paper's are 1..12")
    return out


def shard(specs: list[SequenceSpec], text: str) -> list[SequenceSpec]:
    """`I/N`: every N-th sequence starting at I. Sequences are the unit (each has its own folder and
    manifest), so N jobs write disjoint folders and need no coordination."""
    try:
        i, n = (int(x) for x in text.split("/"))
    except ValueError:
        raise ValueError(f"--shard {text!r}: expected I/N, e.g. 0/4") from None
    if n < 1 or not 0 <= i < n:
        raise ValueError(f"--shard {text!r}: need 0 <= I < N")
    return specs[i::n]


def load_spec_file(path: Path) -> list[SequenceSpec]:
    """Sequences beyond the paper's 12: a JSON list of SequenceSpec fields, or an object whose
    "scenes" holds that list (the committed scene sets, models/scenes/*.json). A paper sequence
    can be named as {"paper": N}."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read the scene spec ({exc})") from exc
    items = data.get("scenes", []) if isinstance(data, dict) else data
    specs = []
    for i, item in enumerate(items if isinstance(items, list) else [items]):
        try:
            if isinstance(item, dict) and set(item) == {"paper"}:
                spec = PAPER_SEQUENCES[int(item["paper"])]
            else:
                spec = SequenceSpec(**item)
            spec.validate()
        except (TypeError, ValueError, KeyError) as exc:
            raise DatasetError(f"{path}: scene {i}: {exc}") from exc
        specs.append(spec)
    names = [s.name for s in specs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise DatasetError(f"{path}: scene names used twice: {dup}")
    return specs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m oibar_hil.dataset", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path, help="output folder (one sub-folder per sequence)")
    ap.add_argument("--seqs", help="paper sequences, e.g. 1,8 or 1-12 (default: all 12)")
    ap.add_argument("--spec", type=Path, help="JSON file with custom sequence specs (instead of --seqs)")
    ap.add_argument(
        "--frames-limit", type=int, default=None, help="render only the first N frames of each sequence"
    )
    ap.add_argument(
        "--workers", type=int, default=os.cpu_count() or 1, help="render processes (default: CPU count)"
    )
    ap.add_argument("--format", choices=("jpg", "png"), default=None, help="frame format (default jpg)")
    ap.add_argument(
        "--envelope", action="store_true", help="envelope mode (+-10 deg, <= 50 mm/s) for the paper sequences"
    )
    ap.add_argument("--force", action="store_true", help="discard existing frames of the chosen sequences")
    ap.add_argument(
        "--verify", action="store_true", help="only verify existing sequences against their manifests"
    )
    ap.add_argument(
        "--shard",
        default=None,
        metavar="I/N",
        help="render only sequences I, I+N, I+2N, ... of the list (0 <= I < N): one shard per "
        "batch job, all writing into the same --out",
    )
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)

    if args.spec:
        try:
            specs = load_spec_file(args.spec)
        except DatasetError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    else:
        specs = [PAPER_SEQUENCES[n] for n in parse_seqs(args.seqs)]
    if args.format:
        specs = [replace(s, image_format=args.format) for s in specs]
    if args.envelope:
        specs = [replace(s, envelope=True, name=s.name + "_envelope") for s in specs]
    if args.shard:
        try:
            specs = shard(specs, args.shard)
        except ValueError as exc:
            ap.error(str(exc))

    if args.verify:
        bad = 0
        for s in specs:
            try:
                m = verify_sequence(args.out / s.name)
                print(f"{s.name}: OK ({m['frames']} frames)")
            except DatasetError as exc:
                bad += 1
                print(f"{s.name}: FAILED\n{exc}", file=sys.stderr)
        return 1 if bad else 0

    try:
        rep = generate_dataset(
            args.out, specs, args.frames_limit, args.workers, args.force, not args.no_progress
        )
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(
        f"rendered {rep.rendered} frames in {rep.seconds:.1f} s ({rep.fps:.1f} frames/s), "
        f"skipped {rep.skipped} already done, {rep.sequences_complete} sequence(s) complete in {args.out}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
