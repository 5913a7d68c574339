"""A rendered sequence made into a lab recording: what a motion-capture lab brings home from one
approach, so that a stand-in for a lab run goes through the calibration toolbox (`oibar calib
extract`, `apply`, `to-dataset`; docs/calibration.md) exactly as a real run would.

For each sequence folder of the data set generator (oibar_hil.dataset; docs/synthetic.md,
"Dataset layout") it writes REC_ROOT/<sequence name>/:

  video.avi       the camera's video, lossless (FFV1): decoded pixels are the sequence's
                  decoded frames, bit for bit
  mocap.csv       the toolbox's long layout, 100 Hz, rigid bodies `housing` (the camera housing)
                  and `tmarkers` (the target's markers), with the mocap noise of the paper and a
                  few one-sample occlusions (NaN rows)
  recording.json  the lab's log of the run: camera rate, which frames to extract, body names,
                  files and their SHA-256
  truth.json      what the lab does not know: the rig transforms, the offset, the room placement
                  of the target, the seed, the source sequence and its SHA-256s

The lab rig is calib_synth's (SynthConfig's defaults: T_housing_cam, T_tmarkers_target, offset_s,
mocap noise and rate), so one calibration, estimated from `--calibration`'s recording (calib_synth's
own writer, REC_ROOT/calibration/), labels every run. The lab is hardware-synchronised: mocap time
= camera frame time + offset_s, the same offset in every recording. The target stands still on a
stand in the mocap room (a fixed T_mocap_target) and the camera moves, as on the paper's robot arm.

The camera's motion between frames is the trajectory's own: the sequence's trajectory is planned
again at its full base rate (plan_sequence with frame_stride 1), checked against poses.csv at the
rendered frames (1e-6), and the camera pose in the target frame is interpolated through every
base-rate sample (position: cubic spline; attitude: scipy's RotationSpline), then sampled at the
mocap's 100 Hz. Before the first sample and after the last the camera keeps its end velocity.

Why the video runs at the trajectory's 10 Hz with black frames between the rendered ones: the
frames are every `frame_stride`-th (48th for the lab stand-ins) sample of a 10 Hz trajectory, so
the true camera rate would be 10/48 = 0.2083 fps. OpenCV's FFmpeg writer turns a frame rate into
a decimal fraction within 0.001 (0.2083 fps becomes 208/1000), so the video's time stamps would
come back from `extract` 4.8077 s apart instead of 4.8 s: 0.6 s off by the 80th frame, and every
label would then belong to another pose. The honest alternative kept here: the camera runs at the
base rate, where time stamps round-trip exactly (frame i at i x 0.1 s), the frames the renderer
drew are at their own instants, and the samples it did not draw are black (nothing was rendered
there; FFV1 stores a black frame in a few kilobytes). `oibar calib extract --every <frame_stride>`
(recording.json's `extract_every`) keeps exactly the drawn frames, numbered by their base-rate
sample. Every video is read back as `extract` reads it before the recording is kept: drawn frames
bit-identical, black frames black, time stamps within 1 us.

Deterministic: the same input and --seed give the same files, byte for byte (noise and
occlusions are drawn from the seed and the sequence's name). Written into a hidden sibling
folder, renamed when complete; a recording already there from the same input is left alone.

CLI:  python -m oibar_hil.lab_recording SEQ_DIR [SEQ_DIR ...] --out REC_ROOT [--seed N] [--calibration]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import zlib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from oibar.geometry.transforms import inv_T, make_T
from oibar.hashing import sha256_file

from .calib_synth import SynthConfig, body_noise, write_mocap_csv
from .dataset import GENERATOR, SequenceSpec, plan_sequence
from .sequence import DatasetError, read_manifest, read_pose_table, verify_files

FORMAT = "oibar-lab-recording/1"
# The rigid-body names of calib_synth's recordings: one calibration names the same bodies.
HOUSING_BODY = "housing"
TARGET_BODY = "tmarkers"
VIDEO = "video.avi"  # AVI, not Matroska: its muxer writes random UIDs, AVI the same bytes each run
VIDEO_FOURCC = "FFV1"  # lossless, intra-only: every frame decodes to the pixels written
MOCAP = "mocap.csv"
MARGIN_S = 1.0  # mocap before the first and after the last frame, as calib_synth records
OCCLUSIONS_PER_BODY = 3
CALIBRATION_DIR = "calibration"
PLAN_TOL = 1e-6  # poses.csv (6 and 9 decimals) against the re-planned trajectory
TIME_TOL_S = 1e-6  # video time stamps against the trajectory's

# The target's stand in the mocap room (z up, floor at 0): 11 m down the hall at 2.2 m, its
# docking axis +Z_t along the room's +X and its +Y_t (the image's down) to the floor, so the
# approach from 10.3 m to contact runs level along the hall.
T_MOCAP_TARGET = make_T(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), [11.0, 0.0, 2.2])


class LabRecordingError(RuntimeError):
    """Bad input or a recording that cannot be written; the message is one line."""


# ----------------------------------------------------------------------------- the source sequence
@dataclass
class Source:
    seq_dir: Path
    name: str
    spec: SequenceSpec
    stride: int
    dt_s: float
    frame_files: list[Path]  # the rendered frames, in order
    time_s: np.ndarray  # (n,) their times, the trajectory's clock
    T_cam_target: np.ndarray  # (n, 4, 4) poses.csv's labels
    sha256: dict


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())


def read_source(seq_dir: Path) -> Source:
    """A complete sequence of the data set generator, every file checked against its manifest."""
    seq_dir = Path(seq_dir)
    if not seq_dir.is_dir():
        raise LabRecordingError(f"{seq_dir}: no such folder (a sequence written by oibar_hil.dataset)")
    if not (seq_dir / "manifest.json").is_file():
        raise LabRecordingError(
            f"{seq_dir}: not a complete generator sequence (no manifest.json; still rendering?)"
        )
    try:
        manifest = read_manifest(
            seq_dir,
            required=lambda m: (
                m["spec"],
                int(m["frames"]),
                float(m["config"]["trajectory"]["params"]["dt_s"]),
            ),
        )
    except DatasetError as exc:
        raise LabRecordingError(_one_line(exc)) from None
    if manifest.get("generator") != GENERATOR:
        raise LabRecordingError(
            f"{seq_dir}: not a sequence of the data set generator (generator {manifest.get('generator')!r}, "
            f"source {manifest.get('source', 'rendered')!r}): only rendered sequences stand in for lab runs"
        )
    try:
        spec = SequenceSpec(**manifest["spec"])
        spec.validate()
    except (TypeError, ValueError) as exc:
        raise LabRecordingError(f"{seq_dir}/manifest.json: not a sequence spec ({exc})") from None
    try:
        verify_files(seq_dir, manifest)  # a missing, truncated or altered frame or pose table
        rows, num = read_pose_table(
            seq_dir / "poses.csv", ("time_s", "tx_m", "ty_m", "tz_m", "qw", "qx", "qy", "qz"), ("file",)
        )
    except DatasetError as exc:
        raise LabRecordingError(_one_line(exc)) from None
    n = int(manifest["frames"])
    if len(rows) != n:
        raise LabRecordingError(f"{seq_dir}/poses.csv: {len(rows)} rows, the manifest says {n} frames")
    files = [seq_dir / r["file"] for r in rows]
    absent = [str(f) for f in files if not f.is_file()]
    if absent:
        raise LabRecordingError(f"{seq_dir}: frame file(s) missing: {', '.join(absent[:3])}")
    dt_s = float(manifest["config"]["trajectory"]["params"]["dt_s"])
    t_m, q_wxyz = num[:, 1:4], num[:, 4:8]
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_quat(q_wxyz[:, [1, 2, 3, 0]]).as_matrix()
    T[:, :3, 3] = t_m
    sha = {name: sha256_file(seq_dir / name) for name in ("manifest.json", "spec.json", "poses.csv")}
    return Source(seq_dir, spec.name, spec, spec.frame_stride, dt_s, files, num[:, 0], T, sha)


# ----------------------------------------------------------------------------- the camera's motion
class CameraMotion:
    """T_target_cam(t) through every base-rate sample of the trajectory: a cubic spline in
    position and a rotation spline in attitude (C2, exact at the samples); outside the trajectory
    the camera keeps its end velocity and angular rate (the recording runs a second either side)."""

    def __init__(self, t_s: np.ndarray, T_target_cam: np.ndarray):
        self.t_s = np.asarray(t_s, float)
        self.p = CubicSpline(self.t_s, T_target_cam[:, :3, 3])
        self.R = RotationSpline(self.t_s, Rotation.from_matrix(T_target_cam[:, :3, :3]))
        h = 1e-4  # end rates, from the splines themselves, so the extrapolation continues them
        self._ends = []
        for t_end, sign in ((self.t_s[0], 1.0), (self.t_s[-1], -1.0)):
            R0, R1 = self.R([t_end, t_end + sign * h])
            w_body = (R0.inv() * R1).as_rotvec() / (sign * h)
            self._ends.append((t_end, self.p(t_end), self.p(t_end, 1), R0, w_body))

    def T_target_cam(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, float)
        inside = np.clip(t, self.t_s[0], self.t_s[-1])
        p = self.p(inside)
        R = self.R(inside).as_matrix()
        for (t_end, p_end, v_end, R_end, w_body), out in zip(
            self._ends, (t < self.t_s[0], t > self.t_s[-1]), strict=True
        ):
            if out.any():
                dt = (t[out] - t_end)[:, None]
                p[out] = p_end + dt * v_end
                R[out] = (R_end * Rotation.from_rotvec(dt * w_body)).as_matrix()
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, :3], T[:, :3, 3] = R, p
        return T


def source_motion(src: Source) -> tuple[CameraMotion, np.ndarray, np.ndarray]:
    """The sequence's trajectory at its full base rate, checked against poses.csv at the rendered
    frames; returns the motion, the base-rate index of every rendered frame and its time on the
    camera's clock (the video's: sample i at i x dt)."""
    plan = plan_sequence(replace(src.spec, frame_stride=1))
    idx = src.stride * np.arange(len(src.time_s))
    if idx[-1] >= plan.n_frames:
        raise LabRecordingError(
            f"{src.seq_dir}: {len(idx)} frames every {src.stride} do not fit its trajectory "
            f"({plan.n_frames} samples): not this spec's sequence?"
        )
    T_ct = np.tile(np.eye(4), (plan.n_frames, 1, 1))
    T_ct[:, :3, :3] = Rotation.from_quat(plan.q_cam_target[:, [1, 2, 3, 0]]).as_matrix()
    T_ct[:, :3, 3] = plan.T_cam_target
    motion = CameraMotion(plan.t_s, inv_T(T_ct))
    at_frames = inv_T(motion.T_target_cam(plan.t_s[idx]))
    camera_time_s = idx * src.dt_s
    dt = max(np.abs(plan.t_s[idx] - src.time_s).max(), np.abs(plan.t_s[idx] - camera_time_s).max())
    dp = np.abs(at_frames[:, :3, 3] - src.T_cam_target[:, :3, 3]).max()
    dR = np.abs(at_frames[:, :3, :3] - src.T_cam_target[:, :3, :3]).max()
    if dt > 1e-3 or dp > PLAN_TOL or dR > 2 * PLAN_TOL:
        raise LabRecordingError(
            f"{src.seq_dir}/poses.csv is not its spec's trajectory (times {dt:.1e} s, positions "
            f"{dp:.1e} m, rotations {dR:.1e} off): rendered by another generator version?"
        )
    return motion, idx, camera_time_s


# ----------------------------------------------------------------------------- mocap
def _occlusions(rng: np.random.Generator, t_mocap_s: np.ndarray, t_query_s: np.ndarray, count: int) -> list:
    """`count` one-sample dropouts, never two within 3 samples (a gap of 2 sample periods is
    bridged by `apply`, a longer one is not), the first on a sample a frame's label is
    interpolated from, so the demonstration goes through the toolbox's gap handling."""
    n = len(t_mocap_s)
    if count <= 0 or n < 10:
        return []
    picks: list[int] = []
    k = int(rng.integers(len(t_query_s)))
    picks.append(int(np.clip(np.searchsorted(t_mocap_s, t_query_s[k]) - rng.integers(2), 1, n - 2)))
    while len(picks) < count:
        i = int(rng.integers(1, n - 1))
        if all(abs(i - j) > 3 for j in picks):
            picks.append(i)
    return sorted(picks)


def mocap_samples(
    motion: CameraMotion,
    frame_time_s: np.ndarray,
    cfg: SynthConfig,
    rng: np.random.Generator,
    occlusions: int,
) -> dict:
    """Both bodies at the mocap rate over the frames' span plus MARGIN_S, mocap clock = camera
    clock + offset_s; occluded samples are NaN."""
    rate = cfg.mocap_rate_hz
    t_query = frame_time_s + cfg.offset_s
    n0 = int(np.floor((t_query[0] - MARGIN_S) * rate))
    n1 = int(np.ceil((t_query[-1] + MARGIN_S) * rate))
    t_mocap_s = np.arange(n0, n1 + 1) / rate
    T_mocap_cam = T_MOCAP_TARGET @ motion.T_target_cam(t_mocap_s - cfg.offset_s)
    T_mocap_housing = T_mocap_cam @ inv_T(cfg.T_housing_cam)
    T_mocap_tmarkers = np.broadcast_to(T_MOCAP_TARGET @ inv_T(cfg.T_tmarkers_target), T_mocap_housing.shape)
    occluded_s: dict[str, list[float]] = {}
    out: dict[str, Any] = {"t_s": t_mocap_s, "occluded_s": occluded_s}
    for body, T in ((HOUSING_BODY, T_mocap_housing), (TARGET_BODY, T_mocap_tmarkers)):
        # calib_synth's noise model, the one the calibration's settings assume (per axis / sqrt 3)
        T = body_noise(np.array(T), rng, cfg.sigma_t_m / np.sqrt(3), np.radians(cfg.sigma_r_deg) / np.sqrt(3))
        drop = _occlusions(rng, t_mocap_s, t_query, occlusions)
        T[drop] = np.nan
        out[body] = T
        occluded_s[body] = [round(float(t_mocap_s[i]), 4) for i in drop]
    return out


# ----------------------------------------------------------------------------- video
def _read_frame(path: Path):
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise LabRecordingError(f"{path}: cannot decode the frame")
    return img


def write_video(path: Path, src: Source, idx: np.ndarray, bar) -> dict:
    """The camera's video at the base rate: drawn frames at their samples, black between; then
    read back as `oibar calib extract` reads it and checked (pixels, time stamps)."""
    import cv2

    rate_hz = 1.0 / src.dt_s
    first = _read_frame(src.frame_files[0])
    h, w = first.shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*VIDEO_FOURCC), rate_hz, (w, h))
    if not writer.isOpened():
        raise LabRecordingError(f"{path}: OpenCV's FFmpeg cannot write {VIDEO_FOURCC} video here")
    black = np.zeros_like(first)
    drawn = {int(i): f for i, f in zip(idx, src.frame_files, strict=True)}
    n_video = int(idx[-1]) + 1
    try:
        for i in range(n_video):
            img = _read_frame(drawn[i]) if i in drawn else black
            if img.shape != first.shape:
                raise LabRecordingError(
                    f"{drawn[i]}: {img.shape[1]}x{img.shape[0]}, the first frame is {w}x{h}"
                )
            writer.write(img)
            bar.update(1)
    finally:
        writer.release()
    cap = cv2.VideoCapture(str(path))
    i = 0
    while True:
        ok, img = cap.read()
        if not ok:
            break
        t_s = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        if abs(t_s - i * src.dt_s) > TIME_TOL_S:
            raise LabRecordingError(
                f"{path}: frame {i} reads back at {t_s:.6f} s, not {i * src.dt_s:.6f} s "
                f"(OpenCV cannot write {rate_hz:g} fps exactly)"
            )
        want = _read_frame(drawn[i]) if i in drawn else black
        if img.shape != want.shape or not np.array_equal(img, want):
            raise LabRecordingError(f"{path}: frame {i} does not read back bit for bit")
        i += 1
        bar.update(1)
    cap.release()
    if i != n_video:
        raise LabRecordingError(f"{path}: {i} frames read back, {n_video} written")
    return {"frames": n_video, "rate_hz": rate_hz, "size_wh": [w, h]}


# ----------------------------------------------------------------------------- one recording
def _pose(T: np.ndarray) -> dict:
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    q = q if q[3] >= 0 else -q
    return {"t_m": [float(v) for v in T[:3, 3]], "q_wxyz": [float(v) for v in q[[3, 0, 1, 2]]]}


def _rig(cfg: SynthConfig) -> dict:
    return {
        "T_housing_cam": _pose(cfg.T_housing_cam),
        "T_tmarkers_target": _pose(cfg.T_tmarkers_target),
        "T_mocap_target": _pose(T_MOCAP_TARGET),
        "offset_s": cfg.offset_s,
        "offset_convention": "mocap time = frame time_s + offset_s",
        "mocap_rate_hz": cfg.mocap_rate_hz,
        "sigma_t_m": cfg.sigma_t_m,
        "sigma_r_deg": cfg.sigma_r_deg,
    }


def _identity(src: Source, seed: int, cfg: SynthConfig, occlusions: int) -> dict:
    return {
        "format": FORMAT,
        "seed": seed,
        "source_sha256": src.sha256,
        "rig": _rig(cfg),
        "occlusions_per_body": occlusions,
    }


def _kept(rec_dir: Path, ident: dict) -> bool:
    """True when rec_dir already holds this recording, complete and unaltered."""
    try:
        truth = json.loads((rec_dir / "truth.json").read_text())
        log = json.loads((rec_dir / "recording.json").read_text())
    except (OSError, ValueError):
        return False
    if truth.get("identity") != ident:
        return False
    return all(
        (rec_dir / name).is_file() and sha256_file(rec_dir / name) == digest
        for name, digest in log.get("files", {}).items()
    )


def write_lab_recording(
    seq_dir: Path,
    out_root: Path,
    seed: int = 1,
    rig: SynthConfig | None = None,
    occlusions: int = OCCLUSIONS_PER_BODY,
    force: bool = False,
    progress: bool = True,
) -> tuple[Path, bool]:
    """REC_ROOT/<name>/ for one sequence; returns (its folder, whether it was written now)."""
    from oibar.progress import Progress

    cfg = rig or SynthConfig()
    src = read_source(seq_dir)
    out_root = Path(out_root)
    rec_dir = out_root / src.name
    ident = _identity(src, seed, cfg, occlusions)
    if rec_dir.exists():
        if _kept(rec_dir, ident):
            return rec_dir, False
        if not force:
            raise LabRecordingError(
                f"{rec_dir}: holds another or an incomplete recording; pass --force to replace it"
            )
    motion, idx, camera_time_s = source_motion(src)
    # one stream per sequence: the recordings of one seed are independent of each other
    rng = np.random.default_rng([seed, zlib.crc32(src.name.encode())])
    mocap = mocap_samples(motion, camera_time_s, cfg, rng, occlusions)

    tmp = out_root / f".{src.name}.partial"
    if tmp.exists():
        shutil.rmtree(tmp)  # what a run that stopped left
    tmp.mkdir(parents=True)
    try:
        n_video = int(idx[-1]) + 1
        bar = (
            Progress(f"{src.name}: video (write, read back)", total=2 * n_video, unit="frame")
            if progress
            else None
        )
        try:
            video = write_video(tmp / VIDEO, src, idx, bar or _NoBar())
        finally:
            if bar:
                bar.close()
        write_mocap_csv(tmp / MOCAP, mocap, names=(HOUSING_BODY, TARGET_BODY))
        log = {
            "format": FORMAT,
            "run": src.name,
            "video": VIDEO,
            "video_codec": f"{VIDEO_FOURCC} (lossless) in AVI",
            "camera_rate_hz": video["rate_hz"],
            "camera_size_wh": video["size_wh"],
            "video_frames": video["frames"],
            "extract_every": src.stride,
            "drawn_frames": len(idx),
            "note": "only every extract_every-th frame was drawn (the others are black): "
            f"oibar calib extract {VIDEO} OUT --every {src.stride}",
            "mocap": MOCAP,
            "mocap_rate_hz": cfg.mocap_rate_hz,
            "mocap_units": "m",
            "housing_body": HOUSING_BODY,
            "target_body": TARGET_BODY,
            "clocks": "hardware-synchronised: one calibration's offset_s holds for every run",
            "files": {name: sha256_file(tmp / name) for name in (VIDEO, MOCAP)},
        }
        truth = {
            "format": FORMAT,
            "identity": ident,
            **_rig(cfg),
            "seed": seed,
            "source": {
                "path": str(src.seq_dir.resolve()),
                "name": src.name,
                "sha256": src.sha256,
                "frame_stride": src.stride,
                "frames": len(idx),
            },
            "frames": {"video_index": idx.tolist(), "time_s": [round(float(t), 6) for t in src.time_s]},
            "mocap_span_s": [float(mocap["t_s"][0]), float(mocap["t_s"][-1])],
            "occluded_s": mocap["occluded_s"],
        }
        (tmp / "recording.json").write_text(json.dumps(log, indent=2) + "\n")
        (tmp / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if rec_dir.exists():  # --force: the old one goes only once the new one is complete
        shutil.rmtree(rec_dir)
    os.replace(tmp, rec_dir)
    return rec_dir, True


class _NoBar:
    def update(self, n: float = 1) -> None:
        pass


def write_calibration_recording(out_root: Path) -> tuple[Path, bool]:
    """REC_ROOT/calibration/: calib_synth's calibration recording of the same rig (its own writer,
    its defaults), for `oibar calib estimate`; left alone when already there."""
    from . import calib_synth

    cfg = SynthConfig()
    out = Path(out_root) / CALIBRATION_DIR
    want = json.loads(json.dumps(calib_synth.truth(cfg)))
    if out.exists():
        try:
            same = json.loads((out / "truth.json").read_text()) == want
        except (OSError, ValueError):
            same = False
        if same:
            return out, False
        raise LabRecordingError(f"{out}: holds another or an incomplete calibration recording; remove it")
    tmp = Path(out_root) / f".{CALIBRATION_DIR}.partial"
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        calib_synth.write_recording(tmp, cfg)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    os.replace(tmp, out)
    return out, True


# ----------------------------------------------------------------------------- CLI
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m oibar_hil.lab_recording",
        description="Rendered sequences -> lab recordings (video + mocap CSV) for the calibration toolbox.",
    )
    ap.add_argument(
        "seq_dirs", nargs="+", type=Path, metavar="SEQ_DIR", help="sequences of oibar_hil.dataset"
    )
    ap.add_argument("--out", type=Path, required=True, help="REC_ROOT: one folder per sequence")
    ap.add_argument("--seed", type=int, default=1, help="mocap noise and occlusions (default 1)")
    ap.add_argument(
        "--calibration",
        action="store_true",
        help="also write REC_ROOT/calibration/: calib_synth's calibration recording of the same rig",
    )
    ap.add_argument("--force", action="store_true", help="replace a recording that holds something else")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    try:
        names = [p.name for p in a.seq_dirs]
        if len(set(names)) != len(names):
            raise LabRecordingError(f"two sequences of one name in {names}: their recordings would collide")
        for seq_dir in a.seq_dirs:
            rec, written = write_lab_recording(
                seq_dir, a.out, a.seed, force=a.force, progress=not a.no_progress
            )
            print(f"{rec}: {'written' if written else 'already there, left as it is'}", flush=True)
        if a.calibration:
            cal, written = write_calibration_recording(a.out)
            print(f"{cal}: {'written' if written else 'already there, left as it is'}", flush=True)
    except LabRecordingError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
