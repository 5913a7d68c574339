"""``oibar nav`` (the navigation daemon), ``oibar replay`` (re-run estimation on a log) and
``oibar pose`` (the estimator alone on image files)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from oibar import argtypes
from oibar.nav import helptext
from oibar.progress import StatusLine

if TYPE_CHECKING:
    from oibar.link.client import LinkClient

# Exit status of `oibar nav` (also in its --help, oibar.nav.helptext, and docs/navigation.md).
EXIT_OK = 0  # mission over, --duration-s reached, or Ctrl-C / SIGTERM: MCU session ended as planned
EXIT_INTERNAL = 1  # an unexpected error inside oibar (one line; -v for the traceback)
EXIT_ERROR = 2  # bad argument or start-up error (model, camera spec, empty source, vehicle, log)
EXIT_SOURCE_ENDED = 3  # the camera source ended (last frame of a video file or frame folder)
EXIT_SOURCE_DIED = 4  # the camera source died: no frame for --camera-dead-s
EXIT_MCU_NOT_SAFE = 5  # stopped otherwise cleanly, but the MCU did not accept the planned end
EXIT_INTERRUPTED = 130  # Ctrl-C before the daemon was running (oibar.cli)
# `oibar pose`: 0, 1, 2 as above, and
EXIT_FRAMES_FAILED = 3  # a frame could not be read or was refused (the others are still estimated)


def default_model_path() -> Path:
    """$OIBAR_MODEL, else the shipped model of this install (oibar.resources)."""
    from oibar.resources import default_model_path as shipped

    return shipped()


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``oibar nav``, ``oibar replay`` and ``oibar pose`` on the ``oibar`` parser's subparsers."""
    _register_nav(sub)
    _register_replay(sub)
    _register_pose(sub)


def _register_nav(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    nav = sub.add_parser(
        "nav",
        help="run the navigation daemon (camera -> OibarNet -> guidance -> MCU)",
        description=helptext.NAV_DESCRIPTION,
        epilog=helptext.NAV_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    # the options in --help's order: where frames come from and commands go, the log, the pace
    _nav_io_args(nav)
    _nav_log_args(nav)
    _nav_pace_args(nav)
    nav.set_defaults(handler=cmd_nav, run=run)


def _nav_io_args(nav: argparse.ArgumentParser) -> None:
    """The camera, the MCU's port, the model and its calibration, the vehicle."""
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


def _nav_log_args(nav: argparse.ArgumentParser) -> None:
    """The flight log (MCAP), its frames and the live view."""
    nav.add_argument(
        "--log",
        type=Path,
        default=None,
        metavar="DIR",
        help="log folder (default: runs/nav/<date-time>); the flight log flight.mcap is written there",
    )
    nav.add_argument("--no-log", action="store_true", help="do not write a flight log")
    nav.add_argument(
        "--record-frames",
        action="store_true",
        help="also record every frame read, lossless (about 50 MB per minute at 10 Hz): `oibar replay` needs them",
    )
    nav.add_argument(
        "--live",
        nargs="?",
        const=("127.0.0.1", 8765),  # (not passed through type)
        default=None,
        metavar="[HOST:]PORT",
        type=_live_address,
        help="serve the flight log's channels to the Foxglove app over WebSocket while flying "
        "(default address 127.0.0.1:8765; no authentication: loopback unless you mean it)",
    )


def _nav_pace_args(nav: argparse.ArgumentParser) -> None:
    """Rates, time limits, threads, the fill target and the serial speed."""
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


def _register_replay(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    rp = sub.add_parser(
        "replay",
        help="re-run pose estimation and the filter on a recorded flight log (MCAP)",
        description="Feed the frames of a flight log written by `oibar nav --record-frames` (MCAP), "
        "at their recorded times with the recorded odometry, through a fresh navigator and compare "
        "with the recorded estimates. With the flight's model, calibration and onnxruntime thread "
        "count (the defaults: taken from the log) on the same machine, every estimate comes out bit "
        "for bit; another --model or --calibration compares two estimators on the same flight.",
    )
    rp.add_argument("log", type=Path, help="flight.mcap written by oibar nav")
    rp.add_argument(
        "--model", type=Path, default=None, metavar="ONNX", help="model (default: as for oibar nav)"
    )
    rp.add_argument("--out", type=Path, default=None, help="write the replayed estimates here (JSON lines)")
    _calibration_arg(rp)
    rp.add_argument(
        "--threads",
        type=argtypes.positive_int(256),
        default=None,
        help="onnxruntime threads, 1-256 (default: the flight's, from the log)",
    )
    rp.set_defaults(handler=cmd_replay, run=run)


def _register_pose(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    ps = sub.add_parser(
        "pose",
        help="estimate the fixture's pose in image files (no daemon): one JSON line per frame",
        description=helptext.POSE_DESCRIPTION,
        epilog=helptext.POSE_EPILOG,
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


def _live_address(spec: str) -> tuple[str, int]:
    from oibar.nav.live import LiveError, parse_address

    try:
        return parse_address(spec)
    except LiveError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


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
    from oibar.nav.flightlog import FlightLogError
    from oibar.nav.pose import ModelFileError
    from oibar.nav.vehicle import VehicleError

    try:
        return int(args.handler(args))
    except (ModelFileError, CameraError, VehicleError, FlightLogError, CalibrationError, OSError) as exc:
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
    from oibar.nav.daemon import DaemonParams, NavDaemon, connect_in_background, install_sigint
    from oibar.nav.guidance import Guidance, MissionParams
    from oibar.nav.vehicle import open_vehicle
    from oibar.sdnotify import Notifier

    # model and calibration errors first, nothing opened yet
    navigator = _load_nav_model(a)
    camera = _open_camera(a)
    vehicle = open_vehicle(a.vehicle)
    log = _open_flight_log(a)
    link = None
    if a.port.lower() != "none":
        link = open_link(a.port, baudrate=a.baudrate)
        connect_in_background(link, on_error=lambda m: print(f"\nlink: {m} (retrying)", file=sys.stderr))
    guidance = Guidance(MissionParams(target_kpa=a.target_pressure_kpa))
    # the live status line on a terminal; in a log, one line every few seconds
    status = StatusLine()
    # under systemd (Type=notify): READY=1 now, WATCHDOG=1 from the loop's own status calls, so a
    # hung loop stops petting and the service is restarted (deploy/systemd/oibar-nav.service)
    notifier = Notifier()

    def show_status(line: str) -> None:
        notifier.watchdog(line)
        status.show(line)

    daemon = NavDaemon(
        navigator,
        guidance,
        camera,
        link=link,
        vehicle=vehicle,
        log=log,
        params=DaemonParams(rate_hz=a.rate_hz, camera_dead_s=a.camera_dead_s),
        status=show_status,
    )
    install_sigint(daemon)
    notifier.ready(f"navigating: camera {a.camera}, port {a.port}")
    try:
        summary = daemon.run(duration_s=a.duration_s)
    finally:
        notifier.stopping(f"stopped: {daemon.stop_reason}")
        notifier.close()
        if link is not None:
            link.close()
        status.end()
    _report_run(summary, daemon)
    rc, why = exit_status(daemon)
    if rc != EXIT_OK:
        print(f"oibar: error: {why} (exit status {rc})", file=sys.stderr, flush=True)
    return rc


def _load_nav_model(a: argparse.Namespace) -> Any:
    """The navigator of ``--model`` (with ``--calibration``), described in one line on stderr."""
    from oibar.nav.daemon import load_navigator

    model = a.model or default_model_path()
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
    return navigator


def _open_camera(a: argparse.Namespace) -> Any:
    from oibar.camera import FolderSource, VideoFileSource, open_source

    camera = open_source(a.camera, rate_hz=a.camera_rate_hz, realtime=True)
    if isinstance(camera, (FolderSource, VideoFileSource)):
        # a finite source is checked before anything opens: an empty folder or an undecodable
        # video is a start-up error (exit 2), not a run that waits for frames forever
        with camera:
            pass
    return camera


def _open_flight_log(a: argparse.Namespace) -> Any:
    """The flight log of ``--log``/``--no-log``, ``--record-frames`` and ``--live`` (None: neither
    a file nor a live view)."""
    from oibar.nav.flightlog import FlightLog

    if a.no_log and a.live is None:
        return None
    log_dir = a.log or Path("runs") / "nav" / time.strftime("%Y%m%d-%H%M%S")
    log = FlightLog(None if a.no_log else log_dir / "flight.mcap", live=a.live, frames=a.record_frames)
    if log.path is not None:
        print(f"log {log.path}{' (with frames)' if a.record_frames else ''}", file=sys.stderr)
    if log.live is not None:
        print(f"live view {log.live.url} (Foxglove: Open connection, Foxglove WebSocket)", file=sys.stderr)
    return log


def _report_run(summary: dict[str, Any], daemon: Any) -> None:
    """The run's last lines on stderr: cycles and latency, corrupt frames, the mission's
    outcome and how the planned end of the MCU session went."""
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
    print(f"mission: {daemon.guidance.outcome}", file=sys.stderr)
    end = daemon.session_end
    if end is not None and daemon.link is not None:
        print(
            f"MCU: planned end {'accepted' if end.accepted else 'NOT accepted'}"
            f"{f', state {end.state}' if end.state else ''} ({end.detail})",
            file=sys.stderr,
        )


def cmd_replay(a: argparse.Namespace) -> int:
    from oibar.nav.daemon import load_navigator
    from oibar.nav.replay import calibration_from_info, format_summary, read_run_info, replay

    model = a.model or default_model_path()
    info = read_run_info(a.log)  # the flight's thread count and calibration: the defaults
    threads = a.threads or (int(info.ort_intra_op_threads) if info is not None else 0) or 2
    navigator = load_navigator(model, threads=threads)
    calibration = a.calibration if a.calibration is not None else calibration_from_info(info)
    if calibration is not None:
        navigator.estimator.use_calibration(calibration)
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
                    crops=int(e.crops),
                )
        if "error" in line:
            line.update(
                T_cam_target_m=None,
                q_cam_target_wxyz=None,
                confidence=None,
                flags=[],
                latency_ms=None,
                crops=None,
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
