"""`oibar calib to-dataset`: a labelled lab recording -> one sequence in the data set generator's
layout (docs/synthetic.md, "Dataset layout"), which the training and evaluation code read unchanged
(oibar_hil.sequence.read_manifest, oibar_models.data.load_sequence).

Input: the folder `oibar calib extract` wrote (frames/ and frames.csv; or any frame index) with the
poses CSV `oibar calib apply` wrote for it (`-o LABELLED_DIR/poses.csv`), and the calibration JSON
the labels came from. Output folder: spec.json, frames/NNNNNN.png|jpg, poses.csv (the dataset's
columns: phase 0 "lab", Sun columns empty), manifest.json (written last) marking it a lab
recording (`"source": "lab"`) with its recording, the SHA-256 of the calibration, the poses and
the frame index, and the camera.

The frames are stored in the network's canonical camera (oibar.camera.calibration: 744x480,
f 583.33 px, principal point at the centre), the camera every model reads (its metadata's
K_frame): copied byte for byte when the lab camera is that camera, else undistorted and
resampled by the same remap the daemon applies with `--calibration`; a remap only changes the
intrinsics, so the labels stay as they are.

Refused (CalibError, the CLI's exit status 2): a frame of the index without a label (unless
`--drop-unlabelled`), a label whose pose is not finite or whose quaternion is not unit, a label
and an index that disagree on a frame's time, a frame that cannot be decoded, a frame of another
size than the camera's, intrinsics other than those the calibration was estimated with.
Atomic: everything is written into a hidden sibling folder that is renamed at the end; a run
that stopped leaves only that folder, which the next run removes. An existing output is kept when
it holds this very input (same hashes), else refused unless `--force`.
"""

from __future__ import annotations

import csv
import io as _io
import json
import os
import shutil
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from oibar.dataset_format import POSES_COLUMNS, read_pose_rows
from oibar.geometry.camera import PinholeCamera, intrinsics_corner_to_centre
from oibar.hashing import sha256_file

from . import io
from .errors import CalibError
from .pnp import Intrinsics

GENERATOR = "oibar calib to-dataset"
LABELS = (
    "T_cam_target = fixture origin in camera frame (OpenCV axes), m; "
    "q_cam_target = (w,x,y,z) of R_cam_target (F_t -> camera); see docs/synthetic.md; "
    "from motion capture (oibar calib apply), docs/calibration.md"
)
POSE_KEYS = ("tx_m", "ty_m", "tz_m", "qw", "qx", "qy", "qz")
QUAT_TOL = 1e-3  # |q| - 1 beyond this: a corrupt label (apply writes 9 decimals)
TIME_TOL_S = 5e-6  # apply writes time_s with 6 decimals
SAME_CAMERA_TOL = 1e-6  # relative, on K; distortion must be 0 within it


@dataclass
class Label:
    frame: int
    file: str
    time_s: float
    T_m: np.ndarray  # (3,)
    q_wxyz: np.ndarray  # (4,) unit
    distance_m: float | None


def _number(text: str | None, where: str, col: str) -> float:
    text = (text or "").strip()
    if not text or text.lower() == "nan":
        return float("nan")
    try:
        return float(text)
    except ValueError:
        raise CalibError(f"{where}: column {col!r}: not a number: {text!r}") from None


def read_labels(path: Path) -> list[Label]:
    """The poses CSV of `oibar calib apply` (or a dataset's poses.csv): one label per row, each
    checked (a finite pose, a unit quaternion, times increasing, no frame twice)."""
    rows = read_pose_rows(
        path,
        ("frame", "file", "time_s", *POSE_KEYS),
        CalibError,
        f"write it with `oibar calib apply ... -o {path}`",
    )
    labels = []
    for line, r in enumerate(rows, start=2):
        where = f"{path}:{line}"
        if None in r.values() or None in r:
            raise CalibError(f"{where}: the row has another number of fields than the header")
        try:
            frame = int(r["frame"])
        except ValueError:
            raise CalibError(f"{where}: frame {r['frame']!r} is not an integer") from None
        v = np.array([_number(r[k], where, k) for k in POSE_KEYS])
        t = _number(r["time_s"], where, "time_s")
        if not np.all(np.isfinite(v)) or not np.isfinite(t):
            raise CalibError(f"{where}: frame {frame} has no label (empty or NaN pose or time)")
        q = v[3:]
        if abs(np.linalg.norm(q) - 1.0) > QUAT_TOL:
            raise CalibError(f"{where}: quaternion norm {np.linalg.norm(q):.4f} is not 1 (corrupt label)")
        d = _number(r.get("distance_m"), where, "distance_m")
        labels.append(
            Label(frame, r["file"].strip(), t, v[:3], q / np.linalg.norm(q), d if np.isfinite(d) else None)
        )
    frames = [lb.frame for lb in labels]
    if len(set(frames)) != len(frames):
        raise CalibError(f"{path}: a frame is labelled twice")
    if np.any(np.diff([lb.time_s for lb in labels]) <= 0):
        raise CalibError(f"{path}: time_s must increase from row to row")
    return labels


def match_index(labels: list[Label], frames_csv: Path | None, drop_unlabelled: bool) -> list[Label]:
    """Check the labels against the recording's frame index: every frame labelled (or, with
    `drop_unlabelled`, left out), each label a frame of the index at its time."""
    if frames_csv is None:
        return labels
    index = {f["frame"]: f for f in io.read_frames_csv(frames_csv, check_files=False)}
    for lb in labels:
        f = index.get(lb.frame)
        if f is None:
            raise CalibError(
                f"frame {lb.frame} is labelled but not in {frames_csv}: labels of another recording?"
            )
        if abs(f["time_s"] - lb.time_s) > TIME_TOL_S or f["file"] != lb.file:
            raise CalibError(
                f"frame {lb.frame}: the labels say {lb.file} at {lb.time_s:.6f} s, {frames_csv} says "
                f"{f['file']} at {f['time_s']:.6f} s: labels of another recording?"
            )
    unlabelled = sorted(set(index) - {lb.frame for lb in labels})
    if unlabelled and not drop_unlabelled:
        more = ", ..." if len(unlabelled) > 10 else ""
        raise CalibError(
            f"{len(unlabelled)} of {len(index)} frames of {frames_csv} have no label (frames "
            f"{', '.join(map(str, unlabelled[:10]))}{more}: no mocap coverage?); pass "
            "--drop-unlabelled to leave them out"
        )
    return labels


def _same_intrinsics(a: Intrinsics, b: Intrinsics) -> bool:
    if (a.width_px, a.height_px) != (b.width_px, b.height_px):
        return False
    scale = float(np.max(np.abs(b.K)))
    da, db = np.zeros(14), np.zeros(14)
    da[: len(a.dist)], db[: len(b.dist)] = a.dist, b.dist
    return bool(np.max(np.abs(a.K - b.K)) <= SAME_CAMERA_TOL * scale and np.max(np.abs(da - db)) <= 1e-9)


def camera_for(calib: dict, calib_path: Path, intrinsics: Path | None) -> tuple[Intrinsics, str]:
    """The lab camera: `intrinsics` when given, else the file the calibration was estimated with
    (its settings.intrinsics). Refused when both are known and differ: the labels were made with
    another camera's."""
    recorded = str((calib.get("settings") or {}).get("intrinsics", "oibar default"))
    rec_intr = None
    if recorded == "oibar default":
        rec_intr = Intrinsics.oibar_default()
    elif Path(recorded).is_file():
        rec_intr = io.read_intrinsics(Path(recorded))
    if intrinsics is None:
        if rec_intr is None:
            raise CalibError(
                f"{calib_path} was estimated with the intrinsics {recorded}, which is not there: "
                "give the camera's file with --intrinsics"
            )
        return rec_intr, recorded
    intr = io.read_intrinsics(intrinsics)
    if rec_intr is not None and not _same_intrinsics(intr, rec_intr):
        raise CalibError(
            f"camera mismatch: --intrinsics {intrinsics} is not the camera {calib_path} was estimated "
            f"with ({recorded})"
        )
    return intr, str(intrinsics)


def canonical_remap(intr: Intrinsics):
    """None when the lab camera is the canonical camera (frames copied as they are), else the
    remap (oibar.camera.calibration.CanonicalRemap) into it."""
    from oibar.camera.calibration import CameraCalibration, CanonicalRemap

    cam = PinholeCamera()
    canon = Intrinsics(cam.width_px, cam.height_px, intrinsics_corner_to_centre(cam.K), np.zeros(5))
    if _same_intrinsics(intr, canon):
        return None
    cal = CameraCalibration(intr.width_px, intr.height_px, intr.K, intr.dist, "lab camera")
    return CanonicalRemap(cal, cam.K, (cam.width_px, cam.height_px))


def _write_frame(src: Path, dst_stem: Path, intr: Intrinsics, remap) -> Path:
    """Decode (a corrupt file is refused), check its size, then copy it or remap it (PNG)."""
    import cv2

    img = cv2.imread(str(src), cv2.IMREAD_COLOR)
    if img is None:
        raise CalibError(f"{src}: missing, or not an image that can be decoded (corrupt frame)")
    h, w = img.shape[:2]
    if (w, h) != (intr.width_px, intr.height_px):
        raise CalibError(
            f"{src}: camera mismatch: the frame is {w}x{h}, the camera's intrinsics say "
            f"{intr.width_px}x{intr.height_px}"
        )
    ext = src.suffix.lower().replace(".jpeg", ".jpg")
    if remap is None and ext in (".png", ".jpg"):
        dst = dst_stem.with_suffix(ext)
        shutil.copyfile(src, dst)
        return dst
    if remap is not None:
        img = remap.apply(np.ascontiguousarray(img))
    dst = dst_stem.with_suffix(".png")
    if not cv2.imwrite(str(dst), img, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise CalibError(f"{dst}: cannot write the frame")
    return dst


def poses_table(labels: list[Label], files: list[str]) -> str:
    """poses.csv in the dataset's columns; lab data have no phase and no Sun."""
    from .pipeline import distance_m

    out = _io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(POSES_COLUMNS)
    for lb, name in zip(labels, files, strict=True):
        if lb.distance_m is None:
            from oibar.geometry.transforms import T_from_pose

            lb.distance_m = distance_m(T_from_pose(lb.T_m, lb.q_wxyz))
        w.writerow(
            [
                lb.frame,
                name,
                f"{lb.time_s:.6f}",
                0,
                "lab",
                f"{lb.distance_m:.6f}",
                *(f"{x:.6f}" for x in lb.T_m),
                *(f"{x:.9f}" for x in lb.q_wxyz),
                f"{np.linalg.norm(lb.T_m):.6f}",
                "",
                "",
                "",
            ]
        )
    return out.getvalue()


@dataclass
class Inputs:
    labelled_dir: Path
    calib: Path
    out: Path
    poses: Path | None = None  # default labelled_dir/poses.csv
    frames: Path | None = None  # default labelled_dir/frames.csv when it exists
    intrinsics: Path | None = None
    drop_unlabelled: bool = False
    force: bool = False

    @property
    def poses_csv(self) -> Path:
        """The labels' file: --poses, else LABELLED_DIR/poses.csv."""
        return Path(self.poses) if self.poses else Path(self.labelled_dir) / "poses.csv"

    def resolved(self) -> Inputs:
        d = Path(self.labelled_dir)
        if not d.is_dir():
            raise CalibError(f"{d}: no such folder (the recording with its poses.csv)")
        poses = Path(self.poses) if self.poses else d / "poses.csv"
        frames = (
            Path(self.frames) if self.frames else (d / "frames.csv" if (d / "frames.csv").is_file() else None)
        )
        return Inputs(
            d,
            Path(self.calib),
            Path(self.out),
            poses,
            frames,
            self.intrinsics,
            self.drop_unlabelled,
            self.force,
        )


def identity(inp: Inputs, intr: Intrinsics, intr_source: str) -> dict:
    """What the sequence is made from: the same identity, the same sequence (spec.json)."""
    return {
        "generator": GENERATOR,
        "source": "lab",
        "name": inp.out.name,
        "poses_sha256": sha256_file(inp.poses_csv),
        "frames_csv_sha256": sha256_file(inp.frames) if inp.frames else None,
        "calibration_sha256": sha256_file(inp.calib),
        "drop_unlabelled": inp.drop_unlabelled,
        "intrinsics": {
            "source": intr_source,
            "width_px": intr.width_px,
            "height_px": intr.height_px,
            "K_opencv": np.asarray(intr.K, float).tolist(),
            "dist": [float(v) for v in intr.dist],
        },
    }


def _existing(out: Path, ident: dict, force: bool) -> dict | None:
    """The manifest of an output that already holds this input; None when it is to be written."""
    if not out.exists():
        return None
    mpath = out / "manifest.json"
    try:
        m = json.loads(mpath.read_text())
        same = m.get("lab", {}).get("identity") == ident
    except (OSError, ValueError):
        m, same = None, False
    if same and not force:
        return m
    if not force:
        raise CalibError(
            f"{out}: exists and holds another recording or is incomplete; pass --force to replace it"
        )
    shutil.rmtree(out)
    return None


def _manifest(inp: Inputs, ident: dict, calib: dict, labels: list[Label], files: dict, remap) -> dict:
    from oibar import __version__
    from oibar.geometry.docking import MOUNT
    from oibar.geometry.fixture import FIXTURE

    t = np.array([lb.time_s for lb in labels])
    rate = float(1.0 / np.median(np.diff(t))) if len(t) > 1 else None
    return {
        "generator": GENERATOR,
        "generator_version": __version__,
        "source": "lab",
        "spec": {"name": inp.out.name, "kind": "lab_recording"},
        "frames": len(labels),
        "frame_rate_hz": rate,
        "config": {
            "camera": PinholeCamera().as_dict(),
            "camera_mount": asdict(MOUNT),
            "fixture": asdict(FIXTURE),
        },
        "lab": {
            "recording": str(inp.labelled_dir.resolve()),
            "poses": str(inp.poses_csv.resolve()),
            "frame_index": str(inp.frames.resolve()) if inp.frames else None,
            "calibration": str(inp.calib.resolve()),
            "calibration_sha256": ident["calibration_sha256"],
            "housing_body": calib.get("housing_body"),
            "target_body": calib.get("target_body"),
            "offset_s": calib.get("offset_s"),
            "camera": ident["intrinsics"],
            "remapped_to_canonical": remap is not None,
            "uncovered_fraction": round(remap.uncovered_fraction, 6) if remap is not None else 0.0,
            "identity": ident,
        },
        "labels": LABELS,
        "files": files,
    }


def _write_sequence(tmp: Path, inp: Inputs, ident: dict, calib: dict, labels, intr, remap, progress) -> None:
    root = (inp.frames or inp.poses_csv).parent
    (tmp / "frames").mkdir(parents=True)
    (tmp / "spec.json").write_text(json.dumps(ident, indent=2, sort_keys=True) + "\n")
    names, files = [], {}
    for i, lb in enumerate(labels):
        dst = _write_frame(root / lb.file, tmp / "frames" / f"{lb.frame:06d}", intr, remap)
        name = f"frames/{dst.name}"
        names.append(name)
        files[name] = sha256_file(dst)
        if progress:
            progress(i + 1, len(labels))
    (tmp / "poses.csv").write_text(poses_table(labels, names))
    files = {"poses.csv": sha256_file(tmp / "poses.csv"), **files}
    manifest = _manifest(inp, ident, calib, labels, files, remap)
    (tmp / "manifest.json").write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")


def to_dataset(inp: Inputs, progress=None) -> tuple[dict, bool]:
    """Write the sequence; returns (its manifest, whether it was written now: False when the
    output already held this input)."""
    inp = inp.resolved()
    calib = io.read_calibration(inp.calib)
    intr, intr_source = camera_for(calib, inp.calib, inp.intrinsics)
    labels = match_index(read_labels(inp.poses_csv), inp.frames, inp.drop_unlabelled)
    ident = identity(inp, intr, intr_source)
    done = _existing(inp.out, ident, inp.force)
    if done is not None:
        return done, False
    remap = canonical_remap(intr)
    if remap is not None and remap.warning():
        print(f"warning: {remap.warning()}", file=sys.stderr)
    tmp = inp.out.parent / f".{inp.out.name}.partial"
    if tmp.exists():
        shutil.rmtree(tmp)  # what a run that stopped left
    try:
        _write_sequence(tmp, inp, ident, calib, labels, intr, remap, progress)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)  # nothing half-written is left behind
        raise
    if inp.out.exists():  # --force: the old output goes only now that the new one is complete
        shutil.rmtree(inp.out)
    os.replace(tmp, inp.out)
    return json.loads((inp.out / "manifest.json").read_text()), True
