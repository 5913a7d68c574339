"""Torch-free runtime for the exported OibarNet: moved to the host package (oibar.nav.pose), the
one onnxruntime runtime the navigation daemon and oibar_models share. Re-exported here so
training, export and evaluation keep their imports."""

from oibar.nav.pose import (  # noqa: F401
    METADATA_PREFIX,
    FrameError,
    ModelFileError,
    OnnxPoseEstimator,
    PoseEstimate,
    PoseEstimator,
    benchmark,
    read_metadata,
    resize_frame,
    to_input,
)
