"""``oibar nav`` (the navigation daemon), ``oibar replay`` (re-run estimation on a log) and
``oibar pose`` (the estimator alone on image files)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from oibar import argtypes
from oibar.progress import StatusLine

if TYPE_CHECKING:
    from oibar.link.client import LinkClient

# Exit status of `oibar nav` (also in its --help and docs/navigation.md).
EXIT_OK = 0  # mission over, --duration-s reached, or Ctrl-C / SIGTERM: MCU session ended as planned
EXIT_INTERNAL = 1  # an unexpected error inside oibar (one line; -v for the traceback)
EXIT_ERROR = 2  # bad argument or start-up error (model, camera spec, empty source, vehicle, log)
EXIT_SOURCE_ENDED = 3  # the camera source ended (last frame of a video file or frame folder)
EXIT_SOURCE_DIED = 4  # the camera source died: no frame for --camera-dead-s
EXIT_MCU_NOT_SAFE = 5  # stopped otherwise cleanly, but the MCU did not accept the planned end
EXIT_INTERRUPTED = 130  # Ctrl-C before the daemon was running (oibar.cli)
# `oibar pose`: 0, 1, 2 as above, and
EXIT_FRAMES_FAILED = 3  # a frame could not be read or was refused (the others are still estimated)

_NAV_DESCRIPTION = """\
Run the OIBAR navigation daemon: every 100 ms take the newest camera frame, estimate the
relative pose of the berthing fixture with OibarNet (ONNX), filter it, decide the guidance
(phase, velocity setpoint, hold or retreat) and command the docking mechanism's MCU over the
serial link. One status line shows what it is doing; Ctrl-C or SIGTERM stops it cleanly
(vehicle hold, the MCU session ended as planned: valves closed, mechanism held or homed, no
fault raised; link and camera closed, log footer written).

Every cycle is logged as one JSON line (--log); with --record-frames the frames are kept too,
so `oibar replay` can re-run the estimation on exactly what the daemon saw.
"""

_NAV_EPILOG = """\
camera (--camera):
  0, 1, ...            an OpenCV camera device index (/dev/video0, ...)
  /dev/video2          a V4L2 device path
  approach.mp4         a video file (played at its frame rate)
  frames/              a folder of images (frames.csv with times if present, else --camera-rate-hz)
  frames+tcp://H:P     RGB frames from another process over a local TCP socket
                       (oibar.camera.stream; `make sitl` feeds the rig's renderer this way)

port (--port):
  /dev/ttyACM0, COM3   the MCU's serial port (115200 baud)
  socket://HOST:PORT   a TCP bridge, e.g. the STM32 image under QEMU
  none                 no MCU: navigation and logging only; guidance holds

vehicle (--vehicle), where velocity setpoints go:
  none                 keep them in the log only (default)
  udp://HOST:PORT      one JSON datagram per cycle for the vehicle's GNC computer;
                       its odometry datagrams back are fused (oibar.nav.vehicle)
  python:MOD:CLASS     your own oibar.nav.vehicle.VehicleInterface subclass

examples:
  oibar nav --camera 0 --port /dev/ttyACM0 --model models/oibarnet.onnx
  oibar nav --camera data/synthetic/seq01/frames --port none --record-frames --duration-s 60
  oibar nav --camera 0 --calibration camera.yaml --port /dev/ttyACM0
  oibar replay runs/nav/20261122-101500/cycles.jsonl --model models/other.onnx

calibration (--calibration FILE): the camera that takes the frames, as OpenCV's calibration
YAML (`oibar calibrate-camera`) or ROS camera_info YAML (plumb_bob, rational_polynomial or no
distortion; any resolution). Each frame is undistorted and remapped to the network's canonical
camera (744x480, f 583.33 px) by one cv2.remap; a camera narrower than that view is accepted
with a warning (its uncovered border is black). A frame of another size than the calibration's
is refused (a hold, "malformed frame"), never guessed. Without it, only 744x480 frames of the
canonical camera are read.

exit status (one line on stderr says why; never a traceback):
  0    mission over, --duration-s reached, or Ctrl-C / SIGTERM: the MCU accepted the planned
       end of the session (CMD_END_SESSION), or there is no MCU (--port none)
  1    an unexpected internal error (run with -v for the traceback); the MCU session is
       still ended as planned first
  2    bad argument or start-up error: model, camera spec, empty or undecodable source,
       vehicle, log folder
  3    the camera source ended (last frame of a video file or frame folder); MCU safe first
  4    the camera source died: no frame for --camera-dead-s (camera unplugged, never
       opened); MCU safe first
  5    stopped otherwise cleanly (0 above), but the MCU did not accept the planned end (link
       down, no answer): it takes the silence for a host link loss (FAULT outside
       BOOT/IDLE/FAULT, valves closed)
  130  Ctrl-C before the daemon was running
A corrupt frame (a truncated JPEG in a folder) is skipped and counted, not an error.
"""


_POSE_DESCRIPTION = """\
Estimate the berthing fixture's pose in each image file with OibarNet, without the daemon: one
JSON line per frame on stdout, in the order given:
  {"frame": PATH, "T_cam_target_m": [x, y, z], "q_cam_target_wxyz": [w, x, y, z],
   "confidence": 0..1, "flags": [...], "latency_ms": MS}
Each frame is read cold, on its own, with the full search (no crop budget, nothing carried from
the previous frame). A frame that cannot be read or is refused gives a line with "error" (the
pose fields null) and one line on stderr.
"""

_POSE_EPILOG = """\
frames: the network's canonical camera (744x480, f 583.33 px, principal point at the centre)
unless --calibration names the camera that took them (any resolution: undistorted and remapped
to the canonical camera); a frame whose size does not match the calibration is refused.

examples:
  oibar pose frame.png
  oibar pose shots/*.jpg --calibration camera.yaml > poses.jsonl

exit status (one line on stderr says why; never a traceback):
  0    every frame read and estimated (a low confidence or a flag is an answer, not an error)
  1    an unexpected internal error (run with -v for the traceback)
  2    bad argument or start-up error: model, calibration file
  3    at least one frame could not be read (missing, corrupt, not an image) or was refused
       (wrong size, not RGB); the others are still estimated
"""


def default_model_path() -> Path:
    """$OIBAR_MODEL, else the shipped model of this install (oibar.resources)."""
    from oibar.resources import default_model_path as shipped

    return shipped()


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    nav = sub.add_parser(
        "nav",
        help="run the navigation daemon (camera -> OibarNet -> guidance -> MCU)",
        description=_NAV_DESCRIPTION,
        epilog=_NAV_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    nav.add_argument(
        "--camera",
        required=True,
        metavar="SPEC",
        type=argtypes.non_empty("--camera"),
        help="camera device, video file or frame folder",
    )
    nav.add_argument(
        "--port",
        required=True,
        metavar="URL",
        type=argtypes.non_empty("--port"),
        help="MCU serial port, socket://HOST:PORT, or none",
    )
    nav.add_argument(
        "--model",
        type=Path,
        default=None,
        metavar="ONNX",
        help="OibarNet ONNX model (default: $OIBAR_MODEL, else the shipped oibarnet.onnx)",
    )
    _calibration_arg(nav)
    nav.add_argument(
        "--vehicle",
        default="none",
        metavar="SPEC",
        type=argtypes.non_empty("--vehicle"),
        help="where velocity setpoints go (default: none)",
    )
    nav.add_argument(
        "--log",
        type=Path,
        default=None,
        metavar="DIR",
        help="log folder (default: runs/nav/<date-time>); cycles.jsonl is written there",
    )
    nav.add_argument("--no-log", action="store_true", help="do not write a cycle log")
    nav.add_argument(
        "--record-frames", action="store_true", help="also keep every frame used (for oibar replay)"
    )
    nav.add_argument(
        "--rate-hz",
        type=argtypes.positive(100.0),
        default=10.0,
        metavar="HZ",
        help="navigation rate, > 0 and <= 100 (default: 10)",
    )
    nav.add_argument(
        "--camera-rate-hz",
        type=argtypes.positive(1000.0),
        default=10.0,
        metavar="HZ",
        help="pace for frame folders without time stamps, > 0 and <= 1000 (default: 10)",
    )
    nav.add_argument(
        "--camera-dead-s",
        type=argtypes.positive(3600.0),
        default=4.0,
        metavar="S",
        help="no frame for S seconds: the camera source is dead, stop with exit status 4 (default: 4)",
    )
    nav.add_argument(
        "--threads",
        type=argtypes.positive_int(256),
        default=2,
        help="onnxruntime threads, 1-256 (default: 2)",
    )
    nav.add_argument(
        "--duration-s", type=argtypes.positive(), default=None, metavar="S", help="stop after S seconds (> 0)"
    )
    nav.add_argument(
        "--target-pressure-kpa",
        type=argtypes.positive(10000.0),
        default=1200.0,
        metavar="KPA",
        help="fill target, > 0 (the MCU checks its own bounds) (default: 1200)",
    )
    nav.add_argument(
        "--baudrate", type=argtypes.positive_int(), default=115200, help="serial baud rate (default: 115200)"
    )
    nav.set_defaults(handler=cmd_nav, run=run)

    rp = sub.add_parser(
        "replay",
        help="re-run pose estimation and the filter on a recorded cycle log",
        description="Feed the frames recorded by `oibar nav --record-frames` through a fresh "
        "navigator (optionally another model) and compare with the recorded estimates.",
    )
    rp.add_argument("log", type=Path, help="cycles.jsonl written by oibar nav")
    rp.add_argument(
        "--model", type=Path, default=None, metavar="ONNX", help="model (default: as for oibar nav)"
    )
    rp.add_argument("--out", type=Path, default=None, help="write the replayed estimates here (JSON lines)")
    _calibration_arg(rp)
    rp.add_argument(
        "--threads",
        type=argtypes.positive_int(256),
        default=2,
        help="onnxruntime threads, 1-256 (default: 2)",
    )
    rp.set_defaults(handler=cmd_replay, run=run)

    ps = sub.add_parser(
        "pose",
        help="estimate the fixture's pose in image files (no daemon): one JSON line per frame",
        description=_POSE_DESCRIPTION,
        epilog=_POSE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ps.add_argument("frames", nargs="+", type=Path, metavar="FRAME", help="image files (PNG, JPEG, ...)")
    ps.add_argument(
        "--model", type=Path, default=None, metavar="ONNX", help="model (default: as for oibar nav)"
    )
    _calibration_arg(ps)
    ps.add_argument(
        "--threads",
        type=argtypes.positive_int(256),
        default=2,
        help="onnxruntime threads, 1-256 (default: 2)",
    )
    ps.set_defaults(handler=cmd_pose, run=run)


def _calibration_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--calibration",
        type=Path,
        default=None,
        metavar="FILE",
        help="the camera's calibration (OpenCV YAML from `oibar calibrate-camera`, or ROS camera_info "
        "YAML): frames are undistorted and remapped to the network's canonical camera; frames of "
        "another size are refused. Without it only the canonical camera's own 744x480 frames are read",
    )


def run(args: argparse.Namespace) -> int:
    """Start-up errors become one line and exit 2; anything unexpected one line and exit 1
    (the traceback only with -v)."""
    from oibar.camera import CameraError
    from oibar.camera.calibration import CalibrationError
    from oibar.nav.cyclelog import CycleLogError
    from oibar.nav.pose import ModelFileError
    from oibar.nav.vehicle import VehicleError

    try:
        return int(args.handler(args))
    except (ModelFileError, CameraError, VehicleError, CycleLogError, CalibrationError, OSError) as exc:
        print(f"oibar: error: {exc}", file=sys.stderr, flush=True)
        return EXIT_ERROR
    except Exception as exc:
        if getattr(args, "verbose", 0):
            import traceback

            traceback.print_exc()
        print(
            f"oibar: internal error: {type(exc).__name__}: {exc} (run with -v for the traceback)",
            file=sys.stderr,
            flush=True,
        )
        return EXIT_INTERNAL


def exit_status(daemon: Any) -> tuple[int, str]:
    """`oibar nav`'s exit status and its one-line reason, from why the daemon stopped and how the
    planned end of the MCU session went (the table in the --help epilog)."""
    from oibar.nav import daemon as d

    reason = daemon.stop_reason
    end = daemon.session_end
    if reason == d.STOP_SOURCE_ENDED:
        return EXIT_SOURCE_ENDED, f"camera source ended ({daemon._cam_error or 'no more frames'})"
    if reason == d.STOP_SOURCE_DIED:
        return EXIT_SOURCE_DIED, (
            f"camera source dead: no frame for {daemon.p.camera_dead_s:g} s "
            f"({daemon._cam_error or 'no frame'})"
        )
    if daemon.link is not None and (end is None or not end.accepted):
        why = end.detail if end is not None else "not attempted"
        return EXIT_MCU_NOT_SAFE, f"the MCU did not accept the planned end of the session: {why}"
    return EXIT_OK, ""


def open_link(port: str, **settings: Any) -> LinkClient:
    """The navigation daemon's link client: heartbeats only from the navigation cycle
    (``heartbeats="caller"``), so when the loop hangs the MCU's link timeout sees a silent host
    and holds or retreats, instead of a heartbeat thread keeping a dead navigator alive."""
    from oibar.link.client import LinkClient

    return LinkClient(port, heartbeats="caller", **settings)


def cmd_nav(a: argparse.Namespace) -> int:
    from oibar.camera import FolderSource, VideoFileSource, open_source
    from oibar.nav.cyclelog import CycleLog
    from oibar.nav.daemon import (
        DaemonParams,
        NavDaemon,
        connect_in_background,
        install_sigint,
        load_navigator,
    )
    from oibar.nav.guidance import Guidance, MissionParams
    from oibar.nav.vehicle import open_vehicle

    model = a.model or default_model_path()
    # model and calibration errors first, nothing opened yet
    navigator = load_navigator(model, threads=a.threads)
    est = navigator.estimator
    if a.calibration is not None:
        est.use_calibration(a.calibration)
        _report_calibration(est)
    lo, hi = est.range_limits_m
    origin = (
        "from the model's oibar.train_range_m"
        if "train_range_m" in est.meta
        else "default: the model states no oibar.train_range_m"
    )
    print(
        f"model {model} (version {est.meta.get('model_version', '?')}), "
        f"input {est.size_wh[0]}x{est.size_wh[1]}, range check {lo:g}-{hi:g} m ({origin})",
        file=sys.stderr,
    )
    camera = open_source(a.camera, rate_hz=a.camera_rate_hz, realtime=True)
    if isinstance(camera, (FolderSource, VideoFileSource)):
        # a finite source is checked before anything opens: an empty folder or an undecodable
        # video is a start-up error (exit 2), not a run that waits for frames forever
        with camera:
            pass
    vehicle = open_vehicle(a.vehicle)
    log = None
    if not a.no_log:
        log_dir = a.log or Path("runs") / "nav" / time.strftime("%Y%m%d-%H%M%S")
        log = CycleLog(log_dir / "cycles.jsonl", frames_dir=(log_dir / "frames") if a.record_frames else None)
        print(f"log {log.path}", file=sys.stderr)
    link = None
    if a.port.lower() != "none":
        link = open_link(a.port, baudrate=a.baudrate)
        connect_in_background(link, on_error=lambda m: print(f"\nlink: {m} (retrying)", file=sys.stderr))
    guidance = Guidance(MissionParams(target_kpa=a.target_pressure_kpa))
    # the live status line on a terminal; in a log, one line every few seconds
    status = StatusLine()
    daemon = NavDaemon(
        navigator,
        guidance,
        camera,
        link=link,
        vehicle=vehicle,
        log=log,
        params=DaemonParams(rate_hz=a.rate_hz, camera_dead_s=a.camera_dead_s),
        status=status.show,
    )
    install_sigint(daemon)
    try:
        summary = daemon.run(duration_s=a.duration_s)
    finally:
        if link is not None:
            link.close()
        status.end()
    p99 = summary.get("frame_to_command_ms_p99")
    print(
        f"{summary['cycles']} cycles, {summary['missed_deadlines']} missed deadlines, "
        f"frame-to-command p99 {p99:.1f} ms"
        if p99 is not None
        else f"{summary['cycles']} cycles, {summary['missed_deadlines']} missed deadlines, no frame used",
        file=sys.stderr,
    )
    if summary.get("corrupt_frames"):
        print(f"{summary['corrupt_frames']} corrupt frame(s) skipped", file=sys.stderr)
    print(f"mission: {guidance.outcome}", file=sys.stderr)
    end = daemon.session_end
    if end is not None and link is not None:
        print(
            f"MCU: planned end {'accepted' if end.accepted else 'NOT accepted'}"
            f"{f', state {end.state}' if end.state else ''} ({end.detail})",
            file=sys.stderr,
        )
    rc, why = exit_status(daemon)
    if rc != EXIT_OK:
        print(f"oibar: error: {why} (exit status {rc})", file=sys.stderr, flush=True)
    return rc


def cmd_replay(a: argparse.Namespace) -> int:
    from oibar.nav.daemon import load_navigator
    from oibar.nav.replay import format_summary, replay

    model = a.model or default_model_path()
    navigator = load_navigator(model, threads=a.threads)
    if a.calibration is not None:
        navigator.estimator.use_calibration(a.calibration)
        _report_calibration(navigator.estimator)
    status = StatusLine()

    def progress(i: int, n: int) -> None:
        status.show(f"replay {i}/{n} cycles", force=i == n)

    res = replay(a.log, navigator, a.out, progress=progress)
    status.end()
    print(format_summary(res))
    return EXIT_OK


def _report_calibration(est: Any) -> None:
    """The camera in use, on stderr; a warning when it covers less than the canonical view."""
    fm = getattr(est, "frame_map", None)
    if fm is None:
        return
    print(
        f"calibration {fm.calib.source}: {fm.calib.describe()}, remapped to the canonical camera",
        file=sys.stderr,
    )
    if fm.warning():
        print(f"oibar: warning: {fm.warning()}", file=sys.stderr, flush=True)


def _finite(values: Any) -> list[float | None]:
    """Numbers for JSON: NaN/inf (no answer) become null."""
    import numpy as np

    return [float(v) if np.isfinite(v) else None for v in np.asarray(values, float).ravel()]


def cmd_pose(a: argparse.Namespace) -> int:
    import json

    import numpy as np
    from PIL import Image

    from oibar.nav.pose import FrameError, KeypointPoseEstimator, PoseEstimator

    model = a.model or default_model_path()
    est = PoseEstimator(model, threads=a.threads)
    est.use_calibration(a.calibration)
    _report_calibration(est)
    if isinstance(est, KeypointPoseEstimator):
        est.search.cold_crop_budget = None  # every frame read cold with the full search
    failed = 0
    for path in a.frames:
        line: dict[str, Any] = {"frame": str(path)}
        try:
            with Image.open(path) as im:
                image = np.asarray(im.convert("RGB"))
        except Exception as exc:  # missing, unreadable, truncated, not an image (PIL raises several)
            failed += 1
            why = (
                exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc) or type(exc).__name__
            )
            line["error"] = f"cannot read the frame: {why}"
        else:
            est.forget()  # each frame on its own: nothing carried from the previous one
            t0 = time.perf_counter()
            try:
                e = est.estimate(image, t_s=0.0)
            except FrameError as exc:
                failed += 1
                line["error"] = f"frame refused: {exc}"
            else:
                line.update(
                    T_cam_target_m=_finite(e.T_cam_target_m),
                    q_cam_target_wxyz=_finite(e.q_cam_target),
                    confidence=float(e.confidence) if np.isfinite(e.confidence) else None,
                    flags=list(e.flags),
                    latency_ms=round((time.perf_counter() - t0) * 1e3, 3),
                )
        if "error" in line:
            line.update(
                T_cam_target_m=None, q_cam_target_wxyz=None, confidence=None, flags=[], latency_ms=None
            )
            print(f"oibar: error: {path}: {line['error']}", file=sys.stderr, flush=True)
        print(json.dumps(line), flush=True)
    if failed:
        print(
            f"oibar: error: {failed} of {len(a.frames)} frame(s) could not be read or were refused "
            f"(exit status {EXIT_FRAMES_FAILED})",
            file=sys.stderr,
            flush=True,
        )
        return EXIT_FRAMES_FAILED
    return EXIT_OK
