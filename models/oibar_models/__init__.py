"""OibarNet: the direct (end-to-end) CNN that turns a camera frame into the pose of the berthing
fixture, T_cam_target (m) and q_cam_target (w, x, y, z), as labelled by oibar_hil.dataset.

Library modules (SPNv2 layout): config, data, nets, loss, engine, metrics, export, evaluate;
thin entry points: `python -m oibar_models.train|export|evaluate --config CONFIG.yaml`.
`infer` is the torch-free runtime (onnxruntime) for the host.
"""

__version__ = "0.1.0"
