"""The pose-estimation stage of the navigation daemon: the one onnxruntime runtime for an
exported OibarNet. Torch-free: onnxruntime, onnx (metadata), numpy, Pillow, OpenCV.

``PoseEstimator(model_path).estimate(rgb, t_s=0.0, prior=None)`` -> :class:`PoseEstimate`
(``T_cam_target_m``, ``q_cam_target``, ``R_cam_target``, ``confidence``, ``flags``) opens
whichever kind of model the file is. A malformed frame raises :class:`FrameError` (a
ValueError: the caller skips the frame); a bad model file raises :class:`ModelFileError` at
construction.

The modules, one responsibility each: ``model_file`` (the file, its metadata, its session),
``frames`` (frame checks and network input), ``result`` (PoseEstimate), ``direct`` (the direct
model: the first pass and fallback), ``reader`` (the keypoint network on crop windows),
``fusion`` (PnP with an attitude prior, fit quality, the filter's measurement), ``search``
(which windows are read, the cold search carried across frames), ``roll`` (which turn of a window
shows a rolled fixture upright) and ``keypoint`` (the keypoint
estimator that joins them).
"""

from oibar.nav.pose.direct import PoseEstimator, benchmark
from oibar.nav.pose.frames import FrameError, resize_frame, to_input
from oibar.nav.pose.keypoint import KeypointPoseEstimator
from oibar.nav.pose.model_file import METADATA_PREFIX, ModelFileError, read_metadata
from oibar.nav.pose.result import PoseEstimate

__all__ = [
    "METADATA_PREFIX",
    "FrameError",
    "KeypointPoseEstimator",
    "ModelFileError",
    "PoseEstimate",
    "PoseEstimator",
    "benchmark",
    "read_metadata",
    "resize_frame",
    "to_input",
]
