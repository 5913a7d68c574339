"""Torch-free runtime for the exported OibarNet (onnxruntime + numpy + Pillow): what the host's
navigation loads. The ONNX file carries its own input size, normalisation, camera intrinsics
and output convention as metadata (see export.py), read here.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from PIL import Image

METADATA_PREFIX = "oibar."


class ModelFileError(RuntimeError):
    """The model file is missing or not an OibarNet ONNX export."""


def resize_frame(image: Image.Image | np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
    """Camera frame -> uint8 (H, W, 3) at the network input size. Training (data.py) and
    inference share this one function so they see identical pixels. PIL's bilinear resize
    widens its filter when shrinking (area-like, no aliasing) and maps image corners onto
    corners, so intrinsics scale exactly by the size ratio."""
    im = Image.fromarray(image) if isinstance(image, np.ndarray) else image
    im = im.convert("RGB")
    if im.size != tuple(size_wh):
        im = im.resize(tuple(size_wh), Image.Resampling.BILINEAR)
    return np.asarray(im, dtype=np.uint8)


def to_input(frames_uint8: np.ndarray) -> np.ndarray:
    """(H, W, 3) or (N, H, W, 3) uint8 -> (N, 3, H, W) float32 in [0, 1]; the model normalises."""
    x = np.asarray(frames_uint8)
    if x.ndim == 3:
        x = x[None]
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2), dtype=np.float32) / np.float32(255.0)


def read_metadata(path: str | Path) -> dict:
    import onnx

    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"model file not found: {path} (train and export one: `make train` then `make export`)")
    try:
        m = onnx.load(str(path), load_external_data=False)
    except Exception as exc:  # onnx raises several types for a damaged file
        raise ModelFileError(f"{path}: not a readable ONNX model ({exc})") from exc
    meta = {}
    for p in m.metadata_props:
        if p.key.startswith(METADATA_PREFIX):
            meta[p.key[len(METADATA_PREFIX):]] = json.loads(p.value)
    if "input_size_wh" not in meta:
        raise ModelFileError(f"{path}: no OibarNet metadata (oibar.input_size_wh); not exported by oibar_models.export")
    return meta


class OnnxPoseEstimator:
    """frame (744x480 RGB uint8) -> (T_cam_target m (3,), q_cam_target (w, x, y, z) (4,))."""

    def __init__(self, path: str | Path, threads: int = 2):
        import onnxruntime as ort

        self.path = Path(path)
        self.meta = read_metadata(self.path)
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        self.session = ort.InferenceSession(str(self.path), so, providers=["CPUExecutionProvider"])
        self.size_wh = tuple(self.meta["input_size_wh"])
        self.input_name = self.session.get_inputs()[0].name
        self.output_names = [o.name for o in self.session.get_outputs()]

    def run(self, x: np.ndarray) -> dict[str, np.ndarray]:
        return dict(zip(self.output_names, self.session.run(None, {self.input_name: x})))

    def predict_batch(self, frames_uint8_small: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frames already at the input size, (N, H, W, 3) uint8."""
        out = self.run(to_input(frames_uint8_small))
        return out["position_m"], out["q_cam_target"]

    def __call__(self, frame) -> tuple[np.ndarray, np.ndarray]:
        t, q = self.predict_batch(resize_frame(frame, self.size_wh))
        return t[0], q[0]


def benchmark(path: str | Path, threads: int = 2, seconds: float = 5.0, with_preprocess: bool = True) -> dict:
    """Single-stream latency on this machine: one 744x480 frame at a time, as in flight."""
    est = OnnxPoseEstimator(path, threads)
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 255, (480, 744, 3), dtype=np.uint8)
    small = resize_frame(frame, est.size_wh)
    for _ in range(5):
        est(frame)
    lat = []
    t_end = time.perf_counter() + seconds
    while time.perf_counter() < t_end:
        t0 = time.perf_counter()
        if with_preprocess:
            est(frame)
        else:
            est.predict_batch(small)
        lat.append(time.perf_counter() - t0)
    lat_ms = np.array(lat) * 1e3
    return {"threads": threads, "runs": len(lat), "mean_ms": float(lat_ms.mean()),
            "median_ms": float(np.median(lat_ms)), "p95_ms": float(np.percentile(lat_ms, 95)),
            "inferences_per_s": float(1e3 / lat_ms.mean()), "with_preprocess": with_preprocess}
