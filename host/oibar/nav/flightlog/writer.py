"""The flight log's writer: :class:`FlightLog` takes each cycle's messages (:class:`CycleInputs`)
from the navigation cycle and writes them in its own thread, through the Foxglove SDK, to the MCAP
file and/or the live view (the channels: oibar.nav.flightlog)."""

from __future__ import annotations

import json
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from oibar.nav import logschema
from oibar.nav.flightlog import wellknown
from oibar.nav.flightlog.channels import (
    CHANNELS,
    FLUSH_EVERY_S,
    FRAME_CAMERA,
    FRAME_FIXTURE,
    FRAME_FIXTURE_FILTER,
    JSON_CHANNELS,
    QUEUE_CYCLES,
    STATIC_EVERY_S,
)
from oibar.nav.flightlog.errors import FlightLogError
from oibar.nav.flightlog.guarded_file import GuardedFile
from oibar.nav.flightlog.messages import (
    cycle_message,
    estimate_message,
    filter_message,
    guidance_message,
    is_pb,
    jsonable,
)

# One cycle's messages as the writer thread takes them: (topic, payload, log time in ns); a
# payload is encoded bytes, or a frame (numpy) that the thread encodes off the cycle.
Item = list[tuple[str, Any, int]]


def _foxglove() -> Any:
    try:
        import foxglove
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise FlightLogError(
            "the Foxglove SDK is not installed: pip install foxglove-sdk (requirements/host.txt)"
        ) from exc
    return foxglove


@dataclass
class CycleInputs:
    """What one cycle gives the log (NavDaemon._log_cycle)."""

    t_s: float
    cycle: int
    step: Any  # oibar.nav.core.NavStep
    out: Any  # oibar.nav.guidance.GuidanceOutput
    image: np.ndarray | None = None
    frame_seq: int | None = None
    frame_t_s: float | None = None
    odometry: Any = None  # as fed to the navigator: (t_s, v_D_mps, sigma_mps) or None
    vehicle_attitude: Any = None  # as fed with the frame: (t_s, att_rad, sigma_rad) or None
    link_up: bool = False
    telemetry: Any = None  # pb.Telemetry
    events: list[Any] = field(default_factory=list)  # pb.Event
    results: list[Any] = field(default_factory=list)  # guidance.RequestResult
    mcu_state: str = ""
    cycle_ms: float = 0.0
    corrupt_frames: int = 0
    camera_error: str = ""


class FlightLog:
    """Writes the channels (oibar.nav.flightlog.CHANNELS) to an MCAP file (``path``; the frames
    only with ``frames``) and/or serves them live (a :class:`oibar.nav.live.LiveServer` on
    ``live``, (host, port)). ``start`` once, ``cycle`` every cycle, ``close`` at the end (with the summary). Opening the
    file or the server raises OSError (a start-up error); after that nothing raises."""

    def __init__(
        self,
        path: str | Path | None,
        *,
        live: tuple[str, int] | None = None,
        frames: bool = False,
        queue_cycles: int = QUEUE_CYCLES,
        compression_threads: int = 0,
    ) -> None:
        fox = _foxglove()
        from foxglove import messages as fm
        from foxglove.mcap import MCAPWriteOptions

        self._fm = fm
        self.path = Path(path) if path is not None else None
        self.frames = bool(frames)  # the camera frames into the file (the live view always gets them)
        self.error: str | None = None
        self.messages_written = 0  # handed to the SDK (file and/or live view)
        self.messages_lost = 0  # for the file: dropped by a full queue or after a write error
        self.cycles_logged = 0
        self.flush_every_s = FLUSH_EVERY_S
        self._last_flush_ns: int | None = None
        self._ctx = fox.Context()
        self._file: GuardedFile | None = None
        self._mcap: Any = None
        self.live: Any = None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = GuardedFile(self.path)
            # one thread: the SDK compresses in the writer thread, off the navigation cycle
            options = MCAPWriteOptions(compression_threads=compression_threads, profile="oibar")
            self._mcap = fox.open_mcap(
                self._file,
                context=self._ctx,
                writer_options=options,
                channel_filter=None if self.frames else (lambda ch: ch.topic != "/camera/image"),
            )
        if live is not None:
            from oibar.nav.live import LiveServer

            try:
                self.live = LiveServer(self._ctx, host=live[0], port=live[1])
            except Exception:
                self._close_file()
                raise
        self._channels: dict[str, Any] = {}
        for topic, schema_name in CHANNELS.items():
            self._channels[topic] = self._make_channel(fox, topic, schema_name)
        self._queue: queue.Queue[Item | None] = queue.Queue(maxsize=max(1, queue_cycles))
        self._wall0_ns = time.time_ns()
        self._static: list[tuple[str, bytes]] = []
        self._next_static_s = 0.0
        self._last_telemetry: Any = None
        self._closed = False
        self._thread = threading.Thread(target=self._write_loop, name="oibar-flight-log", daemon=True)
        self._thread.start()

    def _make_channel(self, fox: Any, topic: str, schema_name: str) -> Any:
        if topic in JSON_CHANNELS:
            return fox.Channel(topic, schema={"type": "object", "title": schema_name}, context=self._ctx)
        if schema_name.startswith("foxglove."):
            cls = getattr(self._fm, schema_name.split(".", 1)[1])
            schema = cls.get_schema()
        elif schema_name.startswith("oibar.log."):
            schema = fox.Schema(name=schema_name, encoding="protobuf", data=logschema.OWN_SCHEMA_DATA)
        else:
            from oibar import pb

            cls = getattr(pb, schema_name.rsplit(".", 1)[1])
            schema = fox.Schema(name=schema_name, encoding="protobuf", data=logschema.schema_data(cls))
        return fox.Channel(topic, schema=schema, message_encoding="protobuf", context=self._ctx)

    # -- state ------------------------------------------------------------------------------

    @property
    def ok(self) -> bool:
        return self.error is None

    @property
    def wall0_ns(self) -> int:
        return self._wall0_ns

    def log_time_ns(self, t_s: float) -> int:
        """The log time of a message of daemon time ``t_s`` (wall clock, ns)."""
        return self._wall0_ns + round(float(t_s) * 1e9)

    # -- the writer thread ------------------------------------------------------------------

    def _write_loop(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            self._write(item)

    def _write(self, item: Item) -> None:
        if self._file is not None and self._file.error is not None:
            self._file_failed(len(item))
            if self.live is None:
                return
        for topic, payload, log_time in item:
            if isinstance(payload, np.ndarray):
                payload = wellknown.raw_image(self._fm, payload, log_time)
            try:
                self._channels[topic].log(payload, log_time=log_time)
                self.messages_written += 1
            except Exception as exc:  # the SDK's own failure: never the navigator's
                if self.error is None:
                    self.error = f"flight log: {type(exc).__name__}: {exc}"
                self.messages_lost += 1
        if self._mcap is not None and item:
            lt = item[-1][2]
            if self._last_flush_ns is None:
                self._last_flush_ns = lt
            elif lt - self._last_flush_ns >= self.flush_every_s * 1e9:
                self._last_flush_ns = lt
                try:  # ends the chunk: on disk now, not when 1 MB has gathered
                    self._mcap.flush()
                except Exception:
                    pass  # a write error is the file's, seen below
        if self._file is not None and self._file.error is not None:
            self._file_failed(0)

    def _file_failed(self, lost: int) -> None:
        """The file cannot be written: report once, close the writer (its output is discarded),
        count what the file misses from now on."""
        assert self._file is not None
        if self.error is None:
            self.error = self._file.error
        self.messages_lost += lost
        if self._mcap is not None:
            mcap, self._mcap = self._mcap, None
            try:
                mcap.close()
            except Exception:
                pass

    def _put(self, item: Item) -> None:
        if self._closed:
            return
        try:
            self._queue.put_nowait(item)
        except queue.Full:  # the writer is behind (slow disk): this cycle is not recorded
            self.messages_lost += len(item)

    # -- what the daemon calls --------------------------------------------------------------

    def start(self, info: Any, intrinsics: Any) -> None:
        """The run's ``oibar.log.RunInfo`` (``run_info``) and the camera's
        ``foxglove.CameraCalibration``: written now and again every STATIC_EVERY_S."""
        fm = self._fm
        self._static = [
            ("/run/info", info.SerializeToString()),
            ("/camera/calibration", intrinsics),
            (
                "/nav/fixture",
                wellknown.fixture_outline_entities(
                    fm, [(FRAME_FIXTURE, (0.1, 1.0, 0.3, 1.0)), (FRAME_FIXTURE_FILTER, (1.0, 0.6, 0.1, 0.8))]
                ).encode(),
            ),
        ]
        self._put([(t, p, self._wall0_ns) for t, p in self._static])
        self._next_static_s = STATIC_EVERY_S

    def cycle(self, c: CycleInputs, nav_filter: Any = None) -> None:
        """Record one cycle. ``nav_filter``: the navigator's filter, read for its state at the
        cycle's time (with the sigmas the solution does not carry)."""
        try:
            item = self._cycle_item(c, nav_filter)
        except Exception as exc:  # a malformed input must not stop navigation: count it
            if self.error is None:
                self.error = f"flight log: cycle {c.cycle} not recorded ({type(exc).__name__}: {exc})"
            self.messages_lost += 1
            return
        self.cycles_logged += 1
        self._put(item)

    def _cycle_item(self, c: CycleInputs, nav_filter: Any) -> Item:
        """Every message of one cycle, in the order they are written."""
        lt = self.log_time_ns(c.t_s)
        item: Item = []
        if c.t_s >= self._next_static_s and self._static:
            self._next_static_s = c.t_s + STATIC_EVERY_S
            item += [(t, p, lt) for t, p in self._static]
        item.append(("/nav/cycle", cycle_message(c).SerializeToString(), lt))
        if c.image is not None and (self.frames or self.live is not None):
            item.append(("/camera/image", c.image, lt))
        item += self._estimate_items(c, lt)
        item += self._filter_items(c, nav_filter, lt)
        item.append(("/guidance/command", guidance_message(c.cycle, c.t_s, c.out).SerializeToString(), lt))
        item += self._link_items(c, lt)
        return item

    def _estimate_items(self, c: CycleInputs, lt: int) -> Item:
        """The estimate in full, and as a pose and a transform for the app when it is finite."""
        est = estimate_message(c.cycle, c.step)
        if est is None:
            return []
        item: Item = [("/nav/estimate", est.SerializeToString(), lt)]
        e = c.step.estimate
        if e.finite:
            fm = self._fm
            ts = wellknown.stamp(fm, lt)
            pose = wellknown.pose(fm, e.T_cam_target_m, e.q_cam_target)
            item.append(
                ("/nav/pose", fm.PoseInFrame(timestamp=ts, frame_id=FRAME_CAMERA, pose=pose).encode(), lt)
            )
            item.append(
                ("/tf", wellknown.transform(fm, ts, FRAME_FIXTURE, e.T_cam_target_m, e.q_cam_target), lt)
            )
        return item

    def _filter_items(self, c: CycleInputs, nav_filter: Any, lt: int) -> Item:
        """The filter's state at the cycle's time, and its pose as a transform when it is valid."""
        state = None
        initialised = False
        if nav_filter is not None:
            initialised = bool(getattr(nav_filter, "initialised", False))
            try:
                state = nav_filter.state(c.t_s)
            except ValueError:  # a clock that went backwards: the state is not this cycle's
                state = None
        item: Item = [
            (
                "/nav/filter",
                filter_message(c.cycle, c.t_s, state, c.step, initialised).SerializeToString(),
                lt,
            )
        ]
        sol = c.step.solution
        if sol.valid:
            fm = self._fm
            tf = wellknown.transform(
                fm, wellknown.stamp(fm, lt), FRAME_FIXTURE_FILTER, sol.t_cam_target_m, sol.q_cam_target
            )
            item.append(("/tf", tf, lt))
        return item

    def _link_items(self, c: CycleInputs, lt: int) -> Item:
        """The navigation update sent, the MCU's telemetry when it is new, and its events."""
        from oibar import pb

        item: Item = []
        nav = c.out.nav
        if is_pb(nav, pb.NavUpdate.DESCRIPTOR.full_name):
            item.append(("/link/nav_update", nav.SerializeToString(), lt))
        tm = c.telemetry
        if tm is not None and tm is not self._last_telemetry and is_pb(tm, pb.Telemetry.DESCRIPTOR.full_name):
            self._last_telemetry = tm
            item.append(("/link/telemetry", tm.SerializeToString(), lt))
        for ev in c.events:
            if is_pb(ev, pb.Event.DESCRIPTOR.full_name):
                item.append(("/link/events", ev.SerializeToString(), lt))
        return item

    def close(self, summary: dict[str, Any] | None = None, t_s: float | None = None) -> None:
        """Write the summary (``/run/summary``), drain the writer, finish the file, stop the live
        view. Never raises; safe to call twice."""
        if self._closed:
            return
        if summary is not None:
            summary = {**summary, "log_messages_lost": self.messages_lost, "log_error": self.error}
            lt = self.log_time_ns(t_s) if t_s is not None else time.time_ns()
            item = [("/run/summary", json.dumps(jsonable(summary)).encode(), lt)]
            try:  # the end of the run: worth waiting a little for a busy writer
                self._queue.put(item, timeout=5.0)
            except queue.Full:
                self.messages_lost += 1
        self._closed = True
        try:  # after everything queued
            self._queue.put(None, timeout=10.0)
        except queue.Full:
            pass
        self._thread.join(timeout=10.0)
        if self._thread.is_alive():  # a disk that hangs: leave the file to the writer, never hang the stop
            if self.error is None:
                self.error = f"{self.path}: the log writer did not finish within 10 s"
        else:
            self._close_file()
        if self.live is not None:
            self.live.stop()

    def _close_file(self) -> None:
        if self._mcap is not None:
            mcap, self._mcap = self._mcap, None
            try:
                mcap.close()
            except Exception as exc:
                if self.error is None:
                    self.error = f"{self.path}: {exc}"
        if self._file is not None:
            self._file.close()
            if self.error is None and self._file.error is not None:
                self.error = self._file.error

    def __enter__(self) -> FlightLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
