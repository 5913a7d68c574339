"""What the run is, for ``/run/info`` and ``/camera/calibration``: versions, the model and its
SHA-256, onnxruntime's thread count, the camera's intrinsics."""

from __future__ import annotations

import platform
import socket
import sys
from pathlib import Path
from typing import Any

import numpy as np

from oibar.hashing import sha256_file
from oibar.nav import logschema
from oibar.nav.flightlog.channels import FRAME_CAMERA
from oibar.nav.flightlog.messages import vec


def camera_intrinsics(estimator: Any) -> tuple[Any, Any]:
    """The camera the frames come from, as ``oibar.log.Intrinsics`` and as Foxglove's
    ``CameraCalibration`` (frame ``camera``): the calibration in use, else the model's canonical
    camera."""
    from foxglove import messages as fm

    from oibar.camera.calibration import canonical_camera

    meta = getattr(estimator, "meta", {}) or {}
    try:
        K_can, (w_can, h_can) = canonical_camera(meta)
    except Exception:  # a test's stand-in estimator without camera metadata
        K_can, (w_can, h_can) = np.eye(3), (0, 0)
    fmap = getattr(estimator, "frame_map", None)
    intr = logschema.new(
        "Intrinsics", canonical_K=vec(K_can), canonical_width_px=int(w_can), canonical_height_px=int(h_can)
    )
    if fmap is not None:
        cal = fmap.calib
        K, dist, (w, h) = np.asarray(cal.K, float), np.asarray(cal.dist, float), cal.size_wh
        intr.calibrated, intr.calibration_source = True, str(cal.source)
    else:
        K, dist, (w, h) = np.asarray(K_can, float), np.zeros(5), (w_can, h_can)
    intr.width_px, intr.height_px = int(w), int(h)
    intr.K.extend(vec(K))
    intr.dist.extend(vec(dist))
    d = vec(dist)
    model = "rational_polynomial" if len(d) == 8 else "plumb_bob"
    if len(d) not in (5, 8):  # Foxglove knows these two; the full vector is in /run/info
        d = (d + [0.0] * 5)[:5]
    P = np.hstack([K, np.zeros((3, 1))])
    cal_msg = fm.CameraCalibration(
        frame_id=FRAME_CAMERA,
        width=int(w),
        height=int(h),
        distortion_model=model,
        D=d,
        K=vec(K),
        R=vec(np.eye(3)),
        P=vec(P),
    )
    return intr, cal_msg.encode()


def run_info(estimator: Any, camera: str, rate_hz: float, wall_clock_start_s: float) -> Any:
    """``oibar.log.RunInfo`` of this run: versions, model, onnxruntime threads, intrinsics."""
    import oibar
    from oibar import pb

    info = logschema.new(
        "RunInfo",
        log_format_version=logschema.LOG_FORMAT_VERSION,
        package_version=str(oibar.__version__),
        protocol_version=int(pb.PROTOCOL_VERSION),
        python_version=sys.version.split()[0],
        platform=platform.platform(),
        hostname=socket.gethostname(),
        camera=str(camera),
        rate_hz=float(rate_hz),
        wall_clock_start_s=float(wall_clock_start_s),
        command_line=" ".join(sys.argv),
    )
    meta = getattr(estimator, "meta", {}) or {}
    path = getattr(estimator, "path", None)
    if path is not None:
        info.model_path = str(path)
        try:
            info.model_sha256 = sha256_file(Path(path))
        except OSError:
            pass
        from oibar.resources import model_version_text

        info.model_text = model_version_text(Path(path))
    info.model_version = str(meta.get("model_version", ""))
    info.ort_intra_op_threads = ort_threads(estimator)
    try:
        import onnxruntime

        info.onnxruntime_version = str(onnxruntime.__version__)
    except ImportError:
        pass
    limits = getattr(estimator, "range_limits_m", None)
    if limits is not None:
        info.range_limits_m.extend(vec(limits))
    intr, _ = camera_intrinsics(estimator)
    info.intrinsics.CopyFrom(intr)
    return info


def ort_threads(estimator: Any) -> int:
    """The estimator's onnxruntime intra-op thread count (0 when it has no session): a direct
    model's session, or a keypoint model's reader's (its networks all share the count)."""
    for owner in (estimator, getattr(estimator, "reader", None), getattr(estimator, "first", None)):
        session = getattr(owner, "session", None)
        if session is None:
            continue
        try:
            return int(session.get_session_options().intra_op_num_threads)
        except Exception:
            continue
    return 0
