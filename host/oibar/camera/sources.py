"""Camera sources: one interface over a real camera, a video file, a folder of frames and the
HIL rig's simulated camera.

Every source delivers :class:`Frame` objects: an RGB ``uint8`` image of shape (H, W, 3) (the
convention of the renderer and of OibarNet; OpenCV's BGR is converted), a sequence number
counted from 0 by the source, and two timestamps:

* ``t_s``: the capture time on the source's own monotonic clock, strictly increasing. For a
  device it is ``time.monotonic()`` right after the grab; for a video file the frame's position
  (index / fps); for a folder the ``time_s`` column of its poses/frames table, or index / rate;
  for a simulated camera the time passed to the render function.
* ``t_host``: ``time.monotonic()`` when :meth:`CameraSource.read` returned the frame, so a
  consumer can tell how old a frame is whatever the source.

Use a source as a context manager (``with VideoFileSource(p) as cam: frame = cam.read()``) or
call :meth:`~CameraSource.open` / :meth:`~CameraSource.close`. :meth:`~CameraSource.read`
blocks until the next frame and raises :class:`EndOfStream` at the end of a finite source and
:class:`CameraLost` when a live source stops delivering. :class:`~oibar.camera.latest.LatestFrame`
runs a source in a background thread for the 10 Hz loop.
"""

from __future__ import annotations

import logging
import math
import os
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from oibar.camera.errors import (
    CameraError,
    CameraLost,
    CameraOpenError,
    CorruptFrame,
    EmptySource,
    EndOfStream,
    SourceNotFound,
    SourceUnreadable,
)

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
VIDEO_EXTENSIONS = (".avi", ".mp4", ".mkv", ".mov", ".m4v", ".webm", ".mpg", ".mpeg")
# Tables looked for (in the folder, then in its parent: the dataset's seqNN/frames + seqNN/poses.csv).
TIMESTAMP_TABLES = ("poses.csv", "frames.csv")
DEFAULT_RATE_HZ = 10.0


def _cv2():
    # Imported on first use: the package is importable (and its errors usable) without OpenCV.
    try:
        import cv2
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise CameraError(
            "OpenCV is not installed; install opencv-python-headless (requirements/host.txt)"
        ) from exc
    return cv2


@dataclass(frozen=True)
class Frame:
    """One captured frame (see the module docstring for the timestamp conventions)."""

    image: np.ndarray = field(repr=False)
    seq: int
    t_s: float
    t_host: float
    source: str = ""

    @property
    def age_s(self) -> float:
        """Seconds since the source delivered this frame (host monotonic clock)."""
        return time.monotonic() - self.t_host


def to_rgb(image: object, what: str, bgr: bool = False) -> np.ndarray:
    """Normalise an image to contiguous RGB uint8 (H, W, 3); grey and BGRA/RGBA are accepted."""
    if not isinstance(image, np.ndarray):
        raise CameraError(f"{what}: expected a numpy image, got {type(image).__name__}")
    img = image
    if img.dtype != np.uint8:
        raise CameraError(f"{what}: expected uint8 pixels, got {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.ndim == 3 and img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    elif img.ndim == 3 and img.shape[2] in (3, 4):
        img = img[:, :, :3]
        if bgr:
            img = img[:, :, ::-1]
    else:
        raise CameraError(f"{what}: expected an (H, W), (H, W, 3) or (H, W, 4) image, got shape {img.shape}")
    if img.shape[0] == 0 or img.shape[1] == 0:
        raise CameraError(f"{what}: empty image")
    return np.ascontiguousarray(img)


class CameraSource(ABC):
    """The interface shared by every source. Not thread-safe: one reader at a time."""

    name: str = "camera"

    def __init__(self) -> None:
        self._opened = False
        self._seq = 0
        self._last_t = -math.inf
        # Frames skipped because they could not be decoded (CorruptFrame), over every open.
        self.corrupt_frames = 0
        self.last_corrupt = ""

    # --- lifecycle -------------------------------------------------------------------------
    def open(self) -> CameraSource:
        """Open the source; raises a :class:`CameraOpenError` subclass when it cannot be used.
        Opening an open source does nothing."""
        if not self._opened:
            self._open()
            self._opened = True
            self._seq = 0
            self._last_t = -math.inf
        return self

    def close(self) -> None:
        """Release the device or file; safe to call twice."""
        if self._opened:
            self._opened = False
            self._close()

    @property
    def is_open(self) -> bool:
        return self._opened

    def __enter__(self) -> CameraSource:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- frames ----------------------------------------------------------------------------
    def read(self) -> Frame:
        """The next frame. Blocks until it is available; raises :class:`EndOfStream` after the
        last frame of a finite source and :class:`CameraLost` when a live source stops."""
        if not self._opened:
            raise CameraError(f"{self.name}: read() on a source that is not open")
        while True:
            try:
                image, t_s = self._read()
                break
            except CorruptFrame as exc:  # skipped and counted; the next frame follows
                self.corrupt_frames += 1
                self.last_corrupt = str(exc)
                log.warning("%s: frame skipped: %s", self.name, exc)
        if not t_s > self._last_t:
            raise CameraError(
                f"{self.name}: capture time went backwards or repeated ({t_s} after {self._last_t})"
            )
        self._last_t = t_s
        frame = Frame(image=image, seq=self._seq, t_s=float(t_s), t_host=time.monotonic(), source=self.name)
        self._seq += 1
        return frame

    def __iter__(self) -> Iterator[Frame]:
        """Frames until the end of a finite source (a live source iterates until it fails)."""
        while True:
            try:
                yield self.read()
            except EndOfStream:
                return

    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _read(self) -> tuple[np.ndarray, float]:
        """Return (RGB image, capture time t_s)."""

    @abstractmethod
    def _close(self) -> None: ...

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name}>"


class _Pacer:
    """Optionally replays a recorded timeline in real time (sleeps until each frame's time)."""

    def __init__(self, realtime: bool) -> None:
        self.realtime = realtime
        self._origin: tuple[float, float] | None = None  # (host time, source time) of the first frame

    def reset(self) -> None:
        self._origin = None

    def wait(self, t_s: float) -> None:
        if not self.realtime:
            return
        now = time.monotonic()
        if self._origin is None:
            self._origin = (now, t_s)
            return
        delay = self._origin[0] + (t_s - self._origin[1]) - now
        if delay > 0:
            time.sleep(delay)


# ------------------------------------------------------------------------------------------
class DeviceSource(CameraSource):
    """A live camera through OpenCV ``VideoCapture``: a device index (``0``), a device path
    (``/dev/video0``) or any string OpenCV accepts (e.g. a GStreamer pipeline or an RTSP URL).

    A failed grab is retried until ``lost_timeout_s`` has passed without a frame, then
    :class:`CameraLost` is raised. A driver that blocks inside the grab cannot be interrupted
    from here; :class:`~oibar.camera.latest.LatestFrame` reports that case on the consumer side.
    """

    def __init__(
        self,
        device: int | str,
        *,
        width: int | None = None,
        height: int | None = None,
        fps: float | None = None,
        lost_timeout_s: float = 2.0,
        backend: int | None = None,
    ) -> None:
        super().__init__()
        if isinstance(device, str) and device.strip().isdigit():
            device = int(device)
        self.device = device
        self.width, self.height, self.fps = width, height, fps
        self.lost_timeout_s = float(lost_timeout_s)
        self.backend = backend
        self.name = f"device {device}"
        self._cap: Any = None  # cv2.VideoCapture once open
        self._last_frame_host = 0.0

    def _open(self) -> None:
        cv2 = _cv2()
        dev = self.device
        if isinstance(dev, str) and dev.startswith(("/", "./", "../")) and not os.path.exists(dev):
            raise SourceNotFound(f"camera device {dev} does not exist (is the camera plugged in?)")
        backend = cv2.CAP_ANY if self.backend is None else self.backend
        cap = cv2.VideoCapture(dev, backend)
        if not cap.isOpened():
            cap.release()
            raise CameraOpenError(
                f"cannot open camera {dev!r}: no such device, busy, or no permission "
                f"(check `ls /dev/video*` and that no other program uses it)"
            )
        if self.width:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        if self.height:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        if self.fps:
            cap.set(cv2.CAP_PROP_FPS, self.fps)
        # Keep the driver's own queue short: stale frames are what LatestFrame exists to avoid.
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        self._cap = cap
        self._last_frame_host = time.monotonic()

    def _read(self) -> tuple[np.ndarray, float]:
        while True:
            ok, img = self._cap.read()
            now = time.monotonic()
            if ok and img is not None:
                self._last_frame_host = now
                return to_rgb(img, self.name, bgr=True), now
            silent = now - self._last_frame_host
            if silent >= self.lost_timeout_s:
                raise CameraLost(
                    f"camera {self.device!r} delivered no frame for {silent:.1f} s (disconnected?)",
                    seconds_without_frame=silent,
                )
            time.sleep(min(0.02, self.lost_timeout_s / 10))

    def _close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


# ------------------------------------------------------------------------------------------
class VideoFileSource(CameraSource):
    """A recorded video file, frame by frame. ``t_s`` = frame index / fps (the file's rate, or
    ``rate_hz`` when the file does not give one). ``realtime=True`` paces reads at that rate."""

    def __init__(
        self, path: str | os.PathLike, *, rate_hz: float | None = None, realtime: bool = False
    ) -> None:
        super().__init__()
        self.path = Path(path)
        self.rate_hz = rate_hz
        self.name = f"video {self.path}"
        self._pacer = _Pacer(realtime)
        self._cap: Any = None  # cv2.VideoCapture once open
        self._index = 0
        self._fps = DEFAULT_RATE_HZ

    def _open(self) -> None:
        cv2 = _cv2()
        if not self.path.exists():
            raise SourceNotFound(f"video file {self.path} does not exist")
        if not self.path.is_file():
            raise SourceUnreadable(f"{self.path} is not a file (a folder of frames? use FolderSource)")
        if not os.access(self.path, os.R_OK):
            raise SourceUnreadable(f"video file {self.path} is not readable (permissions)")
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            cap.release()
            raise SourceUnreadable(
                f"cannot decode video file {self.path} (not a video, corrupt, or unsupported codec)"
            )
        file_fps = cap.get(cv2.CAP_PROP_FPS)
        if self.rate_hz:
            self._fps = float(self.rate_hz)
        elif file_fps and math.isfinite(file_fps) and 0 < file_fps < 10000:
            self._fps = float(file_fps)
        else:
            self._fps = DEFAULT_RATE_HZ
        # Decode the first frame now so that an empty or undecodable file fails at open.
        ok, img = cap.read()
        if not ok or img is None:
            cap.release()
            raise EmptySource(f"video file {self.path} holds no decodable frame")
        self._cap = cap
        self._pending = img
        self._index = 0
        self._pacer.reset()

    @property
    def fps(self) -> float:
        return self._fps

    def _read(self) -> tuple[np.ndarray, float]:
        img = self._pending
        if img is None:
            ok, img = self._cap.read()
            if not ok or img is None:
                raise EndOfStream(f"{self.name}: end of file after {self._index} frames")
        self._pending = None
        t_s = self._index / self._fps
        self._index += 1
        self._pacer.wait(t_s)
        return to_rgb(img, self.name, bgr=True), t_s

    def _close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None
        self._pending = None


# ------------------------------------------------------------------------------------------
class CallableSource(CameraSource):
    """A camera backed by a function ``t_s -> image``: the HIL rig's rendered camera.

    ``realtime=True`` (default): frames are requested every ``1 / rate_hz`` seconds of host
    time and ``t_s`` is host seconds since :meth:`open`. ``realtime=False`` (lockstep
    simulation): no sleeping, ``t_s = t0_s + seq / rate_hz``.

    The function returns an RGB (or grey) uint8 image, or ``None`` for "no frame this time"
    (a simulated dropout); after ``lost_timeout_s`` without an image :class:`CameraLost` is
    raised. An exception from the function is reported as :class:`CameraLost` with the cause
    chained. ``bgr=True`` converts images given in OpenCV's order.
    """

    def __init__(
        self,
        render: Callable[[float], np.ndarray | None],
        *,
        rate_hz: float = DEFAULT_RATE_HZ,
        realtime: bool = True,
        t0_s: float = 0.0,
        lost_timeout_s: float = 2.0,
        bgr: bool = False,
        name: str = "simulated camera",
    ) -> None:
        super().__init__()
        if not callable(render):
            raise TypeError("render must be a callable t_s -> image")
        if not rate_hz > 0:
            raise ValueError("rate_hz must be positive")
        self.render = render
        self.rate_hz = float(rate_hz)
        self.realtime = realtime
        self.t0_s = float(t0_s)
        self.lost_timeout_s = float(lost_timeout_s)
        self.bgr = bgr
        self.name = name
        self._start = 0.0
        self._tick = 0
        self._last_frame_host = 0.0

    def _open(self) -> None:
        self._start = time.monotonic()
        self._tick = 0
        self._last_frame_host = self._start

    def _next_time(self) -> float:
        period = 1.0 / self.rate_hz
        if not self.realtime:
            t = self.t0_s + self._tick * period
            self._tick += 1
            return t
        due = self._start + self._tick * period
        now = time.monotonic()
        if due > now:
            time.sleep(due - now)
        else:
            # Behind schedule (slow render): skip the ticks that have already passed.
            self._tick = max(self._tick, int((now - self._start) / period))
        self._tick += 1
        return self.t0_s + (time.monotonic() - self._start)

    def _read(self) -> tuple[np.ndarray, float]:
        while True:
            t_s = self._next_time()
            try:
                img = self.render(t_s)
            except Exception as exc:
                raise CameraLost(f"{self.name} failed at t={t_s:.3f} s: {exc}") from exc
            now = time.monotonic()
            if img is not None:
                self._last_frame_host = now
                return to_rgb(img, self.name, bgr=self.bgr), t_s
            silent = now - self._last_frame_host
            if silent >= self.lost_timeout_s:
                raise CameraLost(
                    f"{self.name} delivered no frame for {silent:.1f} s", seconds_without_frame=silent
                )
            if not self.realtime:
                time.sleep(min(0.01, self.lost_timeout_s / 10))

    def _close(self) -> None:
        pass


# ------------------------------------------------------------------------------------------
def open_source(spec: str | int, *, rate_hz: float = DEFAULT_RATE_HZ, realtime: bool = False) -> CameraSource:
    """A source from a command-line value (not yet opened): an integer or ``/dev/video*`` ->
    :class:`DeviceSource`; an existing folder -> :class:`FolderSource`; an existing file ->
    :class:`VideoFileSource`; ``frames+tcp://HOST:PORT`` -> :class:`~oibar.camera.stream.FrameStreamSource`
    (frames from another process, oibar.camera.stream); anything else with ``://`` ->
    :class:`DeviceSource` (stream URL)."""
    if isinstance(spec, int) or str(spec).strip().isdigit():
        return DeviceSource(int(spec))
    s = str(spec)
    if s.startswith("frames+tcp://"):
        from oibar.camera.stream import FrameStreamSource

        return FrameStreamSource(s)
    if s.startswith("/dev/") or "://" in s:
        return DeviceSource(s)
    p = Path(s)
    if p.is_dir():
        from oibar.camera.folder import FolderSource

        return FolderSource(p, rate_hz=rate_hz, realtime=realtime)
    if p.is_file():
        return VideoFileSource(p, realtime=realtime)
    raise SourceNotFound(
        f"camera {s!r}: no such file or folder (give a device index like 0, /dev/videoN, "
        f"a video file or a folder of frames)"
    )
