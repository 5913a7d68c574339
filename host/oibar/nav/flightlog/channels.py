"""What a flight log holds: its channels (topic -> schema, the table in oibar.nav.flightlog), the
frame ids of its transform tree and how often the writer repeats and flushes."""

from __future__ import annotations

# topic -> schema name. The order is the order of the table in oibar.nav.flightlog.
CHANNELS: dict[str, str] = {
    "/camera/image": "foxglove.RawImage",
    "/camera/calibration": "foxglove.CameraCalibration",
    "/nav/pose": "foxglove.PoseInFrame",
    "/tf": "foxglove.FrameTransform",
    "/nav/fixture": "foxglove.SceneUpdate",
    "/nav/estimate": "oibar.log.PoseEstimate",
    "/nav/filter": "oibar.log.FilterState",
    "/nav/cycle": "oibar.log.Cycle",
    "/guidance/command": "oibar.log.GuidanceCommand",
    "/link/nav_update": "oibar.v1.NavUpdate",
    "/link/telemetry": "oibar.v1.Telemetry",
    "/link/events": "oibar.v1.Event",
    "/run/info": "oibar.log.RunInfo",
    "/run/summary": "oibar.log.RunSummary",  # JSON (a JSON Schema of that title)
}
JSON_CHANNELS = {"/run/summary"}
# Frame ids of the transform tree (Foxglove's camera convention is OpenCV's: x right, y down, z ahead).
FRAME_CAMERA = "camera"
FRAME_FIXTURE = "fixture"  # the estimate of this frame
FRAME_FIXTURE_FILTER = "fixture_filter"  # the filter's state
STATIC_EVERY_S = 1.0  # run info, calibration, outline again: a viewer that joins late sees them
FLUSH_EVERY_S = 1.0  # the file is at most this much behind the flight: what a kill or power loss costs
QUEUE_CYCLES = 30  # cycles the writer may fall behind (3 s at 10 Hz, ~30 MB of frames) before it drops
