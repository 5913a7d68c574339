"""Camera frames as the networks take them: checks, resizing, the input tensor."""

from __future__ import annotations

from typing import Any

import numpy as np
from PIL import Image

ASPECT_TOLERANCE = 0.02  # relative: 744x480 vs 248x160 is exact; a cropped or rotated frame is not
# A frame whose pixels barely vary (lens cap, black, saturated) carries no fixture: no answer.
MIN_FRAME_STD_DN = 2.0


class FrameError(ValueError):
    """A camera frame the estimator cannot use (wrong shape, dtype, aspect, or non-finite)."""


def resize_frame(image: Image.Image | np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
    """Camera frame -> uint8 (H, W, 3) at the network input size. Training (data.py) and
    inference share this one function so they see identical pixels. PIL's bilinear resize
    widens its filter when shrinking (area-like, no aliasing) and maps image corners onto
    corners, so intrinsics scale exactly by the size ratio."""
    im = Image.fromarray(image) if isinstance(image, np.ndarray) else image
    im = im.convert("RGB")
    w, h = size_wh
    if im.size != (w, h):
        im = im.resize((w, h), Image.Resampling.BILINEAR)
    return np.asarray(im, dtype=np.uint8)


def to_input(frames_uint8: np.ndarray) -> np.ndarray:
    """(H, W, 3) or (N, H, W, 3) uint8 -> (N, 3, H, W) float32 in [0, 1]; the model normalises."""
    x = np.asarray(frames_uint8)
    if x.ndim == 3:
        x = x[None]
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2), dtype=np.float32) / np.float32(255.0)


def check_rgb_frame(image: Any, input_wh: tuple[int, int], camera_wh: tuple[int, int]) -> None:
    """FrameError (with the reason) unless ``image`` is an RGB uint8 frame at least the network's
    input size and of the camera's aspect: resizing anything else would distort the geometry."""
    if not isinstance(image, np.ndarray):
        raise FrameError(f"frame must be a numpy array, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3:
        raise FrameError(f"frame must be (H, W, 3) RGB, got shape {image.shape}")
    if image.dtype != np.uint8:
        if np.issubdtype(image.dtype, np.floating) and not np.all(np.isfinite(image)):
            raise FrameError(f"frame has NaN/inf pixels (dtype {image.dtype}); expected uint8 RGB")
        raise FrameError(f"frame dtype must be uint8, got {image.dtype}")
    h, w = image.shape[:2]
    in_w, in_h = input_wh
    if w < in_w or h < in_h:
        raise FrameError(f"frame {w}x{h} is smaller than the network input {in_w}x{in_h}")
    fw, fh = camera_wh
    if abs((w / h) / (fw / fh) - 1.0) > ASPECT_TOLERANCE:
        raise FrameError(
            f"frame {w}x{h} has aspect {w / h:.3f}, the model expects the camera's "
            f"{fw}x{fh} ({fw / fh:.3f}); a crop or rotation would distort the geometry"
        )


def check_time(t_s: float) -> None:
    """FrameError unless the frame's capture time is a finite number."""
    if not np.isfinite(t_s):
        raise FrameError(f"frame time t_s must be finite, got {t_s}")


def is_blank(image: np.ndarray) -> bool:
    """Whether the frame's pixels barely vary (MIN_FRAME_STD_DN, every 4th pixel each way)."""
    return float(image[::4, ::4].std()) < MIN_FRAME_STD_DN
