"""The flight log: every navigation cycle recorded as MCAP through the Foxglove SDK, and the same
channels served live to the Foxglove app (``oibar nav --live``, oibar.nav.live).

Channels (``CHANNELS``; all protobuf but the summary, JSON). Foxglove's well-known schemas where one fits,
so the app draws them as they are; the rest are ours (oibar.nav.logschema) or the MCU link's own
messages (proto/oibar.proto):

==================== ========================== ==================================================
topic                schema                     what
==================== ========================== ==================================================
/camera/image        foxglove.RawImage          every frame the navigator read, rgb8, lossless
/camera/calibration  foxglove.CameraCalibration the camera's intrinsics (for the image overlay)
/nav/pose            foxglove.PoseInFrame       the estimator's pose of the fixture, camera frame
/tf                  foxglove.FrameTransform    camera -> ``fixture`` (estimate), camera ->
                                                ``fixture_filter`` (the filter's pose)
/nav/fixture         foxglove.SceneUpdate       the fixture's outline in both frames: drawn over
                                                the image and in the 3D view
/nav/estimate        oibar.log.PoseEstimate     the estimate in full: confidence, flags, latency
/nav/filter          oibar.log.FilterState      the filter's state with its 1-sigma uncertainties
/nav/cycle           oibar.log.Cycle            times, frame, odometry, hold reason, link, timings
/guidance/command    oibar.log.GuidanceCommand  phase, velocity setpoints, mechanism request
/link/nav_update     oibar.v1.NavUpdate         the navigation update sent to the MCU
/link/telemetry      oibar.v1.Telemetry         each new telemetry packet from the MCU
/link/events         oibar.v1.Event             the MCU's events
/run/info            oibar.log.RunInfo          versions, model and its SHA-256, onnxruntime
                                                threads, intrinsics, camera, rate
/run/summary         oibar.log.RunSummary, JSON the run's summary, outcome and counters (at the end)
==================== ========================== ==================================================

Every message of a cycle carries the cycle's log time (wall clock at its start), which is how
``oibar replay`` (oibar.nav.replay) pairs a frame with its cycle. Frames are the navigator's own
pixels, so replay feeds it exactly what it read.

The cycle hands its messages to a writer thread (a bounded queue): a slow or full disk never holds
up navigation. A full disk or an unwritable log never stops it either: the MCAP writer turns
itself off, counts the messages lost from then on (``messages_lost``, as it counts those the full
queue dropped) and reports the error once (``error``); the daemon shows it in its status line and
summary. A live view keeps running without the file.

The modules, one responsibility each: ``channels`` (the topics, their schemas, the frame ids and
the writer's pace), ``errors`` (FlightLogError), ``messages`` (the ``oibar.log`` messages of a
cycle), ``wellknown`` (Foxglove's well-known messages: the fixture outline, poses, transforms,
images), ``runinfo`` (what the run is: versions, model, intrinsics), ``guarded_file`` (the file
that survives a full disk), ``writer`` (:class:`FlightLog`, its thread and queue) and ``reader``
(reading a log back).
"""

from oibar.nav.flightlog.channels import CHANNELS
from oibar.nav.flightlog.errors import FlightLogError
from oibar.nav.flightlog.messages import estimate_message, filter_message, odometry_message
from oibar.nav.flightlog.reader import LogInventory, LogMessage, inspect_log, read_messages, read_summary
from oibar.nav.flightlog.runinfo import camera_intrinsics, ort_threads, run_info
from oibar.nav.flightlog.wellknown import fixture_outline_entities
from oibar.nav.flightlog.writer import CycleInputs, FlightLog

__all__ = [
    "CHANNELS",
    "CycleInputs",
    "FlightLog",
    "FlightLogError",
    "LogInventory",
    "LogMessage",
    "camera_intrinsics",
    "estimate_message",
    "filter_message",
    "fixture_outline_entities",
    "inspect_log",
    "odometry_message",
    "ort_threads",
    "read_messages",
    "read_summary",
    "run_info",
]
