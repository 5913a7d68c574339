"""Run a camera source in a background thread and keep only the newest frame.

The 10 Hz loop calls :meth:`LatestFrame.get` when it is ready for a frame and receives the
newest one captured since the previous call; frames that were overwritten before it asked are
counted in :attr:`LatestFrame.dropped`, never queued, so a slow cycle cannot make the next
cycles work on stale images. A frame is never returned twice and never older than one already
returned (sequence numbers strictly increase).

``get`` raises :class:`CameraLost` when no new frame arrives within ``lost_timeout_s`` (also
when the source hangs inside its own read, which the thread cannot interrupt), the source's own
error when the reader thread failed, and :class:`EndOfStream` after the last frame of a finite
source.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

from oibar.camera.errors import CameraError, CameraLost, EndOfStream
from oibar.camera.sources import CameraSource, Frame

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LatestFrameStats:
    captured: int  # frames read from the source
    delivered: int  # frames returned by get()/poll()
    dropped: int  # frames replaced by a newer one before anyone took them


class LatestFrame:
    """``with LatestFrame(source, lost_timeout_s=1.0) as cam: frame = cam.get()``.

    :meth:`start` opens the source in the calling thread (so an open error is raised there)
    and starts the reader; :meth:`stop` stops it, joins it and closes the source.
    """

    def __init__(
        self, source: CameraSource, *, lost_timeout_s: float = 1.0, join_timeout_s: float = 2.0
    ) -> None:
        if not lost_timeout_s > 0:
            raise ValueError("lost_timeout_s must be positive")
        self.source = source
        self.lost_timeout_s = float(lost_timeout_s)
        self.join_timeout_s = float(join_timeout_s)
        self._cond = threading.Condition()
        self._latest: Frame | None = None  # newest frame not yet returned
        self._last_seq = -1  # seq of the last frame returned
        self._error: BaseException | None = None
        self._ended = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._captured = 0
        self._delivered = 0
        self._dropped = 0
        self._last_capture_host = 0.0

    # --- lifecycle -------------------------------------------------------------------------
    def start(self) -> LatestFrame:
        if self._thread is not None:
            raise CameraError(f"{self.source.name}: LatestFrame already started")
        self.source.open()
        self._stop.clear()
        self._last_capture_host = time.monotonic()
        self._thread = threading.Thread(target=self._run, name=f"camera-{self.source.name}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> bool:
        """Stop the reader and close the source. Returns False when the reader is stuck inside
        the source's read (it is a daemon thread; the source is then left open rather than
        closed under it, and :attr:`running` stays True until the thread leaves read(); call
        stop() again then). Safe to call twice."""
        thread = self._thread
        if thread is None:
            return True
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        thread.join(self.join_timeout_s)
        if thread.is_alive():
            # Kept: ``running`` stays True until it leaves read(), so an owner can wait for it
            # instead of opening the source again under it (two readers on one device).
            log.warning(
                "%s: reader thread still blocked in read() after %.1f s; leaving it",
                self.source.name,
                self.join_timeout_s,
            )
            return False
        self._thread = None
        self.source.close()
        return True

    def __enter__(self) -> LatestFrame:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # --- reader thread ---------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                frame = self.source.read()
            except EndOfStream:
                with self._cond:
                    self._ended = True
                    self._cond.notify_all()
                return
            except BaseException as exc:  # reported to the consumer by get()
                with self._cond:
                    self._error = exc
                    self._cond.notify_all()
                return
            with self._cond:
                if self._latest is not None:
                    self._dropped += 1
                self._latest = frame
                self._captured += 1
                self._last_capture_host = time.monotonic()
                self._cond.notify_all()

    # --- consumer --------------------------------------------------------------------------
    def _take(self) -> Frame | None:
        frame = self._latest
        if frame is None:
            return None
        self._latest = None
        if frame.seq <= self._last_seq:  # cannot happen with a well-behaved source; be strict
            return None
        self._last_seq = frame.seq
        self._delivered += 1
        return frame

    def _raise_if_done(self) -> None:
        if self._error is not None:
            err = self._error
            if isinstance(err, CameraError):
                raise err
            raise CameraLost(f"{self.source.name} failed: {err!r}") from err
        if self._ended:
            raise EndOfStream(f"{self.source.name}: no more frames")

    def poll(self) -> Frame | None:
        """The newest frame not yet returned, or None; never blocks. Raises like :meth:`get`
        once the source has failed or ended and no frame is left."""
        with self._cond:
            frame = self._take()
            if frame is None:
                self._raise_if_done()
            return frame

    def get(self, timeout_s: float | None = None) -> Frame:
        """The newest frame not yet returned, waiting for one if needed. Raises
        :class:`CameraLost` when none arrives within ``timeout_s`` (default: the source has
        been silent for ``lost_timeout_s``)."""
        if self._thread is None and self._latest is None and not (self._error or self._ended):
            raise CameraError(f"{self.source.name}: LatestFrame not started")
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while True:
                frame = self._take()
                if frame is not None:
                    return frame
                self._raise_if_done()
                now = time.monotonic()
                if deadline is not None:
                    remaining = deadline - now
                    silent = now - self._last_capture_host
                else:
                    silent = now - self._last_capture_host
                    remaining = self.lost_timeout_s - silent
                if remaining <= 0:
                    raise CameraLost(
                        f"{self.source.name}: no new frame for {silent:.2f} s", seconds_without_frame=silent
                    )
                if self._stop.is_set():
                    raise CameraError(f"{self.source.name}: LatestFrame stopped")
                self._cond.wait(remaining)

    @property
    def dropped(self) -> int:
        """Frames captured but replaced by a newer one before the consumer took them."""
        with self._cond:
            return self._dropped

    @property
    def stats(self) -> LatestFrameStats:
        with self._cond:
            return LatestFrameStats(self._captured, self._delivered, self._dropped)

    @property
    def seconds_since_last_capture(self) -> float:
        with self._cond:
            return time.monotonic() - self._last_capture_host
