"""Camera sources for the navigation loop (issue 8, item 1).

:class:`DeviceSource` (OpenCV camera), :class:`VideoFileSource`, :class:`FolderSource` and
:class:`CallableSource` (the HIL rig's rendered camera) share the :class:`CameraSource`
interface and deliver :class:`Frame` objects (RGB uint8 image, sequence number, capture time
``t_s`` and host time ``t_host``). :class:`LatestFrame` runs one in a background thread and
hands the consumer only the newest frame. Errors derive from :class:`CameraError`.
"""

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
from oibar.camera.folder import FolderSource
from oibar.camera.latest import LatestFrame, LatestFrameStats
from oibar.camera.sources import (
    CallableSource,
    CameraSource,
    DeviceSource,
    Frame,
    VideoFileSource,
    open_source,
)

__all__ = [
    "CallableSource",
    "CameraError",
    "CameraLost",
    "CameraOpenError",
    "CameraSource",
    "CorruptFrame",
    "DeviceSource",
    "EmptySource",
    "EndOfStream",
    "FolderSource",
    "Frame",
    "LatestFrame",
    "LatestFrameStats",
    "SourceNotFound",
    "SourceUnreadable",
    "VideoFileSource",
    "open_source",
]
