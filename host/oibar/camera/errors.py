"""Exceptions raised by the camera sources.

Everything derives from :class:`CameraError`, so a caller that only wants "no usable frame"
catches one type, while the navigation loop can tell the cases apart: a source that could not
be opened (a configuration problem, reported at start), a finite source that has run out
(:class:`EndOfStream`, the normal end of a replay) and a camera that stopped delivering while
running (:class:`CameraLost`: hold, then abort).
"""

from __future__ import annotations


class CameraError(Exception):
    """Base class of every camera failure."""


class CameraOpenError(CameraError):
    """A source could not be opened (no such device, device busy, unsupported format...)."""


class SourceNotFound(CameraOpenError, FileNotFoundError):
    """The video file, the frame folder or the timestamp table does not exist."""


class SourceUnreadable(CameraOpenError):
    """The file exists but cannot be decoded (not a video, corrupt, unsupported codec), or a
    frame or timestamp table inside a folder is unreadable or inconsistent."""


class EmptySource(CameraOpenError):
    """The folder holds no image file, or the video file holds no frame."""


class CorruptFrame(CameraError):
    """One frame could not be decoded (a truncated or corrupt image file). The source skips it
    and goes on with the next: :meth:`~oibar.camera.sources.CameraSource.read` never raises it;
    it counts it in ``corrupt_frames``."""


class EndOfStream(CameraError):
    """A finite source (video file, frame folder) has delivered its last frame."""


class CameraLost(CameraError):
    """The source stopped delivering frames for longer than its timeout (camera unplugged,
    driver stuck, simulated camera stalled), or it failed while running."""

    def __init__(self, message: str, seconds_without_frame: float | None = None) -> None:
        self.seconds_without_frame = seconds_without_frame
        super().__init__(message)
