"""Torch-free runtime for the exported OibarNet: the host package's (oibar.nav.pose), the one
onnxruntime runtime the navigation daemon and oibar_models share. Re-exported here so training,
export and evaluation keep their imports."""

from oibar.nav.pose import (  # noqa: F401
    METADATA_PREFIX,
    FrameError,
    ModelFileError,
    PoseEstimate,
    PoseEstimator,
    benchmark,
    read_metadata,
    resize_frame,
    to_input,
)

OnnxPoseEstimator = PoseEstimator  # the name export parity, evaluation and the bench use
