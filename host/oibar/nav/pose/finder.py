"""The fixture finder: a small network that reads the whole frame, shrunk, and says where the
fixture is (the centre and side of the box around its keypoints). It only places a crop window
for the keypoint network; the keypoint reading and PnP decide whether the fixture is there, so a
wrong place costs one crop, never a pose.

Why: a cold far frame whose direct-model window misses the fixture (1-3 sides off at ~10 m)
read 85-97 crops in the search (about 300 ms against a 100 ms cycle); the finder's window is one
crop (docs/benchmarks.md, "Where a cold frame's crops go"; docs/model_history.md, "The studies
on other looks").

Graph (models/oibar_models/finder.py exports it): input ``image`` (1, 3, H, W) float32 in [0, 1],
the frame resized to ``oibar.input_size_wh``; outputs ``heat`` (1, 1, h, w) logits of "the box
centre is in this cell", ``offset`` (1, 2, h, w) the centre within its cell (0-1, x then y) and
``log_side`` (1, 1, h, w), log(box side in frame px / ``oibar.side_unit_px``). Cells are
``oibar.stride_px`` input pixels wide.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from oibar.nav.pose.model_file import ModelFileError, open_session, read_metadata

OUTPUTS = ("heat", "offset", "log_side")


@dataclass(frozen=True)
class FinderAnswer:
    center_px: tuple[float, float]  # the box centre in frame pixels
    side_px: float  # the box's larger side in frame pixels (the keypoints' extent, no margin)
    score: float  # the winning cell's probability, 0-1


class FixtureFinder:
    """frame (RGB uint8, the frame size the finder was trained at) -> FinderAnswer."""

    def __init__(self, path: str | Path, threads: int = 2, allow_spinning: bool = False):
        self.path = Path(path)
        self.meta: dict[str, Any] = read_metadata(self.path)
        if self.meta.get("kind") != "finder":
            raise ModelFileError(f"{self.path}: not a fixture finder (oibar.kind {self.meta.get('kind')!r})")
        try:
            self.input_wh = tuple(int(v) for v in self.meta["input_size_wh"])
            self.frame_wh = tuple(int(v) for v in self.meta["frame_size_wh"])
            self.stride_px = int(self.meta["stride_px"])
            self.side_unit_px = float(self.meta["side_unit_px"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{self.path}: finder metadata incomplete ({exc!r})") from exc
        self.session = open_session(self.path, threads, allow_spinning)
        outs = [o.name for o in self.session.get_outputs()]
        if outs != list(OUTPUTS):
            raise ModelFileError(f"{self.path}: outputs {outs}, expected {list(OUTPUTS)}")
        self.input_name = self.session.get_inputs()[0].name

    def prepare(self, image_rgb_uint8: np.ndarray) -> np.ndarray:
        h, w = image_rgb_uint8.shape[:2]
        if (w, h) != self.frame_wh:
            raise ValueError(f"the finder reads {self.frame_wh[0]}x{self.frame_wh[1]} frames, got {w}x{h}")
        small = cv2.resize(image_rgb_uint8, self.input_wh, interpolation=cv2.INTER_AREA)
        return (small.astype(np.float32) * (1.0 / 255.0)).transpose(2, 0, 1)[None]

    def find(self, image_rgb_uint8: np.ndarray) -> FinderAnswer:
        heat, offset, log_side = self.session.run(None, {self.input_name: self.prepare(image_rgb_uint8)})
        return decode(
            heat[0, 0],
            offset[0],
            log_side[0, 0],
            self.stride_px,
            self.input_wh,
            self.frame_wh,
            self.side_unit_px,
        )


def decode(
    heat: np.ndarray,
    offset: np.ndarray,
    log_side: np.ndarray,
    stride_px: int,
    input_wh: tuple[int, ...],
    frame_wh: tuple[int, ...],
    side_unit_px: float,
) -> FinderAnswer:
    """The best cell's box in frame pixels (the trainer's labels, inverted)."""
    i, j = np.unravel_index(int(np.argmax(heat)), heat.shape)
    sx, sy = input_wh[0] / frame_wh[0], input_wh[1] / frame_wh[1]
    u = (j + float(offset[0, i, j])) * stride_px / sx
    v = (i + float(offset[1, i, j])) * stride_px / sy
    side = side_unit_px * float(np.exp(np.clip(log_side[i, j], -6.0, 6.0)))
    score = float(1.0 / (1.0 + np.exp(-float(heat[i, j]))))
    return FinderAnswer((u, v), side, score)
