"""File formats of the toolbox (documented in docs/calibration.md): the mocap export, the frame
index, the pattern and intrinsics files, the calibration result and the poses output.
Every reader raises CalibError with the file and line on malformed input.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from oibar.dataset_format import POSES_COLUMNS
from oibar.geometry.rotations import matrix_to_quat as R_to_quat_wxyz
from oibar.geometry.transforms import T_from_pose

from .errors import CalibError
from .pnp import Intrinsics, Pattern
from .timing import Track

# Accepted header spellings (case-insensitive) for the long mocap layout.
MOCAP_COLUMNS = {
    "time": ("time_s", "time", "t", "timestamp"),
    "body": ("body", "rigid_body", "rigidbody", "name"),
    "x": ("x_m", "x", "tx", "pos_x"),
    "y": ("y_m", "y", "ty", "pos_y"),
    "z": ("z_m", "z", "tz", "pos_z"),
    "qw": ("qw", "rot_w", "w"),
    "qx": ("qx", "rot_x"),
    "qy": ("qy", "rot_y"),
    "qz": ("qz", "rot_z"),
}
UNIT_TO_M = {"m": 1.0, "mm": 1e-3}


def _open_csv(path: Path):
    path = Path(path)
    if not path.is_file():
        raise CalibError(f"{path}: no such file")
    fh = open(path, newline="")  # noqa: SIM115  (returned open: the caller reads and closes it)
    reader = csv.reader(fh)
    try:
        header = next(reader)
    except StopIteration:
        fh.close()
        raise CalibError(f"{path}: empty file") from None
    return fh, reader, [h.strip().lower() for h in header]


def _float(text: str, path: Path, line: int, col: str) -> float:
    text = text.strip()
    if text == "" or text.lower() == "nan":
        return float("nan")
    try:
        return float(text)
    except ValueError:
        raise CalibError(f"{path}:{line}: column {col!r}: not a number: {text!r}") from None


def read_mocap_csv(path: Path, position_unit: str = "m") -> dict[str, Track]:
    """Long layout: one row per sample and rigid body. Rows with empty/NaN fields are occluded
    samples and dropped. Returns one Track per rigid body name."""
    path = Path(path)
    if position_unit not in UNIT_TO_M:
        raise CalibError(f"unknown position unit {position_unit!r} (m or mm)")
    scale = UNIT_TO_M[position_unit]
    fh, reader, header = _open_csv(path)
    with fh:
        col = {}
        for key, names in MOCAP_COLUMNS.items():
            hit = [header.index(n) for n in names if n in header]
            if not hit:
                raise CalibError(
                    f"{path}: no {key!r} column (header {','.join(header)}; expected e.g. "
                    "time_s,body,x_m,y_m,z_m,qw,qx,qy,qz)"
                )
            col[key] = hit[0]
        rows: dict[str, list] = {}
        for line, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) < len(header):
                raise CalibError(f"{path}:{line}: {len(row)} fields, the header has {len(header)}")
            vals = [
                _float(row[col[k]], path, line, k) for k in ("time", "x", "y", "z", "qw", "qx", "qy", "qz")
            ]
            if not np.all(np.isfinite(vals)):
                continue  # occluded sample
            q = np.array(vals[4:8])
            if abs(np.linalg.norm(q) - 1.0) > 0.01:
                raise CalibError(
                    f"{path}:{line}: quaternion norm {np.linalg.norm(q):.3f} is not 1 "
                    "(columns in w,x,y,z order?)"
                )
            rows.setdefault(row[col["body"]].strip(), []).append(vals)
    if not rows:
        raise CalibError(f"{path}: no samples")
    tracks = {}
    for name, vals in rows.items():
        a = np.array(vals)
        order = np.argsort(a[:, 0], kind="stable")
        a = a[order]
        if np.any(np.diff(a[:, 0]) <= 0):
            raise CalibError(f"{path}: rigid body {name!r} has repeated time stamps")
        tracks[name] = Track(name, a[:, 0], T_from_pose(a[:, 1:4] * scale, a[:, 4:8]))
    return tracks


def pick_tracks(tracks: dict[str, Track], housing: str, target: str, path: Path) -> tuple[Track, Track]:
    for name in (housing, target):
        if name not in tracks:
            raise CalibError(f"{path}: no rigid body {name!r} (found: {', '.join(sorted(tracks))})")
    for name in (housing, target):
        if len(tracks[name].t_s) < 2:
            raise CalibError(f"{path}: rigid body {name!r} has fewer than 2 samples")
    return tracks[housing], tracks[target]


def read_frames_csv(path: Path, check_files: bool = True) -> list[dict]:
    """`frame,file,time_s` (extra columns ignored, so a dataset poses.csv also works); files are
    relative to the CSV's folder. Missing image files are an error."""
    path = Path(path)
    fh, reader, header = _open_csv(path)
    with fh:
        for need in ("frame", "file", "time_s"):
            if need not in header:
                raise CalibError(f"{path}: no {need!r} column (expected frame,file,time_s)")
        i_f, i_file, i_t = header.index("frame"), header.index("file"), header.index("time_s")
        frames = []
        for line, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) < len(header):
                raise CalibError(f"{path}:{line}: {len(row)} fields, the header has {len(header)}")
            try:
                k = int(row[i_f])
            except ValueError:
                raise CalibError(f"{path}:{line}: frame {row[i_f]!r} is not an integer") from None
            t = _float(row[i_t], path, line, "time_s")
            if not np.isfinite(t):
                raise CalibError(f"{path}:{line}: no time stamp")
            name = row[i_file].strip()
            frames.append({"frame": k, "file": name, "time_s": t, "path": path.parent / name})
    if not frames:
        raise CalibError(f"{path}: no frames")
    times_s = np.array([f["time_s"] for f in frames])
    if np.any(np.diff(times_s) <= 0):
        raise CalibError(f"{path}: time_s must increase from frame to frame")
    if check_files:
        missing = [f["file"] for f in frames if not f["path"].is_file()]
        if missing:
            more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
            raise CalibError(f"{path}: {len(missing)} frame file(s) missing: {', '.join(missing[:3])}{more}")
    return frames


def _pose_json(T: np.ndarray) -> dict:
    return {
        "t_m": [round(float(v), 9) for v in T[:3, 3]],
        "q_wxyz": [round(float(v), 12) for v in R_to_quat_wxyz(T[:3, :3])],
    }


def _pose_from_json(d, where: str) -> np.ndarray:
    try:
        t, q = np.asarray(d["t_m"], float), np.asarray(d["q_wxyz"], float)
        if t.shape != (3,) or q.shape != (4,) or abs(np.linalg.norm(q) - 1) > 1e-3:
            raise ValueError
    except (KeyError, TypeError, ValueError):
        raise CalibError(
            f'{where}: a pose is {{"t_m": [x, y, z], "q_wxyz": [w, x, y, z]}} (unit quaternion)'
        ) from None
    return T_from_pose(t, q)


def _load_json(path: Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise CalibError(f"{path}: no such file")
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise CalibError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(d, dict):
        raise CalibError(f"{path}: expected a JSON object")
    return d


def read_pattern(path: Path) -> Pattern:
    d = _load_json(path)
    if d.get("type", "charuco") != "charuco":
        raise CalibError(f'{path}: only "type": "charuco" boards are supported')
    try:
        p = Pattern(
            int(d["squares_x"]),
            int(d["squares_y"]),
            float(d["square_m"]),
            float(d["marker_m"]),
            str(d.get("dictionary", "DICT_4X4_50")),
            _pose_from_json(d["T_target_pattern"], f"{path}: T_target_pattern"),
        )
    except KeyError as exc:
        raise CalibError(f"{path}: missing {exc.args[0]!r}") from None
    if p.squares_x < 3 or p.squares_y < 3 or not 0 < p.marker_m < p.square_m:
        raise CalibError(f"{path}: need >= 3x3 squares and 0 < marker_m < square_m")
    return p


def write_pattern(path: Path, p: Pattern) -> None:
    d = {
        "type": "charuco",
        "squares_x": p.squares_x,
        "squares_y": p.squares_y,
        "square_m": p.square_m,
        "marker_m": p.marker_m,
        "dictionary": p.dictionary,
        "T_target_pattern": _pose_json(p.T_target_pattern),
    }
    Path(path).write_text(json.dumps(d, indent=2) + "\n")


def read_intrinsics(path: Path | None) -> Intrinsics:
    """OpenCV convention (pixel centres on integers). None: the OIBAR camera of docs/synthetic.md.
    The toolbox's intrinsics JSON, or the files ``--calibration`` reads (OpenCV's calibration
    YAML/XML/JSON, ROS camera_info YAML: oibar.camera.calibration)."""
    if path is None:
        return Intrinsics.oibar_default()
    if Path(path).suffix.lower() in (".yaml", ".yml", ".xml"):
        return _intrinsics_from_calibration(path)
    d = _load_json(path)
    if "fx_px" not in d and any(k in d for k in ("camera_matrix", "K", "k")):
        return _intrinsics_from_calibration(path)
    try:
        K = np.array(
            [[float(d["fx_px"]), 0, float(d["cx_px"])], [0, float(d["fy_px"]), float(d["cy_px"])], [0, 0, 1]]
        )
        dist = np.asarray(d.get("dist", [0, 0, 0, 0, 0]), float)
        intr = Intrinsics(int(d["width_px"]), int(d["height_px"]), K, dist)
    except KeyError as exc:
        raise CalibError(f"{path}: missing {exc.args[0]!r}") from None
    except (TypeError, ValueError):
        raise CalibError(f"{path}: intrinsics must be numbers") from None
    if K[0, 0] <= 0 or K[1, 1] <= 0 or dist.ndim != 1 or len(dist) not in (4, 5, 8, 12, 14):
        raise CalibError(f"{path}: need fx_px, fy_px > 0 and 4, 5, 8, 12 or 14 distortion coefficients")
    return intr


def _intrinsics_from_calibration(path: Path) -> Intrinsics:
    from oibar.camera.calibration import CalibrationError, load_calibration

    try:
        c = load_calibration(path)
    except CalibrationError as exc:
        raise CalibError(str(exc)) from None
    return Intrinsics(c.width_px, c.height_px, c.K, c.dist)


def write_intrinsics(path: Path, intr: Intrinsics) -> None:
    d = {
        "convention": "opencv (pixel centres on integers)",
        "width_px": intr.width_px,
        "height_px": intr.height_px,
        "fx_px": intr.K[0, 0],
        "fy_px": intr.K[1, 1],
        "cx_px": intr.K[0, 2],
        "cy_px": intr.K[1, 2],
        "dist": [float(v) for v in intr.dist],
    }
    Path(path).write_text(json.dumps(d, indent=2) + "\n")


CALIB_FORMAT = "oibar-calib/1"


def write_calibration(path: Path, result: dict) -> None:
    out = dict(result)
    out["format"] = CALIB_FORMAT
    for key in ("T_housing_cam", "T_tmarkers_target"):
        out[key] = _pose_json(result[key])
    Path(path).write_text(json.dumps(out, indent=2) + "\n")


def read_calibration(path: Path) -> dict:
    d = _load_json(path)
    if d.get("format") != CALIB_FORMAT:
        raise CalibError(f"{path}: not a calibration file of this toolbox (format {d.get('format')!r})")
    for key in ("T_housing_cam", "T_tmarkers_target"):
        if key not in d:
            raise CalibError(f"{path}: missing {key!r}")
        d[key] = _pose_from_json(d[key], f"{path}: {key}")
    for key in ("offset_s", "housing_body", "target_body"):
        if key not in d:
            raise CalibError(f"{path}: missing {key!r}")
    return d


def write_poses_csv(path: Path, rows: list[dict]) -> None:
    """The dataset's poses format (docs/synthetic.md). Lab recordings have no trajectory phase
    and no Sun: phase is 0 / "lab" and the Sun columns are empty."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(POSES_COLUMNS)
        for r in rows:
            T = r["T_cam_target"]
            q = R_to_quat_wxyz(T[:3, :3])
            w.writerow(
                [
                    r["frame"],
                    r["file"],
                    f"{r['time_s']:.6f}",
                    0,
                    "lab",
                    f"{r['distance_m']:.6f}",
                    *(f"{x:.6f}" for x in T[:3, 3]),
                    *(f"{x:.9f}" for x in q),
                    f"{np.linalg.norm(T[:3, 3]):.6f}",
                    "",
                    "",
                    "",
                ]
            )


def read_poses_csv(path: Path) -> list[dict]:
    fh, reader, header = _open_csv(path)
    with fh:
        need = ("frame", "file", "tx_m", "ty_m", "tz_m", "qw", "qx", "qy", "qz")
        for n in need:
            if n not in header:
                raise CalibError(f"{path}: no {n!r} column (the dataset's poses format)")
        out = []
        for line, row in enumerate(reader, start=2):
            if not row:
                continue
            d = dict(zip(header, row, strict=False))  # a short row reads as missing columns
            t = [_float(d[k], Path(path), line, k) for k in ("tx_m", "ty_m", "tz_m")]
            q = [_float(d[k], Path(path), line, k) for k in ("qw", "qx", "qy", "qz")]
            out.append({"frame": int(d["frame"]), "file": d["file"], "T_cam_target": T_from_pose(t, q)})
    return out
