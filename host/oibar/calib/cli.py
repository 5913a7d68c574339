"""`oibar calib ...`: the ground-truth calibration commands (docs/calibration.md).

    oibar calib extract VIDEO OUT_DIR            video -> frames/ + frames.csv
    oibar calib estimate --mocap M --frames F --pattern P --housing-body H --target-body T -o calib.json
    oibar calib apply --calib calib.json --mocap M --frames F -o poses.csv
    oibar calib overlay --poses poses.csv --out DIR [--every N]
    oibar calib to-dataset LABELLED_DIR --calib calib.json --out DATA_DIR/NAME
                                                 frames + labels -> a sequence in the generator's layout

A synthetic recording with known truth (rendered, so it lives with the simulator):
    python -m oibar_hil.calib_synth OUT_DIR

Bad input ends with one line `oibar: error: ...` and exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from oibar.argtypes import number, positive_int

EXIT_OK = 0
EXIT_ERROR = 2


def register(sub) -> None:
    """Add the `calib` subcommand group to the `oibar` parser's subparsers."""
    calib = sub.add_parser(
        "calib",
        help="mocap ground-truth calibration (estimate, apply, overlay, to-dataset)",
        description="Ground-truth calibration toolbox for the motion-capture lab (docs/calibration.md).",
    )
    calib.set_defaults(handler=lambda a: (calib.print_help(sys.stderr), EXIT_ERROR)[1])
    cs = calib.add_subparsers(dest="calib_command", metavar="COMMAND")
    _register_extract(cs)
    _register_estimate(cs)
    _register_apply(cs)
    _register_overlay(cs)
    _register_to_dataset(cs)


def _register_extract(cs) -> None:
    ex = cs.add_parser(
        "extract", help="split a video into frames/ and frames.csv (time stamps from the video)"
    )
    ex.add_argument("video", type=Path)
    ex.add_argument("out", type=Path, help="output folder")
    ex.add_argument(
        "--every", type=positive_int(), default=1, metavar="N", help="keep every N-th frame (default 1)"
    )
    ex.set_defaults(handler=cmd_extract)


def _register_estimate(cs) -> None:
    es = cs.add_parser("estimate", help="estimate T_housing_cam, T_tmarkers_target and the time offset")
    _inputs(es)
    es.add_argument(
        "--pattern", type=Path, required=True, help="pattern JSON (ChArUco board and T_target_pattern)"
    )
    es.add_argument(
        "--offset-s",
        type=float,
        default=None,
        help="known time offset (mocap time = frame time + offset); default: estimate it",
    )
    es.add_argument(
        "--offset-search-s", type=float, default=0.5, help="search +- this many seconds (default 0.5)"
    )
    es.add_argument(
        "--mocap-sigma-mm", type=float, default=0.2, help="RMS mocap position noise per sample (0.2)"
    )
    es.add_argument(
        "--mocap-sigma-deg", type=float, default=0.5, help="RMS mocap rotation noise per sample (0.5)"
    )
    es.add_argument(
        "--corner-sigma-px", type=float, default=None, help="corner noise (default: from the PnP residuals)"
    )
    es.add_argument("--housing-body", required=True, help="mocap rigid body on the camera housing")
    es.add_argument("--target-body", required=True, help="mocap rigid body on the target")
    es.add_argument("-o", "--out", type=Path, required=True, help="calibration JSON to write")
    es.set_defaults(handler=cmd_estimate)


def _register_apply(cs) -> None:
    ap = cs.add_parser("apply", help="write the ground-truth camera-to-target poses for every frame")
    _inputs(ap)
    ap.add_argument("--calib", type=Path, required=True, help="calibration JSON from `estimate`")
    ap.add_argument(
        "--max-gap-s",
        type=float,
        default=None,
        help="longest mocap gap bridged by interpolation (default 2.5 sample periods)",
    )
    ap.add_argument(
        "--smooth-half-width-s",
        type=number(0.0, 10.0),
        default=None,
        metavar="S",
        help="each label from a local quadratic fit of the mocap within +-S seconds of its frame "
        "(default: estimate's window, 0.1; 0: interpolate between the two neighbouring samples); "
        "S must be short against the motion (docs/calibration.md)",
    )
    ap.add_argument("-o", "--out", type=Path, required=True, help="poses CSV to write (dataset format)")
    ap.set_defaults(handler=cmd_apply)


def _register_overlay(cs) -> None:
    ov = cs.add_parser("overlay", help="draw the target model from a poses file onto its frames")
    ov.add_argument(
        "--poses", type=Path, required=True, help="poses CSV (from `apply`, or a dataset's poses.csv)"
    )
    ov.add_argument(
        "--root",
        type=Path,
        default=None,
        help="folder the file column is relative to (default: the poses file's folder)",
    )
    ov.add_argument(
        "--intrinsics",
        type=Path,
        default=None,
        help="intrinsics: the toolbox's JSON, OpenCV calibration YAML or ROS camera_info YAML "
        "(default: the OIBAR camera)",
    )
    ov.add_argument(
        "--every", type=positive_int(), default=10, metavar="N", help="every N-th row (default 10)"
    )
    ov.add_argument("--out", type=Path, required=True, help="output folder for the PNGs")
    ov.set_defaults(handler=cmd_overlay)


def _register_to_dataset(cs) -> None:
    td = cs.add_parser(
        "to-dataset",
        help="a labelled recording (frames + `apply`'s poses.csv) -> one sequence in the data set layout",
        description="Write a labelled lab recording as one sequence in the data set generator's layout "
        "(docs/calibration.md, 'From a lab recording to a fine-tuned model').",
    )
    td.add_argument(
        "labelled_dir", type=Path, help="the recording: frames.csv, frames/ and apply's poses.csv"
    )
    td.add_argument("--calib", type=Path, required=True, help="the calibration JSON the labels came from")
    td.add_argument("--out", type=Path, required=True, help="the sequence folder to write (DATA_DIR/NAME)")
    td.add_argument("--poses", type=Path, default=None, help="the labels (default LABELLED_DIR/poses.csv)")
    td.add_argument(
        "--frames", type=Path, default=None, help="the frame index (default LABELLED_DIR/frames.csv)"
    )
    td.add_argument(
        "--intrinsics", type=Path, default=None, help="the camera (default: the calibration's own)"
    )
    td.add_argument(
        "--drop-unlabelled", action="store_true", help="leave out frames without a label instead of refusing"
    )
    td.add_argument("--force", action="store_true", help="replace an output that holds something else")
    td.set_defaults(handler=cmd_to_dataset)


def _inputs(p) -> None:
    p.add_argument(
        "--mocap", type=Path, required=True, help="mocap CSV (time_s,body,x_m,y_m,z_m,qw,qx,qy,qz)"
    )
    p.add_argument("--mocap-units", choices=("m", "mm"), default="m", help="position unit in the mocap CSV")
    p.add_argument("--frames", type=Path, required=True, help="frame index CSV (frame,file,time_s)")
    p.add_argument(
        "--intrinsics",
        type=Path,
        default=None,
        help="intrinsics: the toolbox's JSON, OpenCV calibration YAML or ROS camera_info YAML "
        "(default: the OIBAR camera)",
    )


def run(args: argparse.Namespace) -> int:
    """Dispatch with the toolbox's errors turned into one line and exit 2."""
    from .errors import CalibError

    try:
        return args.handler(args)
    except CalibError as exc:
        print(f"oibar: error: {exc}", file=sys.stderr, flush=True)
        return EXIT_ERROR


def cmd_extract(a) -> int:
    import cv2

    from .errors import CalibError

    if a.every < 1:
        raise CalibError("--every must be >= 1")
    cap = cv2.VideoCapture(str(a.video))
    if not a.video.is_file() or not cap.isOpened():
        raise CalibError(f"{a.video}: cannot open the video")
    (a.out / "frames").mkdir(parents=True, exist_ok=True)
    rows, k, kept = ["frame,file,time_s"], 0, 0
    while True:
        ok, img = cap.read()
        if not ok:
            break
        t_s = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        if k % a.every == 0:
            name = f"frames/{k:06d}.png"
            cv2.imwrite(str(a.out / name), img)
            rows.append(f"{k},{name},{t_s:.6f}")
            kept += 1
        k += 1
    if kept == 0:
        raise CalibError(f"{a.video}: no frames decoded")
    (a.out / "frames.csv").write_text("\n".join(rows) + "\n")
    print(f"{kept} frames -> {a.out / 'frames.csv'} (time_s from the video's time stamps)")
    return EXIT_OK


def _progress(done: int, total: int) -> None:
    if done == total or done % 50 == 0:
        print(f"  pattern detection: {done}/{total} frames", file=sys.stderr, flush=True)


def cmd_estimate(a) -> int:
    from . import io
    from .pipeline import EstimateInputs, estimate

    inp = EstimateInputs(
        a.mocap,
        a.frames,
        a.pattern,
        a.housing_body,
        a.target_body,
        a.intrinsics,
        a.mocap_units,
        a.offset_s,
        a.offset_search_s,
        a.mocap_sigma_mm,
        a.mocap_sigma_deg,
        a.corner_sigma_px,
    )
    res = estimate(inp, progress=_progress)
    res.pop("_details")
    io.write_calibration(a.out, res)
    print(summary(res))
    print(f"wrote {a.out}")
    return EXIT_OK


def summary(res: dict) -> str:
    from oibar.geometry.rotations import matrix_to_quat as R_to_quat_wxyz

    lines = []
    for key in ("T_housing_cam", "T_tmarkers_target"):
        T = res[key]
        s = res["sigma_1"][key]
        lines.append(
            f"{key}: t = {_fmt(T[:3, 3] * 1e3)} mm, q_wxyz = {_fmt(R_to_quat_wxyz(T[:3, :3]), 6)}"
            f"  (1 sigma {s['t_mm']} mm, {s['r_deg']} deg)"
        )
    so = res["sigma_1"]["offset_ms"]
    lines.append(f"offset_s: {res['offset_s']:.5f}" + (f" (1 sigma {so:.2f} ms)" if so else " (given)"))
    p, r = res["poses"], res["residuals"]
    lines.append(
        f"poses: {p['used']} used of {p['pattern_found']} with the pattern ({p['frames']} frames), "
        f"{p['outliers']} outliers; max rotation {p['max_rotation_deg']:.0f} deg, "
        f"axis spread {p['axis_spread']:.2f}"
    )
    lines.append(
        f"residuals: chi2/dof {r['chi2_per_dof']:.2f}; per pose {r['pose_translation_mm']['rms']:.2f} mm / "
        f"{r['pose_rotation_deg']['rms']:.3f} deg RMS; "
        f"chain reprojection {r['chain_reprojection_px']['rms']:.2f} px RMS; "
        f"PnP {r['pnp_reprojection_px']['rms']:.3f} px RMS"
    )
    return "\n".join(lines)


def _fmt(v, digits: int = 3) -> str:
    return "(" + ", ".join(f"{float(x):.{digits}f}" for x in v) + ")"


def cmd_apply(a) -> int:
    from . import io, timing
    from .pipeline import apply

    calib = io.read_calibration(a.calib)
    tracks = io.read_mocap_csv(a.mocap, a.mocap_units)
    frames = io.read_frames_csv(a.frames, check_files=False)
    hw = timing.SMOOTH_HALF_WIDTH_S if a.smooth_half_width_s is None else a.smooth_half_width_s
    rows, skipped = apply(calib, tracks, frames, a.mocap, a.max_gap_s, hw)  # 0: interpolation
    io.write_poses_csv(a.out, rows)
    msg = f"{len(rows)} of {len(frames)} frames -> {a.out}"
    if skipped:
        more = ", ..." if len(skipped) > 10 else ""
        msg += f"; {len(skipped)} without mocap coverage skipped (frames {', '.join(map(str, skipped[:10]))}{more})"
    print(msg)
    return EXIT_OK


def cmd_overlay(a) -> int:
    import cv2

    from . import io
    from .errors import CalibError
    from .overlay import caption, draw_model

    if a.every < 1:
        raise CalibError("--every must be >= 1")
    intr = io.read_intrinsics(a.intrinsics)
    rows = io.read_poses_csv(a.poses)
    root = a.root or a.poses.parent
    a.out.mkdir(parents=True, exist_ok=True)
    n = 0
    for row in rows[:: a.every]:
        img = cv2.imread(str(root / row["file"]))
        if img is None:
            raise CalibError(f"{root / row['file']}: cannot read the image (set --root?)")
        img = caption(draw_model(img, row["T_cam_target"], intr), f"frame {row['frame']}")
        cv2.imwrite(str(a.out / f"overlay_{row['frame']:06d}.png"), img)
        n += 1
    print(f"{n} overlays -> {a.out}")
    return EXIT_OK


def cmd_to_dataset(a) -> int:
    from .dataset import Inputs, to_dataset

    inp = Inputs(a.labelled_dir, a.calib, a.out, a.poses, a.frames, a.intrinsics, a.drop_unlabelled, a.force)
    manifest, written = to_dataset(inp)
    lab = manifest["lab"]
    how = "remapped into the canonical camera" if lab["remapped_to_canonical"] else "copied"
    if written:
        print(f"{manifest['frames']} labelled frames ({how}) -> {a.out} (lab recording, manifest.json)")
    else:
        print(f"{a.out} already holds this recording ({manifest['frames']} frames); nothing written")
    return EXIT_OK
