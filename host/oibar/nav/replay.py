"""``oibar replay``: run a recorded flight (an MCAP flight log, oibar.nav.flightlog) through a
fresh navigator and compare its estimates with the recorded ones.

Each cycle gets what the flight's navigator got: the frame's pixels (``/camera/image``, lossless),
the cycle and capture times, the vehicle's odometry and attitude (``/nav/cycle``), in order, cycles without
a frame included. With the same model, the same calibration (taken from the log's intrinsics unless
``--calibration`` names another) and the same onnxruntime thread count (the log's unless
``--threads`` says otherwise) on the same machine, every estimate and filter state comes out
bit for bit as recorded: replay reports each difference. Another model or calibration compares
two estimators on the same flight.

Guidance is not re-run: its inputs (the MCU's telemetry, the link) were those of the flight and
are in the log for reading.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from oibar.geometry.rotations import angle_between_quats_deg
from oibar.nav.flightlog import FlightLogError, LogInventory, LogMessage, read_messages
from oibar.nav.logschema import DecodeError, ProtobufDecoder

if TYPE_CHECKING:
    from oibar.nav.core import Navigator

REPLAY_TOPICS = ("/run/info", "/nav/cycle", "/camera/image", "/nav/estimate", "/nav/filter")
_FILTER_FIELDS = ("r_D_m", "v_D_mps", "att_rad", "pos_sigma_m", "vel_sigma_mps", "att_sigma_deg")


@dataclass
class ReplayResult:
    cycles: int = 0
    frames_replayed: int = 0
    frames_missing: int = 0  # a cycle that read a frame whose image is not in the log
    holds_recorded: int = 0
    holds_replayed: int = 0
    estimates_compared: int = 0
    estimates_exact: int = 0  # T, q and confidence bit for bit
    estimates_only_recorded: int = 0  # recorded, none replayed (or the other way round below)
    estimates_only_replayed: int = 0
    filter_compared: int = 0
    filter_exact: int = 0  # position, velocity, attitude and their sigmas bit for bit
    first_difference: str = ""
    dt_m: list[float] = field(default_factory=list)  # |T_new - T_recorded|
    dq_deg: list[float] = field(default_factory=list)
    model: str = ""
    model_matches: bool | None = None  # same SHA-256 as the flight's model (None: not recorded)
    threads: int = 0
    threads_recorded: int = 0
    calibration: str = ""
    truncated: bool = False  # the log ends without its summary (the flight was killed)
    notes: list[str] = field(default_factory=list)

    @property
    def exact(self) -> bool:
        """Every recorded estimate and filter state reproduced bit for bit, and nothing extra."""
        return (
            self.estimates_compared == self.estimates_exact
            and self.filter_compared == self.filter_exact
            and self.estimates_only_recorded == 0
            and self.estimates_only_replayed == 0
            and self.frames_missing == 0
        )

    def summary(self) -> dict[str, Any]:
        def stat(xs: list[float], f: Callable[[list[float]], Any]) -> float | None:
            return float(f(xs)) if xs else None

        return {
            "model": self.model,
            "model_matches_flight": self.model_matches,
            "threads": self.threads,
            "threads_in_flight": self.threads_recorded,
            "calibration": self.calibration,
            "cycles": self.cycles,
            "frames_replayed": self.frames_replayed,
            "frames_missing": self.frames_missing,
            "holds_recorded": self.holds_recorded,
            "holds_replayed": self.holds_replayed,
            "estimates_compared": self.estimates_compared,
            "estimates_exact": self.estimates_exact,
            "estimates_only_recorded": self.estimates_only_recorded,
            "estimates_only_replayed": self.estimates_only_replayed,
            "filter_states_compared": self.filter_compared,
            "filter_states_exact": self.filter_exact,
            "exact": self.exact,
            "first_difference": self.first_difference or None,
            "position_diff_m_mean": stat(self.dt_m, np.mean),
            "position_diff_m_max": stat(self.dt_m, np.max),
            "attitude_diff_deg_mean": stat(self.dq_deg, np.mean),
            "attitude_diff_deg_max": stat(self.dq_deg, np.max),
            "log_truncated": self.truncated,
            "notes": self.notes,
        }


def decode_image(m: LogMessage, msg: Any) -> np.ndarray:
    """An RGB uint8 frame from a ``foxglove.RawImage`` (rgb8, bgr8, mono8) or
    ``foxglove.CompressedImage`` (png, jpeg: the original bytes of a camera that sends them)."""
    if m.schema_name.endswith("RawImage"):
        w, h, step, enc = int(msg.width), int(msg.height), int(msg.step), str(msg.encoding)
        ch = {"rgb8": 3, "bgr8": 3, "mono8": 1}.get(enc)
        if ch is None:
            raise DecodeError(f"camera image encoding {enc!r} is not rgb8, bgr8 or mono8")
        buf = np.frombuffer(msg.data, np.uint8)
        if buf.size < h * step or step < w * ch:
            raise DecodeError(f"camera image {w}x{h} {enc}: {buf.size} bytes for a step of {step}")
        img = buf[: h * step].reshape(h, step)[:, : w * ch].reshape(h, w, ch)
        if enc == "bgr8":
            img = img[:, :, ::-1]
        elif enc == "mono8":
            img = np.repeat(img, 3, axis=2)
        return np.ascontiguousarray(img)
    import cv2

    decoded = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR)
    if decoded is None:
        raise DecodeError(f"camera image ({msg.format or 'unknown format'}) cannot be decoded")
    return np.ascontiguousarray(decoded[:, :, ::-1])


@dataclass
class _Group:
    log_time: int
    cycle: Any = None
    image: np.ndarray | None = None
    estimate: Any = None
    filter: Any = None


def _groups(
    messages: Iterator[LogMessage], decoder: ProtobufDecoder, on_info: Callable[[Any], None]
) -> Iterator[_Group]:
    """The log's cycles: each /nav/cycle with its frame, estimate and filter state (the messages
    of one cycle share its log time and are written together)."""
    current: _Group | None = None
    for m in messages:
        if m.topic == "/run/info":
            on_info(decoder.decode(m.schema_id, m.schema_name, m.schema_data, m.data))
            continue
        if current is not None and m.log_time != current.log_time:
            if current.cycle is not None:
                yield current
            current = None
        if current is None:
            current = _Group(m.log_time)
        msg = decoder.decode(m.schema_id, m.schema_name, m.schema_data, m.data)
        if m.topic == "/nav/cycle":
            current.cycle = msg
        elif m.topic == "/camera/image":
            current.image = decode_image(m, msg)
        elif m.topic == "/nav/estimate":
            current.estimate = msg
        elif m.topic == "/nav/filter":
            current.filter = msg
    if current is not None and current.cycle is not None:
        yield current


def read_run_info(path: str | Path) -> Any:
    """The log's ``oibar.log.RunInfo`` (None when it has none)."""
    decoder = ProtobufDecoder()
    for m in read_messages(path, topics=["/run/info"]):
        return decoder.decode(m.schema_id, m.schema_name, m.schema_data, m.data)
    return None


def calibration_from_info(info: Any) -> Any:
    """The flight's camera calibration from its logged intrinsics (None when it flew the
    canonical camera)."""
    if info is None or not info.HasField("intrinsics") or not info.intrinsics.calibrated:
        return None
    from oibar.camera.calibration import CameraCalibration

    intr = info.intrinsics
    return CameraCalibration(
        int(intr.width_px),
        int(intr.height_px),
        np.asarray(intr.K, float).reshape(3, 3),
        np.asarray(intr.dist, float),
        f"the flight log ({intr.calibration_source or 'calibration'})",
    )


def _same(a: Any, b: Any) -> bool:
    """Bit-for-bit equal float vectors (NaN equal to NaN)."""
    x, y = np.asarray(a, float), np.asarray(b, float)
    return x.shape == y.shape and bool(np.array_equal(x.view(np.uint64), y.view(np.uint64)))


def _odometry(cyc: Any) -> Any:
    if not cyc.HasField("odometry"):
        return None
    o = cyc.odometry
    if o.malformed or len(o.v_D_mps) != 3:
        return None  # the flight's navigator refused it too (malformed): nothing fused either way
    return (float(o.t_s), np.asarray(o.v_D_mps, float), float(o.sigma_mps))


def _vehicle_attitude(cyc: Any) -> Any:
    """The vehicle's attitude the flight checked the frame against (None: none, or malformed)."""
    if not cyc.HasField("vehicle_attitude"):
        return None
    a = cyc.vehicle_attitude
    if a.malformed or len(a.att_rad) != 3:
        return None  # the flight's check ignored it too
    return (float(a.t_s), np.asarray(a.att_rad, float), float(a.sigma_rad))


def replay(
    log_path: str | Path,
    navigator: Navigator,
    out_path: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
    threads_recorded_check: bool = True,
) -> ReplayResult:
    """Replay the flight log at ``log_path`` through ``navigator`` (fresh: nothing fed yet).
    ``out_path``: one JSON line per cycle with the replayed and the recorded estimate, then the
    summary. FlightLogError when the log cannot be read or holds no cycle."""
    from oibar.nav.flightlog import ort_threads

    log_path = Path(log_path)
    inv = _replayable(log_path)
    n_cycles = inv.message_counts.get("/nav/cycle", 0)
    est = navigator.estimator
    res = ReplayResult(model=str(getattr(est, "path", "")), truncated=not inv.complete)
    res.threads = ort_threads(est)
    decoder = ProtobufDecoder()

    def on_info(info: Any) -> None:
        _check_run_info(res, est, info, threads_recorded_check)

    out = open(out_path, "w", encoding="utf-8") if out_path else None  # noqa: SIM115  (closed below)
    try:
        msgs = read_messages(log_path, topics=REPLAY_TOPICS)
        for g in _groups(msgs, decoder, on_info):
            step, new = _replay_cycle(res, navigator, g)
            if out is not None:
                out.write(json.dumps(_cycle_record(g, step, new)) + "\n")
            if progress:
                progress(res.cycles, n_cycles)
    except DecodeError as exc:
        raise FlightLogError(f"{log_path}: {exc}") from exc
    finally:
        if out is not None:
            out.write(json.dumps({"summary": res.summary()}) + "\n")
            out.close()
    fmap = getattr(est, "frame_map", None)
    res.calibration = "" if fmap is None else str(fmap.calib.source)
    return res


def _replayable(log_path: Path) -> LogInventory:
    """The log's inventory; FlightLogError when it holds no cycle or no frame to replay."""
    from oibar.nav.flightlog import inspect_log

    inv = inspect_log(log_path)
    if inv.message_counts.get("/nav/cycle", 0) == 0:
        raise FlightLogError(f"{log_path}: no navigation cycle recorded")
    if inv.message_counts.get("/camera/image", 0) == 0:
        raise FlightLogError(
            f"{log_path}: the log holds no camera frame, so nothing can be replayed; "
            "record with `oibar nav --record-frames`"
        )
    return inv


def _check_run_info(res: ReplayResult, est: Any, info: Any, threads_recorded_check: bool) -> None:
    """What the flight ran (its ``oibar.log.RunInfo``) against what replays it: the model's
    SHA-256 and onnxruntime's thread count, a note for each that differs."""
    if res.threads_recorded:
        return  # repeated for live viewers: the first is the flight's
    res.threads_recorded = int(info.ort_intra_op_threads)
    if info.model_sha256 and getattr(est, "path", None) is not None:
        from oibar.hashing import sha256_file

        try:
            res.model_matches = sha256_file(Path(est.path)) == info.model_sha256
        except OSError:
            res.model_matches = None
        if res.model_matches is False:
            res.notes.append(f"another model than the flight's ({info.model_version or info.model_path})")
    if (
        threads_recorded_check
        and res.threads
        and res.threads_recorded
        and res.threads != res.threads_recorded
    ):
        res.notes.append(
            f"onnxruntime threads {res.threads}, the flight used {res.threads_recorded}: "
            "estimates may differ in the last bits"
        )


def _replay_cycle(res: ReplayResult, navigator: Navigator, g: _Group) -> tuple[Any, Any]:
    """One recorded cycle through the navigator, compared with the record: (its step, its
    ``oibar.log.PoseEstimate`` or None)."""
    from oibar.nav.flightlog import estimate_message

    cyc = g.cycle
    res.cycles += 1
    if cyc.hold_reason:
        res.holds_recorded += 1
    image = g.image
    if cyc.has_frame and image is None:
        res.frames_missing += 1
    step = navigator.step(
        float(cyc.t_s),
        image,
        frame_t_s=float(cyc.frame_t_s) if image is not None else None,
        frame_seq=int(cyc.frame_seq) if image is not None else None,
        odometry=_odometry(cyc),
        attitude_ref=_vehicle_attitude(cyc) if image is not None else None,
    )
    if image is not None:
        res.frames_replayed += 1
    if step.hold_reason:
        res.holds_replayed += 1
    new = estimate_message(int(cyc.cycle), step)
    _compare_estimate(res, int(cyc.cycle), g.estimate, new)
    if g.filter is not None:
        _compare_filter(res, int(cyc.cycle), g.filter, navigator, float(cyc.t_s))
    return step, new


def _cycle_record(g: _Group, step: Any, new: Any) -> dict[str, Any]:
    """The ``--out`` line of a cycle: the replayed and the recorded estimate."""
    return {
        "cycle": int(g.cycle.cycle),
        "t_s": float(g.cycle.t_s),
        "estimate": _estimate_json(new),
        "recorded_estimate": _estimate_json(g.estimate),
        "hold_reason": step.hold_reason,
    }


def _estimate_json(m: Any) -> dict[str, Any] | None:
    if m is None:
        return None

    def fin(xs: Any) -> list[float | None]:
        return [float(v) if np.isfinite(v) else None for v in xs]

    return {
        "T_cam_target_m": fin(m.T_cam_target_m),
        "q_cam_target_wxyz": fin(m.q_cam_target_wxyz),
        "confidence": float(m.confidence) if np.isfinite(m.confidence) else None,
        "flags": list(m.flags),
    }


def _note_difference(res: ReplayResult, text: str) -> None:
    if not res.first_difference:
        res.first_difference = text


def _compare_estimate(res: ReplayResult, cycle: int, old: Any, new: Any) -> None:
    if old is None and new is None:
        return
    if old is None:
        res.estimates_only_replayed += 1
        _note_difference(res, f"cycle {cycle}: an estimate the flight did not make")
        return
    if new is None:
        res.estimates_only_recorded += 1
        _note_difference(res, f"cycle {cycle}: no estimate where the flight made one")
        return
    res.estimates_compared += 1
    same = (
        _same(old.T_cam_target_m, new.T_cam_target_m)
        and _same(old.q_cam_target_wxyz, new.q_cam_target_wxyz)
        and _same([old.confidence], [new.confidence])
        and list(old.flags) == list(new.flags)
    )
    if same:
        res.estimates_exact += 1
    else:
        _note_difference(res, f"cycle {cycle}: estimate differs")
    T_old, T_new = np.asarray(old.T_cam_target_m, float), np.asarray(new.T_cam_target_m, float)
    if T_old.size == 3 and T_new.size == 3 and np.all(np.isfinite(T_old)) and np.all(np.isfinite(T_new)):
        res.dt_m.append(float(np.linalg.norm(T_new - T_old)))
        q_old, q_new = np.asarray(old.q_cam_target_wxyz, float), np.asarray(new.q_cam_target_wxyz, float)
        if q_old.size == 4 and q_new.size == 4:
            # the same bits are 0 deg: arccos of a dot product rounded near 1 would say 1e-6
            res.dq_deg.append(0.0 if _same(q_old, q_new) else float(angle_between_quats_deg(q_new, q_old)))


def _compare_filter(res: ReplayResult, cycle: int, old: Any, navigator: Navigator, t_s: float) -> None:
    try:
        st = navigator.filter.state(t_s)
    except ValueError:
        return
    res.filter_compared += 1
    same = bool(old.valid) == bool(st.valid) and all(
        _same(getattr(old, name), getattr(st, name)) for name in _FILTER_FIELDS if len(getattr(old, name))
    )
    if same:
        res.filter_exact += 1
    else:
        _note_difference(res, f"cycle {cycle}: filter state differs")


def format_summary(res: ReplayResult) -> str:
    s = res.summary()
    lines = [
        f"model               {s['model']}"
        + (
            ""
            if res.model_matches is None
            else (" (the flight's)" if res.model_matches else " (NOT the flight's)")
        ),
        f"onnxruntime threads {res.threads} (flight: {res.threads_recorded or '?'})",
        f"cycles              {s['cycles']}"
        + (" (the log ends early: the flight was cut short)" if res.truncated else ""),
        f"frames replayed     {s['frames_replayed']} ({s['frames_missing']} missing)",
        f"hold cycles         recorded {s['holds_recorded']}, replayed {s['holds_replayed']}",
        f"estimates           {res.estimates_exact} of {res.estimates_compared} bit for bit"
        + (
            f"; {res.estimates_only_recorded} only recorded, {res.estimates_only_replayed} only replayed"
            if res.estimates_only_recorded or res.estimates_only_replayed
            else ""
        ),
        f"filter states       {res.filter_exact} of {res.filter_compared} bit for bit",
    ]
    if res.dt_m:
        lines += [
            f"position vs record  mean {s['position_diff_m_mean']:.3g} m, max {s['position_diff_m_max']:.3g} m",
            f"attitude vs record  mean {s['attitude_diff_deg_mean']:.3g} deg, "
            f"max {s['attitude_diff_deg_max']:.3g} deg",
        ]
    lines.append(
        "exact               yes: every estimate as recorded"
        if res.exact
        else f"exact               no ({res.first_difference or 'frames missing'})"
    )
    lines += [f"note                {n}" for n in res.notes]
    return "\n".join(lines)


def summary_json(res: ReplayResult) -> str:
    return json.dumps(res.summary(), indent=1)
