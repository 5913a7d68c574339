"""The pose-estimation stage of the navigation daemon: the one onnxruntime runtime for an
exported OibarNet (issue 8, item 2). Torch-free: onnxruntime, onnx (metadata), numpy, Pillow.

The ONNX file (oibar_models.export) carries its own input size, normalisation, camera
intrinsics and output convention as ``oibar.*`` metadata; everything here is read from it, so
any export works without code changes. Graph: input ``image`` (N, 3, H, W) float32 in [0, 1];
outputs ``position_m`` (N, 3) = T_cam_target (camera frame, OpenCV axes), ``q_cam_target``
(N, 4) (w, x, y, z; w >= 0), ``R_cam_target`` (N, 3, 3) and ``rot6d`` (N, 6), the raw 6D
before Gram-Schmidt.

:class:`PoseEstimator` is what the daemon holds: ``estimate(frame, t_s) -> PoseEstimate`` with a
per-frame plausibility ``confidence``. A malformed frame raises :class:`FrameError` (a
ValueError: the caller skips the frame); a bad model file raises :class:`ModelFileError` at
construction. ``OnnxPoseEstimator`` is the older name, kept for oibar_models.
"""

from __future__ import annotations

import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from oibar.geometry.camera import project_target_points as project
from oibar.geometry.docking import tilt_scaled
from oibar.geometry.rotations import matrix_to_quat, mean_quat, quat_to_matrix, rotation_angle_deg
from oibar.nav.fit_history import FitHistory
from oibar.nav.keypoints import (
    MIRROR_ATT,
    CropWindow,
    HeadGainModel,
    KeypointErrorModel,
    PnpResult,
    PriorErrorModel,
    attitude_from_crop,
    cut,
    map_pose,
    mirror_crop_px,
    mirror_permutation,
    mirror_symmetric_attitude,
    refine_corners_px,
    solve_pnp,
    window_around,
)

METADATA_PREFIX = "oibar."
REQUIRED_OUTPUTS = ("position_m", "q_cam_target", "R_cam_target")

# Camera-distance envelope used when the model's metadata does not state its training range
# (exports up to model version 0.1.0 do not): the synthetic campaign spans 0.4-10.4 m, widened
# so only physically absurd answers are flagged.
DEFAULT_RANGE_LIMITS_M = (0.2, 20.0)
# Raw-6D orthonormality defect at which confidence falls to exp(-1/2) = 0.61: about 5x the
# defect's 99th percentile on a training sequence (0.004 on seq02, development model), so only
# answers clearly unlike anything seen in training are down-weighted. Its link to the actual
# error is weak and inconsistent (docs/navigation.md), hence the mild setting.
DEFAULT_DEFECT_SCALE = 0.02
# Multipliers applied to the confidence when an answer is implausible but not impossible.
OUT_OF_RANGE_FACTOR = 0.2  # camera distance outside the training envelope
OUT_OF_VIEW_FACTOR = 0.2  # target origin projects outside the image: the net cannot have seen it
ASPECT_TOLERANCE = 0.02  # relative: 744x480 vs 248x160 is exact; a cropped or rotated frame is not


class ModelFileError(RuntimeError):
    """The model file is missing, damaged, or not an OibarNet ONNX export."""


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


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The ``oibar.*`` metadata of an export, JSON-decoded; ModelFileError naming the file if it
    is missing, unreadable, or carries none."""
    import onnx

    path = Path(path)
    if not path.is_file():
        raise ModelFileError(
            f"model file not found: {path} (train and export one: `make train` then `make export`)"
        )
    try:
        m = onnx.load(str(path), load_external_data=False)
    except Exception as exc:  # onnx/protobuf raise several types for a damaged file
        raise ModelFileError(f"{path}: not a readable ONNX model ({type(exc).__name__}: {exc})") from exc
    if len(m.graph.node) == 0:  # protobuf parses some garbage (and empty files) as an empty model
        raise ModelFileError(f"{path}: not a readable ONNX model (no graph nodes; truncated or not ONNX)")
    meta = {}
    for p in m.metadata_props:
        if p.key.startswith(METADATA_PREFIX):
            try:
                meta[p.key[len(METADATA_PREFIX) :]] = json.loads(p.value)
            except json.JSONDecodeError as exc:
                raise ModelFileError(f"{path}: metadata {p.key!r} is not valid JSON ({exc})") from exc
    if "input_size_wh" not in meta:
        raise ModelFileError(
            f"{path}: no OibarNet metadata (oibar.input_size_wh); not exported by oibar_models.export"
        )
    size = meta["input_size_wh"]
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
        raise ModelFileError(f"{path}: oibar.input_size_wh must be [width, height] in pixels, got {size!r}")
    return meta


@dataclass
class PoseEstimate:
    """One frame's answer. T/q/R: the target's pose in the camera frame (p_C = R p_t + T)."""

    T_cam_target_m: np.ndarray  # (3,) metres, camera frame (OpenCV axes)
    q_cam_target: np.ndarray  # (4,) (w, x, y, z), w >= 0
    R_cam_target: np.ndarray  # (3, 3)
    t_s: float  # capture time of the frame, as given by the caller
    latency_ms: float  # resize + inference, this call
    confidence: float  # 0..1 plausibility (not a calibrated probability)
    camera_range_m: float  # ||T_cam_target||: camera-to-fixture distance
    ortho_defect: float  # ||rot6d - its Gram-Schmidt projection||; 0 for a valid rotation
    flags: tuple[str, ...] = field(default_factory=tuple)  # why confidence was lowered, if it was
    # What a filter should fuse, when it differs from the pose above: the same keypoints solved
    # without the attitude prior. The prior (the crop's attitude head) makes each frame's pose
    # better on its own but pulls the tilt toward "aligned" on every frame alike, an error a
    # filter cannot average away; PnP alone is noisier and unbiased (docs/model_history.md).
    T_meas_cam_target_m: np.ndarray | None = None
    R_meas_cam_target: np.ndarray | None = None

    @property
    def finite(self) -> bool:
        return bool(np.all(np.isfinite(self.T_cam_target_m)) and np.all(np.isfinite(self.R_cam_target)))

    def measurement(self) -> tuple[np.ndarray, np.ndarray]:
        """(T_cam_target_m, R_cam_target) for a filter: the prior-free pose when there is one,
        else the pose itself."""
        if self.T_meas_cam_target_m is not None and self.R_meas_cam_target is not None:
            return self.T_meas_cam_target_m, self.R_meas_cam_target
        return self.T_cam_target_m, self.R_cam_target


def _range_limits(meta: dict[str, Any], given: tuple[float, float] | None) -> tuple[float, float]:
    """The camera-distance envelope: as given, else the export's training range, else the default."""
    limits = given if given is not None else tuple(meta.get("train_range_m", DEFAULT_RANGE_LIMITS_M))
    lo, hi = (float(v) for v in limits)
    if not 0 <= lo < hi:
        raise ValueError(f"range_limits_m must be (low, high) with 0 <= low < high, got {limits}")
    return lo, hi


def _session(path: Path, threads: int, allow_spinning: bool) -> Any:
    import onnxruntime as ort

    so = ort.SessionOptions()
    # A small shared CPU: a fixed thread count, no inter-op parallelism (the graph is a chain).
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL  # fuse conv+bn+relu etc.
    # One frame shape for the whole flight: the arena and the memory pattern are planned once
    # (at warm-up) and reused, so steady-state runs allocate nothing.
    so.enable_cpu_mem_arena = True
    so.enable_mem_pattern = True
    # Spinning workers burn a core between frames; at 10 Hz that core belongs to the link and camera.
    so.add_session_config_entry("session.intra_op.allow_spinning", "1" if allow_spinning else "0")
    so.log_severity_level = 3  # errors only: graph-optimiser notes are not the operator's business
    try:
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own Fail/InvalidGraph/... types
        raise ModelFileError(f"{path}: onnxruntime cannot load it ({type(exc).__name__}: {exc})") from exc


class PoseEstimator:
    """frame (RGB uint8, the camera's aspect) -> :class:`PoseEstimate`.

    ``PoseEstimator(path)`` opens whichever kind of OibarNet the file is: a direct model (this
    class) or a keypoint model (:class:`KeypointPoseEstimator`, chosen from the file's
    ``oibar.kind`` metadata), so callers never need to know which.

    Also offers the batch interface oibar_models uses: ``run`` (raw outputs for a prepared
    input), ``predict_batch`` (frames already at the input size) and ``__call__`` (one frame ->
    (T, q))."""

    def __new__(cls, path: str | Path | None = None, *args: Any, **kwargs: Any) -> PoseEstimator:
        if cls is PoseEstimator and path is not None and read_metadata(path).get("kind") == "keypoints":
            cls = KeypointPoseEstimator
        return super().__new__(cls)

    def __init__(
        self,
        path: str | Path,
        threads: int = 2,
        warmup_runs: int = 3,
        range_limits_m: tuple[float, float] | None = None,
        defect_scale: float = DEFAULT_DEFECT_SCALE,
        allow_spinning: bool = False,
    ):
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        if warmup_runs < 0:
            raise ValueError(f"warmup_runs must be >= 0, got {warmup_runs}")
        if defect_scale <= 0:
            raise ValueError(f"defect_scale must be > 0, got {defect_scale}")
        self.path = Path(path)
        self.meta = read_metadata(self.path)
        self.session = _session(self.path, threads, allow_spinning)
        self.size_wh = tuple(self.meta["input_size_wh"])
        inputs = self.session.get_inputs()
        if len(inputs) != 1 or len(inputs[0].shape) != 4:
            raise ModelFileError(
                f"{self.path}: expected one 4-D image input, got {[(i.name, i.shape) for i in inputs]}"
            )
        self.input_name = inputs[0].name
        self.output_names = [o.name for o in self.session.get_outputs()]
        missing = [n for n in REQUIRED_OUTPUTS if n not in self.output_names]
        if missing:
            raise ModelFileError(
                f"{self.path}: outputs {missing} missing (has {self.output_names}); not an OibarNet export"
            )
        cam = self.meta.get("camera") or {}
        # Frames must have the camera's aspect: resizing anything else would distort the geometry.
        self.frame_wh = (int(cam["width_px"]), int(cam["height_px"])) if "width_px" in cam else self.size_wh
        self.K_frame = np.array(cam["K_frame"], float) if "K_frame" in cam else None
        self.range_limits_m = _range_limits(self.meta, range_limits_m)
        self.defect_scale = float(defect_scale)
        w, h = self.size_wh
        zero = np.zeros((1, 3, h, w), np.float32)
        for _ in range(warmup_runs):  # first runs plan memory and pick kernels: keep them out of flight
            self.run(zero)

    # ------------------------------------------------------------------ batch interface
    def run(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Prepared input (N, 3, H, W) float32 in [0, 1] -> every output by name."""
        return dict(zip(self.output_names, self.session.run(None, {self.input_name: x}), strict=True))

    def predict_batch(self, frames_uint8_small: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frames already at the input size, (N, H, W, 3) uint8 -> (T (N, 3), q (N, 4))."""
        out = self.run(to_input(frames_uint8_small))
        return out["position_m"], out["q_cam_target"]

    def __call__(self, frame: Image.Image | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t, q = self.predict_batch(resize_frame(frame, self.size_wh))
        return t[0], q[0]

    # ------------------------------------------------------------------ the daemon's interface
    def check_frame(self, image: Any) -> None:
        """FrameError (with the reason) unless ``image`` is an RGB uint8 frame the net can use."""
        if not isinstance(image, np.ndarray):
            raise FrameError(f"frame must be a numpy array, got {type(image).__name__}")
        if image.ndim != 3 or image.shape[2] != 3:
            raise FrameError(f"frame must be (H, W, 3) RGB, got shape {image.shape}")
        if image.dtype != np.uint8:
            if np.issubdtype(image.dtype, np.floating) and not np.all(np.isfinite(image)):
                raise FrameError(f"frame has NaN/inf pixels (dtype {image.dtype}); expected uint8 RGB")
            raise FrameError(f"frame dtype must be uint8, got {image.dtype}")
        h, w = image.shape[:2]
        in_w, in_h = self.size_wh
        if w < in_w or h < in_h:
            raise FrameError(f"frame {w}x{h} is smaller than the network input {in_w}x{in_h}")
        fw, fh = self.frame_wh
        if abs((w / h) / (fw / fh) - 1.0) > ASPECT_TOLERANCE:
            raise FrameError(
                f"frame {w}x{h} has aspect {w / h:.3f}, the model expects the camera's "
                f"{fw}x{fh} ({fw / fh:.3f}); a crop or rotation would distort the geometry"
            )

    # Whether estimate() uses a predicted pose (the navigation filter's) to look in the right place.
    uses_prior = False

    def forget(self) -> None:
        """Drop what earlier frames left (a new sequence, or frames to be judged each on its
        own). A direct model keeps nothing."""

    def estimate(
        self,
        image_rgb_uint8: np.ndarray,
        t_s: float = 0.0,
        prior: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> PoseEstimate:
        """One frame -> pose. `prior` (R_cam_target, T_cam_target_m), the pose predicted for this
        frame, is ignored by a direct model: it sees the whole frame anyway."""
        if not np.isfinite(t_s):
            raise FrameError(f"frame time t_s must be finite, got {t_s}")
        self.check_frame(image_rgb_uint8)
        t0 = time.perf_counter()
        out = self.run(to_input(resize_frame(image_rgb_uint8, self.size_wh)))
        latency_ms = (time.perf_counter() - t0) * 1e3
        T = out["position_m"][0].astype(float)
        R = out["R_cam_target"][0].astype(float)
        q = out["q_cam_target"][0].astype(float)
        r6 = out["rot6d"][0].astype(float) if "rot6d" in out else None
        conf, rng_m, defect, flags = self.plausibility(T, R, r6)
        return PoseEstimate(
            T_cam_target_m=T,
            q_cam_target=q,
            R_cam_target=R,
            t_s=float(t_s),
            latency_ms=latency_ms,
            confidence=conf,
            camera_range_m=rng_m,
            ortho_defect=defect,
            flags=flags,
        )

    def plausibility(
        self, T: np.ndarray, R: np.ndarray, rot6d: np.ndarray | None
    ) -> tuple[float, float, float, tuple[str, ...]]:
        """(confidence 0..1, camera range m, 6D defect, flags). The net has no uncertainty head;
        these are cheap consistency checks on its own outputs:
          - the raw 6D should already be two orthonormal columns (the loss trains it towards the
            true ones); its distance to the Gram-Schmidt result grows on frames unlike training;
          - z <= 0 (target behind the camera) or non-finite numbers are impossible: confidence 0;
          - a distance outside the training envelope, or a target origin that projects outside
            the image, cannot come from what the net saw: confidence scaled down."""
        if not (
            np.all(np.isfinite(T))
            and np.all(np.isfinite(R))
            and (rot6d is None or np.all(np.isfinite(rot6d)))
        ):
            return 0.0, float("nan"), float("nan"), ("non_finite",)
        rng_m = float(np.linalg.norm(T))
        defect = 0.0
        if rot6d is not None:
            defect = float(np.linalg.norm(rot6d - np.concatenate([R[:, 0], R[:, 1]])))
        conf = float(np.exp(-0.5 * (defect / self.defect_scale) ** 2))
        flags = []
        if defect > self.defect_scale:
            flags.append("ortho_defect")
        if T[2] <= 0:
            return 0.0, rng_m, defect, tuple(flags + ["behind_camera"])
        lo, hi = self.range_limits_m
        if not lo <= rng_m <= hi:
            conf *= OUT_OF_RANGE_FACTOR
            flags.append("out_of_range")
        if self.K_frame is not None:
            u, v, w = self.K_frame @ T
            fw, fh = self.frame_wh
            if not (0 <= u / w <= fw and 0 <= v / w <= fh):
                conf *= OUT_OF_VIEW_FACTOR
                flags.append("out_of_view")
        return float(np.clip(conf, 0.0, 1.0)), rng_m, defect, tuple(flags)


OnnxPoseEstimator = PoseEstimator  # the name oibar_models (export parity, evaluation) uses


# ----------------------------------------------------------------------------- keypoints + PnP
# A frame whose pixels barely vary (lens cap, black, saturated) carries no fixture: no answer.
MIN_FRAME_STD_DN = 2.0
# The PnP answer and the direct model's must agree this well (position difference / range,
# attitude difference); the direct model's own error is ~10-15 % on unseen scenes, so only a
# gross disagreement (a PnP on the wrong points) is flagged.
DISAGREE_POS_FRACTION = 0.5
DISAGREE_ATT_DEG = 20.0
# Reprojection RMS (crop pixels) at which confidence falls to exp(-1/2): a few times the
# keypoints' typical error on validation scenes.
REPROJ_SCALE_CROP_PX = 3.0
FALLBACK_FACTOR = 0.3  # confidence of the direct model's answer when PnP has none
# The refining pass's sub-pixel corners (``oibar.corner_refine_side_px``): the keypoints refined
# (the fixture's sharp corners: the rim's and the connector's; with the connector's too, 0.15.0's
# validation attitude at 0-1 / 1-2 m is 0.53 / 0.48 deg, against 0.62 / 0.57 with the rim's alone
# and 0.65 / 0.66 with none: every 8th frame), cornerSubPix's half window per pixel of the
# fixture's extent (the rim band is 6 % of it: 5 px at 0.5 m, where the fixture spans ~270 px),
# its bounds, and how far a corner may move per pixel of half window before the search is taken
# to have found another corner.
CORNER_NAMES = (
    "rim_top_left",
    "rim_top_right",
    "rim_bottom_right",
    "rim_bottom_left",
    "connector_top_left",
    "connector_top_right",
    "connector_bottom_right",
    "connector_bottom_left",
)
CORNER_HALF_WIN_PER_EXTENT = 0.02
CORNER_HALF_WIN_PX = (2, 6)
CORNER_MAX_MOVE_PER_HALF_WIN = 0.4
# Windows tried in turn until the keypoints give a consistent pose: (shift x, shift y) in window
# sides and a size factor, around the direct model's window. The network was trained with the
# fixture up to ~0.25 side off centre and +-25 % in size, so half-side steps leave no gap. Only
# frames where the first window fails pay for the search (~6 % of far validation frames): up to
# 11 passes, about 0.4 s on 2 busy cores. Measured on the validation scenes (every 16th frame):
# mean position error 1.82 % with the first window only, 1.26 % without the diagonal steps,
# 0.95 % with all 11.
SEARCH_STEPS = (
    (0, 0, 1.0),
    (-0.5, 0, 1.0),
    (0.5, 0, 1.0),
    (0, -0.5, 1.0),
    (0, 0.5, 1.0),
    (-0.5, -0.5, 1.0),
    (0.5, -0.5, 1.0),
    (-0.5, 0.5, 1.0),
    (0.5, 0.5, 1.0),
    (0, 0, 0.7),
    (0, 0, 1.4),
)
MIN_INLIERS = 5
# A fit whose keypoints miss their reprojection by more than this (RMS, crop px) is weak: on the
# validation scenes (every 31st frame, 228 fits) every fit within 5 % of the truth had an RMS of
# at most 0.90 crop px (p99 0.84) and every fit off by more than 5 % had at least 1.38 (a shadowed
# scene where the first pass takes a 10 m fixture for a 0.5 m one and the keypoint network draws
# a "fixture" on the station's structure). A weak fit does not stop the search; if no strong fit
# is found it is returned with confidence x FALLBACK_FACTOR and the flag `weak_fit`.
STRONG_FIT_RMS_CROP_PX = 1.2
# When neither the prediction's window nor SEARCH_STEPS give a strong fit, smaller windows inside
# the first pass's one are read in one batch (a half-size 3x3 grid and a quarter-size 5x5 grid,
# steps in the first pass's window sides) and the ZOOM_TRY most keypoint-like (presence, tight
# heat maps) are solved: the first pass can take a far fixture for a near one and put a window
# 5-25x too large around it. Cost: one batch of 34 crops (~0.15-0.25 s on 2 cores), only on
# frames with nothing better and no predicted pose (a cold start or a lost track).
ZOOM_STEPS = tuple(
    (dx, dy, k)
    for k, offs in ((0.5, (-0.25, 0.0, 0.25)), (0.25, (-0.3, -0.15, 0.0, 0.15, 0.3)))
    for dy in offs
    for dx in offs
)
ZOOM_TRY = 3
# The zoom's first level also reads windows twice the first pass's size around it, out to two
# of its sides away (5x5): on an unseen look (validation scene va003's, the demo's approach from
# 10 m) the first pass put the fixture 1.65 window sides off, beyond SEARCH_STEPS' reach, and
# every cold-start frame came out weak until the mission timed out. A fixture-holding double
# window ranks first by its tight heat maps (0.046 vs <= 0.014 for its neighbours and 0.001 for
# background), and the next level zooms into it. 25 more crops in that batch, on cold starts only,
# and only while the double windows stay within WIDE_MAX_SIDE_PX (the frame's height): a first
# pass that took a far fixture for a near one (va012: windows of 250-900 px around a 35-55 px
# fixture) has the scale wrong, not the place, and double windows there ranked the station's
# structure first (va012 tracking 3.4 -> 19 % before this bound).
WIDE_STEPS = tuple((dx, dy, 2.0) for dy in (-2.0, -1.0, 0.0, 1.0, 2.0) for dx in (-2.0, -1.0, 0.0, 1.0, 2.0))
WIDE_MAX_SIDE_PX = 480.0


def zoom_steps(wide: bool) -> tuple[tuple[float, float, float], ...]:
    """(dx, dy in base window sides, size factor) of one zoom level's batch."""
    return ZOOM_STEPS + (WIDE_STEPS if wide else ())


# When the zoom's windows still give no strong fit, the most fixture-like of them is zoomed into
# the same way, never into windows smaller than ZOOM_MIN_SIDE_PX: the
# first pass can put a 10 m fixture at 0.4 m, a window 10-25x too large (validation scene va012,
# whose keypoints are read to 0.3-0.7 crop px in the right window), which one level (4x) misses.
ZOOM_LEVELS = 3
ZOOM_MIN_SIDE_PX = 24.0  # no zoom window smaller (the fixture's window at ~15 m)
# The last resort of a cold start: when the prediction, SEARCH_STEPS and the zoom give no strong
# fit, the whole frame is read in windows of SCAN_SIDE_PX, SCAN_STRIDE sides apart (so some
# window holds the fixture within a quarter side of its centre, as in training), in batches of
# SCAN_BATCH, and the SCAN_TRY most fixture-like are solved. The zoom follows the first pass,
# whose scale can be wrong and whose place can be 0.5-2 windows off at once: on validation scene
# va012's look (shadowed, 9-10.5 m) the first pass read 0.45 m and the zoom never found the
# 35-40 px fixture (14 of 52 cold frames beyond 4 m weak; the rig's mission from 9 m never locked
# and aborted). Windows of 64 px (1.6-2.7x a far fixture's, 6-15 m) ranked the fixture's first
# on every one of the 16 cold frames of the validation scenes where the search failed (its score
# 0.04-0.21, the best elsewhere <= 0.04 but for its neighbours). Cost: ~320 crops, ~0.7 s on 2
# cores, on cold frames that found nothing else (nearer fixtures are the first pass's strength).
SCAN_SIDE_PX = 64.0
SCAN_STRIDE = 0.5
SCAN_BATCH = 64
SCAN_TRY = 3
# A ranked scan window that gives too few keypoints to solve is read again smaller (SCAN_SHRINK:
# its centre and a quarter side either way, at SCAN_SHRINK_FACTOR of its side, in one batch; the
# most fixture-like solved). 64 px holds a fixture at 9-12 m at about half the scale the keypoint
# network was trained on: on validation scene va012's look from 10.5 m (turned -2 / 1.5 deg, the
# fixture 28 px wide) stage 15's network ranked the fixture's window first (0.065, the next 0.001)
# but saw 3 of its 14 keypoints there, so the scan never solved it and the rig's mission aborted;
# 0.6 of the window found it to 0.29 crop px RMS (0.5: 0.41, 0.75: 0.28). 0.13.0 saw 5 there, a
# weak fit the scan then reads again in its own window. 10 crops, only where the old scan had
# nothing from that window.
SCAN_SHRINK_FACTOR = 0.6
SCAN_SHRINK = tuple((dx, dy) for dy in (-0.25, 0.0, 0.25) for dx in (-0.25, 0.0, 0.25))
# Crops one cold frame may read through the keypoint network (the hint's and SEARCH_STEPS' count
# but are never cut short; past the budget the zoom and the scan stop and go on in the next
# frames, ColdSearch), so that no cycle nears the MCU's 1 s link timeout: the whole cold search
# reads up to ~480 crops (1 + 11, three zoom levels of 34-59 + 3, the scan's 322 + 6); a frame
# that reaches the scan took 1.8-2.0 s (376 crops, 3 noise frames). A crop costs about the same
# read alone or in a batch: 4.6 ms a single pass (read + PnP), 4.8 ms a crop in a batch of 64
# (307 ms, p90 340), and the first pass 5.6 ms (medians; 2 vCPU Debian, no GPU, onnxruntime 2
# threads, the cores shared with training: upper bounds). With 60 crops the same frames took 7
# cycles each of 290 ms (median; p90 328, at most 336). Fewer would never fit the zoom's first
# batch (59) beside the hint's crop (MIN_COLD_CROP_BUDGET). A frame that runs only SEARCH_STEPS
# (12 crops, ~60 ms) is not affected; nor is the refining pass after a strong fit (outside the
# budget: 1 crop for the shipped model).
COLD_CROP_BUDGET = 60
MIN_COLD_CROP_BUDGET = len(ZOOM_STEPS) + len(WIDE_STEPS) + 1  # the largest batch, the hint's crop
# A carried cold search is dropped this long (frame time) after its first frame. Its scores and
# windows stay valid while the fixture barely moves in the image: on the validation scenes it
# moves at most 7 px/s at 6-15 m (median 0.5 px/s), and a scan window holds it within a quarter
# of its 64 px side of its centre, as the keypoint network was trained. The longest search takes
# 10 frames at COLD_CROP_BUDGET, 2.7 s at the ~0.3 s a cold cycle takes in the daemon; the scan's
# scores are then at most 7 frames (1.8 s, 13 px) old when its windows are solved.
COLD_CARRY_MAX_AGE_S = 3.0


def scan_windows(frame_wh: tuple[int, int], side_px: float, stride: float, out_px: int) -> list[CropWindow]:
    """Square windows of side_px covering the frame, centres `stride` sides apart (row-major),
    the outer ones flush with the frame's edges."""
    w, h = frame_wh
    step = side_px * stride
    windows = []
    for cy in _spaced(h, side_px, step):
        for cx in _spaced(w, side_px, step):
            windows.append(CropWindow((cx, cy), side_px, out_px))
    return windows


def _spaced(length_px: float, side_px: float, step_px: float) -> np.ndarray:
    """Window centres along one axis: from side/2 to length - side/2, at most step_px apart."""
    if length_px <= side_px:
        return np.array([length_px / 2.0])
    n = int(np.ceil((length_px - side_px) / step_px - 1e-9)) + 1
    return np.linspace(side_px / 2.0, length_px - side_px / 2.0, n)


def _checked_prior(prior: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """A usable predicted pose or None: a rotation and a finite translation in front of the camera."""
    if prior is None:
        return None
    try:
        R = np.asarray(prior[0], float).reshape(3, 3)
        T = np.asarray(prior[1], float).reshape(3)
    except (TypeError, ValueError, IndexError) as exc:
        raise ValueError(f"prior must be (R_cam_target 3x3, T_cam_target_m 3), got {prior!r}") from exc
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(T))) or T[2] <= 0:
        return None
    if abs(np.linalg.det(R) - 1.0) > 1e-3 or not np.allclose(R.T @ R, np.eye(3), atol=1e-3):
        return None
    return R, T


# The thresholds above and below in crop pixels (REPROJ_SCALE_CROP_PX, STRONG_FIT_RMS_CROP_PX,
# MIRROR_AGREE_CROP_PX) were measured on models reading a 128 px crop. A model with another crop
# size (`oibar.crop.out_px`) reads the same fixture over more or fewer pixels, so it is held to
# the same fraction of its crop: every threshold is in pixels of a CROP_REF_PX crop.
CROP_REF_PX = 128


def fit_rms_crop_px(r: PnpResult, win: CropWindow) -> float:
    """A fit's reprojection RMS over its inliers, in pixels of a CROP_REF_PX crop (for the shipped
    128 px models: the crop's own pixels)."""
    return float(r.rms_px) * win.scale * CROP_REF_PX / win.out_px


# Mirror reading (read_crop): on the fixture the two readings of a keypoint agree to 0.2 crop px
# (median; 99 % within 1.0, 99.9 % within 2.9: validation frames, 0.8.1). Averaging a crop of
# anything else with its mirror makes a left-right symmetric pattern that PnP takes for an
# aligned fixture (va012's cold start: 96 % range errors at confidence 0.96), so a keypoint whose
# readings disagree by more than this is not there.
MIRROR_AGREE_CROP_PX = 2.0

# A keypoint is where its heat map is tight. On the fixture the spread (the heat map's width,
# CROP_REF_PX terms) is 5.7 px (median; max 6.8 for 0.8.1 and 7.4 for 0.11.0 over 15 500 keypoints
# in windows cut around the true pose on every validation scene, every 9th frame). A crop of the
# station's structure can still give a few keypoints that PnP fits within STRONG_FIT_RMS_CROP_PX:
# on va012's cold start (the first pass takes the 10 m fixture for a 0.45 m one) 0.11.0's fit of
# six keypoints spread 8.5-25 px answered 0.42 m at confidence 0.94. Broader than this: not there.
MAX_SPREAD_CROP_PX = 9.0

ATTITUDE_PRIORS = ("direct", "head")  # oibar.fusion.attitude_prior: whose attitude the fit leans on
# The prior-free fit is handed to the filter only while it stays near the fused one: beyond these
# it is a gross PnP failure (a far frame's mirrored pose), not the prior's bias, which is ~0.5-2
# deg and ~1 % of the range on the validation scenes.
MEAS_MAX_ATT_DEV_DEG = 10.0
MEAS_MAX_POS_DEV_FRACTION = 0.10
# What the filter is fed (``oibar.filter_measurement``, chosen per network on the closed loop):
# "prior_free" (the default, 0.8.1: its attitude head pulls every frame's tilt toward aligned
# alike) or "fused" (the pose itself: a network whose head is better than PnP alone at range).
FILTER_MEASUREMENTS = ("prior_free", "fused")


# The largest turn of the refining pass's extra readings: the network was trained on crops
# turned up to 15 deg (kp_data.CropAugment.angle_deg); beyond, it reads crops it never saw.
MAX_TURNED_READING_DEG = 15.0
# Whose keypoints the filter's prior-free fit is solved from when the refining pass reads turned
# windows (``oibar.turned_reading_measurement``): "mean", the averaged ones the answer is fitted to
# (0.15.6), or "untouched", the untouched window's alone. At range that fit's tilt rests on
# hundredths of a pixel, and the average shifts every keypoint's bias by a few: 0.15.6 moved the
# measurement's signed attitude bias by 0.07-0.10 deg on validation and lost the loop on one turn
# (docs/model_history.md, 2026-11-27), while its answer gained.
TURNED_READING_MEASUREMENTS = ("mean", "untouched")
# ``oibar.placed_pass_refines``: when tracking, the crop placed by the filter's prediction (or the
# estimator's own latest strong fit) is read as the refining pass is (turned readings, the corner
# step), and a strong fit there ends the frame when its window was well placed (below), instead of
# a plain read followed by a second crop cut around its fit. One network run a tracked frame
# instead of two: the turned reading's batch of three costs about what two single crops do (7.4
# against 2 x 3.6 ms offline), and the daemon's second run was where 0.15.7 lost its frame ->
# command p99 (docs/model_history.md, 2026-11-27).
# Well placed: the window the refining pass would cut around the fit is centred within
# WELL_PLACED_CROP_PX of the placed one (crop px) and its side within WELL_PLACED_SIDE_FRAC. On
# validation a window up to 4 frame px off (13 crop px at 10 m) read as well as one on the truth,
# and one 10-20 px off lost 1 deg beyond 8 m (candidate 0.15.8, docs/model_history.md, 2026-11-28);
# elsewhere the usual refining pass follows.
WELL_PLACED_CROP_PX = 8.0
WELL_PLACED_SIDE_FRAC = 0.10


def measurement_without_prior(
    r: PnpResult, T: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The fit's prior-free pose (r.no_prior) for a filter, or (None, None) when the fit had no
    prior, PnP alone failed, or it lies grossly off the fused pose (MEAS_MAX_*)."""
    alone = r.no_prior
    if alone is None or not alone.ok:
        return None, None
    R_a, T_a = alone.pose()
    range_m = float(np.linalg.norm(T))
    if float(np.linalg.norm(T_a - T)) > MEAS_MAX_POS_DEV_FRACTION * range_m:
        return None, None
    if rotation_angle_deg(R_a.T @ R) > MEAS_MAX_ATT_DEV_DEG:
        return None, None
    return np.asarray(T_a, float), np.asarray(R_a, float)


@dataclass
class CropReading:
    """What the keypoint network reads from one crop: keypoints in frame pixels (K, 2), NaN where
    absent; their spread (K,) crop px; presence (K,) 0..1; the attitude head's R_cam_target
    (None for a model without the head)."""

    uv_px: np.ndarray
    spread_crop_px: np.ndarray
    present: np.ndarray
    R_cam_target_head: np.ndarray | None = None
    # the untouched window's own keypoints when uv_px averages several readings (turned), else None
    untouched_uv_px: np.ndarray | None = None


@dataclass
class ColdSearch:
    """Where a cold search (the zoom, then the scan) stopped when its frame's crop budget ran out
    (COLD_CROP_BUDGET), for the next frames to go on from: the zoom level under way, its base
    window and, once read, its windows to solve; the scan's scores so far. Which of the ranked
    windows have been solved (`tried`) holds for either."""

    level: int  # the zoom level under way; ZOOM_LEVELS: the scan
    base: CropWindow | None = None  # the zoom level's base window
    k_base: float = 1.0  # its size factor against the first pass's window
    ranked: list[tuple[CropWindow, float]] | None = None  # the level's windows to solve (None: unread)
    scan_scores: list[np.ndarray] = field(default_factory=list)  # the scan's, batch by batch
    tried: int = 0  # ranked windows solved so far
    # its first frame's time and the latest one's (estimate stamps them; NaN: never stamped)
    t_first_s: float = float("nan")
    t_last_s: float = float("nan")


class KeypointPoseEstimator(PoseEstimator):
    """Keypoints + PnP (issue 15): the direct model (the first pass, a file beside this one named
    by ``oibar.first_pass``) places a crop at full resolution around the fixture; the keypoint
    network finds the fixture's known points in it; PnP (OpenCV's RANSAC, then our own
    Levenberg-Marquardt) turns them into the pose. A second crop around that pose refines it. The
    direct answer stays as the cross-check (gross disagreement lowers confidence) and the fallback
    (when PnP finds no consistent pose, with low confidence and a flag saying so)."""

    def __init__(
        self,
        path: str | Path,
        threads: int = 2,
        warmup_runs: int = 3,
        range_limits_m: tuple[float, float] | None = None,
        defect_scale: float = DEFAULT_DEFECT_SCALE,
        allow_spinning: bool = False,
        refine_passes: int = 2,
        zoom_search: bool = True,
        scan_search: bool = True,
        mirror: bool | None = None,
        turned_reading_deg: float | None = None,
        turned_reading_head: bool | None = None,
        turned_reading_measurement: str | None = None,
        cold_crop_budget: int | None = COLD_CROP_BUDGET,
        corner_refine_side_px: float | None = None,
        placed_pass_refines: bool | None = None,
        overlap_first_pass: bool = True,
    ):
        self.path = Path(path)
        self.zoom_search = bool(zoom_search)
        # When a prediction (or the latest strong fit) places the first crop, the direct model
        # runs on a second thread while that crop is read: each network leaves most of the second
        # core idle at batch 1 (no spinning workers), and the crop does not need the direct answer
        # to be cut. The same computations, so the same pose; only sooner.
        self.overlap_first_pass = bool(overlap_first_pass)
        self.scan_search = bool(scan_search)
        # None: no budget (a tool that judges frames one by one, with no cycle to keep)
        if cold_crop_budget is not None and cold_crop_budget < MIN_COLD_CROP_BUDGET:
            raise ValueError(
                f"cold_crop_budget must be at least {MIN_COLD_CROP_BUDGET} crops (the zoom's first "
                f"batch and the hint's crop), or None; got {cold_crop_budget}"
            )
        self.cold_crop_budget = cold_crop_budget
        self.meta = read_metadata(self.path)
        for key in ("keypoints_3d_m", "crop", "pnp", "camera", "first_pass"):
            if key not in self.meta:
                raise ModelFileError(f"{self.path}: keypoint model without oibar.{key} metadata")
        first = self.path.parent / self.meta["first_pass"]
        if not first.is_file():
            raise ModelFileError(
                f"{self.path}: its first-pass model {first.name} is missing (it must lie beside it)"
            )
        self.first = PoseEstimator(first, threads, warmup_runs, range_limits_m, defect_scale, allow_spinning)
        if isinstance(self.first, KeypointPoseEstimator):
            raise ModelFileError(f"{first}: a first-pass model must be a direct model")
        self.session = _session(self.path, threads, allow_spinning)
        self.input_name = self.session.get_inputs()[0].name
        self.output_names = [o.name for o in self.session.get_outputs()]
        missing = [n for n in ("kp_crop_px", "kp_present") if n not in self.output_names]
        if missing:
            raise ModelFileError(f"{self.path}: outputs {missing} missing (has {self.output_names})")
        self.size_wh = tuple(self.meta["input_size_wh"])
        self.out_px = int(self.meta["crop"]["out_px"])
        self.margin = float(self.meta["crop"]["margin"])
        self.points_m = np.asarray(self.meta["keypoints_3d_m"], float)
        self.reproj_crop_px = float(self.meta["pnp"]["reproj_crop_px"])
        self.min_present = float(self.meta["pnp"]["min_present"])
        cam = self.meta["camera"]
        self.frame_wh = (int(cam["width_px"]), int(cam["height_px"]))
        self.K_frame = np.array(cam["K_frame"], float)
        self.range_limits_m = _range_limits(self.meta, range_limits_m)
        self.defect_scale = float(defect_scale)
        self.refine_passes = max(1, int(refine_passes))
        self.fit_history = FitHistory()  # recent strong fits: a run of them can overrule the direct model
        if (self.meta.get("fusion") or {}).get("kp_error_model"):
            self._error_model(self.meta["fusion"])  # a malformed table fails here, not in flight
        if (self.meta.get("fusion") or {}).get("prior_error_model"):
            self._prior_error_model(self.meta["fusion"])
        if (self.meta.get("fusion") or {}).get("head_gain"):
            self._head_gain(self.meta["fusion"])
        self.R_att_ref = self._attitude_head()
        # read_crop's twins, when the refining pass reads each crop with its mirror: as the
        # export says (``oibar.mirror_reading``, chosen per network on the closed loop), unless told
        if mirror is None:
            mirror = bool(self.meta.get("mirror_reading", False))
        self.mirror = mirror_permutation(self.points_m) if mirror else None
        if mirror and (
            self.mirror is None
            or (self.R_att_ref is not None and not mirror_symmetric_attitude(self.R_att_ref))
        ):
            raise ModelFileError(
                f"{self.path}: the mirror reading needs a left-right symmetric keypoint set and "
                "attitude-head reference (oibar.keypoints_3d_m, oibar.attitude_head.R_ref); this "
                "model has not: export it without --mirror-reading"
            )
        # the refining pass's turned readings: as the export says (``oibar.turned_reading_deg``,
        # chosen per network on validation and the closed loop), unless told
        turned = (
            self.meta.get("turned_reading_deg", 0.0) if turned_reading_deg is None else turned_reading_deg
        )
        if (
            isinstance(turned, bool)
            or not isinstance(turned, int | float)
            or not 0.0 <= float(turned) <= MAX_TURNED_READING_DEG
        ):
            raise ModelFileError(
                f"{self.path}: oibar.turned_reading_deg must be a number of degrees in "
                f"[0, {MAX_TURNED_READING_DEG:g}] (0: read once), got {turned!r}"
            )
        self.turned_reading_deg = float(turned)
        # and whether the attitude head's answer is the mean of all of them
        # (``oibar.turned_reading_head``) or the untouched window's alone
        self.turned_reading_head = self._export_flag("turned_reading_head", turned_reading_head)
        # and whose keypoints the filter's prior-free fit uses (``oibar.turned_reading_measurement``)
        meas = (
            self.meta.get("turned_reading_measurement", "mean")
            if turned_reading_measurement is None
            else turned_reading_measurement
        )
        if meas not in TURNED_READING_MEASUREMENTS:
            raise ModelFileError(
                f"{self.path}: oibar.turned_reading_measurement must be one of "
                f"{TURNED_READING_MEASUREMENTS}, got {meas!r}"
            )
        self.turned_reading_measurement = meas
        # a crop placed by a prediction read as the refining pass, final when well placed
        # (``oibar.placed_pass_refines``; the note after TURNED_READING_MEASUREMENTS)
        placed = self._export_flag("placed_pass_refines", placed_pass_refines)
        if placed and self.mirror is not None:
            raise ModelFileError(
                f"{self.path}: oibar.placed_pass_refines cannot go with oibar.mirror_reading: a "
                "predicted window may not hold the fixture, and a crop of anything averaged with its "
                "mirror makes a symmetric pattern that PnP fits well"
            )
        self.placed_pass_refines = placed
        # the refining pass's sub-pixel corners: as the export says
        # (``oibar.corner_refine_side_px``, chosen per network on validation), unless told
        side = (
            self.meta.get("corner_refine_side_px", 0.0)
            if corner_refine_side_px is None
            else corner_refine_side_px
        )
        if isinstance(side, bool) or not isinstance(side, int | float) or not 0.0 <= float(side) < np.inf:
            raise ModelFileError(
                f"{self.path}: oibar.corner_refine_side_px must be a size in frame pixels >= 0 "
                f"(0: off), got {side!r}"
            )
        self.corner_refine_side_px = float(side)
        names = list(self.meta.get("keypoint_names") or [])
        self.corner_idx = np.array([names.index(n) for n in CORNER_NAMES if n in names], int)
        if self.corner_refine_side_px > 0 and len(self.corner_idx) != len(CORNER_NAMES):
            raise ModelFileError(
                f"{self.path}: the corner refinement needs the rim's and the connector's corners "
                f"among its keypoints (oibar.keypoint_names {list(CORNER_NAMES)}); this model "
                f"names {names}"
            )
        self.filter_measurement = self.meta.get("filter_measurement", "prior_free")
        if self.filter_measurement not in FILTER_MEASUREMENTS:
            raise ModelFileError(
                f"{self.path}: oibar.filter_measurement must be one of {FILTER_MEASUREMENTS}, "
                f"got {self.filter_measurement!r}"
            )
        if (self.meta.get("fusion") or {}).get("attitude_prior", "direct") not in ATTITUDE_PRIORS:
            raise ModelFileError(
                f"{self.path}: oibar.fusion.attitude_prior must be one of {ATTITUDE_PRIORS}, "
                f"got {self.meta['fusion']['attitude_prior']!r}"
            )
        if (self.meta.get("fusion") or {}).get("attitude_prior") == "head" and self.R_att_ref is None:
            raise ModelFileError(f"{self.path}: its fusion asks for the attitude head, which it lacks")
        if (self.meta.get("fusion") or {}).get("head_gain") and self.meta["fusion"].get(
            "attitude_prior"
        ) != "head":
            raise ModelFileError(
                f"{self.path}: its fusion has a head gain but its prior is not the attitude head"
            )
        # last: a fault of this file's own is reported as this file's, not as a far network that
        # no longer matches it
        self._open_far_network(threads, allow_spinning)
        zero = np.zeros((1, 3, self.out_px, self.out_px), np.float32)
        for _ in range(warmup_runs):
            self.run(zero)
            if self.far_session is not None:
                self.far_session.run(None, {self.input_name: zero})

    def _open_far_network(self, threads: int, allow_spinning: bool) -> None:
        """``oibar.far_network`` ({"file", "from_m"}): a second keypoint network, a file beside
        this one, that reads every crop window whose head-on range is `from_m` or more (the
        section "Candidate 0.26.0" of docs/model_history.md: one network of this size reads near
        or far well, not both). It must be the same kind of network as this one: the same
        outputs, keypoints, crop and attitude head, since every table of this file's (fusion,
        error models, corner step) reads its answers too."""
        spec = self.meta.get("far_network")
        if spec is None:
            return
        try:
            name, from_m = str(spec["file"]), spec["from_m"]
        except (KeyError, TypeError) as exc:
            raise ModelFileError(
                f"{self.path}: oibar.far_network must be {{'file': NAME, 'from_m': RANGE}}, got {spec!r}"
            ) from exc
        if (
            isinstance(from_m, bool)
            or not isinstance(from_m, int | float)
            or not 0.0 < float(from_m) < np.inf
        ):
            raise ModelFileError(
                f"{self.path}: oibar.far_network.from_m must be a range in m > 0, got {from_m!r}"
            )
        far = self.path.parent / name
        if Path(name).name != name or not far.is_file():
            raise ModelFileError(
                f"{self.path}: its far network {name!r} is missing (a file name; it must lie beside it)"
            )
        meta = read_metadata(far)
        for key in ("kind", "keypoints_3d_m", "keypoint_names", "crop", "attitude_head", "input_size_wh"):
            if meta.get(key) != self.meta.get(key):
                raise ModelFileError(
                    f"{far}: not the same kind of network as {self.path.name} (oibar.{key} differs), "
                    "so this file's tables cannot read it"
                )
        session = _session(far, threads, allow_spinning)
        inputs = session.get_inputs()
        outputs = [o.name for o in session.get_outputs()]
        if outputs != self.output_names or [i.name for i in inputs] != [self.input_name]:
            raise ModelFileError(
                f"{far}: inputs/outputs {[i.name for i in inputs]} / {outputs} differ from "
                f"{self.path.name}'s {[self.input_name]} / {self.output_names}"
            )
        self.far_session, self.far_from_m = session, float(from_m)

    def _reads_far(self, win: CropWindow) -> bool:
        """Whether the far network reads this window (its head-on range from `far_from_m` on)."""
        return self.far_session is not None and self._range_for_side_m(win.side_px) >= self.far_from_m

    def run_windows(self, x: np.ndarray, wins: list[CropWindow]) -> dict[str, np.ndarray]:
        """Crops (N, 3, S, S) of the windows `wins` (one per row) -> every output by name, each
        row read by the network for its window's range (`_reads_far`); one network, one batch,
        without a far network."""
        if self.far_session is None:
            return self.run(x)
        far = np.array([self._reads_far(w) for w in wins], bool)
        if not far.any():
            return self.run(x)
        far_out = dict(
            zip(self.output_names, self.far_session.run(None, {self.input_name: x[far]}), strict=True)
        )
        if far.all():
            return far_out
        near_out = self.run(x[~far])
        out = {}
        for k, v in near_out.items():
            both = np.empty((len(wins),) + v.shape[1:], v.dtype)
            both[~far], both[far] = v, far_out[k]
            out[k] = both
        return out

    def check_frame(self, image: Any) -> None:
        self.first.check_frame(image)
        h, w = image.shape[:2]
        if (w, h) != self.frame_wh:
            raise FrameError(
                f"frame {w}x{h}: the keypoint model works in the camera's own pixels, "
                f"{self.frame_wh[0]}x{self.frame_wh[1]}"
            )

    def _export_flag(self, key: str, given: bool | None) -> bool:
        """An on/off reading option: `given`, else as the export says (off without the key); a
        value that is not true or false is a damaged export."""
        flag = self.meta.get(key, False) if given is None else given
        if not isinstance(flag, bool):
            raise ModelFileError(f"{self.path}: oibar.{key} must be true or false, got {flag!r}")
        return flag

    def _attitude_head(self) -> np.ndarray | None:
        """R_ref of the attitude head (model >= 0.6.0), None for a model without one."""
        head = self.meta.get("attitude_head")
        if head is None:
            return None
        try:
            R_ref = np.asarray(head["R_ref"], float)
            name = str(head["output"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"{self.path}: oibar.attitude_head is malformed ({exc})") from exc
        if R_ref.shape != (3, 3) or not np.allclose(R_ref @ R_ref.T, np.eye(3), atol=1e-6):
            raise ModelFileError(f"{self.path}: oibar.attitude_head.R_ref is not a rotation matrix")
        if name not in self.output_names:
            raise ModelFileError(f"{self.path}: the attitude head's output {name!r} is missing")
        return R_ref

    def read_crop(self, image: np.ndarray, win: CropWindow, refining: bool = False) -> CropReading:
        """One window through the keypoint network (CropReading). In the refining pass
        (`refining`: a window cut around a strong fit) the export can ask for more readings of
        the same window, all in one batch, averaged in frame pixels:

        - its mirror image (``oibar.mirror_reading``, a left-right symmetric fixture,
          `self.mirror`): the mirror's reading mapped back (u -> S - u, each keypoint from its
          twin, the head's rotation vector turned over), so the network's own left-right leaning
          cancels. 0.8.1 reads a -0.24 deg tilt about y on every validation frame at 2-5 m and
          +0.12 deg in the mirror; averaged, -0.06 deg (docs/model_history.md, 2026-11-24).
        - the window turned by +-``oibar.turned_reading_deg`` about its centre (a camera rolled
          about its boresight: the network was trained on crops turned up to 15 deg). Each
          reading's keypoints go back to the frame through its own window; a keypoint counts
          where most readings see it. 0.8.1 at 8 deg: validation attitude 0.84 -> 0.81 deg, the
          filter's measurement 0.86 -> 0.82 (docs/model_history.md, 2026-11-25). With
          ``oibar.turned_reading_head`` the attitude head's answer is the mean of the readings'
          (each mapped to the camera through its own window), else the untouched window's:
          0.15.3 at 8 deg on validation, 0.539 -> 0.531 deg (docs/model_history.md, 2026-11-27).
          The untouched window's own keypoints ride along (`untouched_uv_px`) for the filter's
          prior-free fit (``oibar.turned_reading_measurement``).

        Only for a window already known to hold the fixture: averaged with its mirror, a crop of
        anything makes a symmetric pattern that PnP fits well."""
        wins = [win]
        if refining and self.turned_reading_deg > 0:
            a = float(np.radians(self.turned_reading_deg))
            wins += [replace(win, angle_rad=win.angle_rad + a), replace(win, angle_rad=win.angle_rad - a)]
        mirror = refining and self.mirror is not None
        crops = [cut(image, w) for w in wins]
        batch = [c for crop in crops for c in ((crop, crop[:, ::-1]) if mirror else (crop,))]
        rows = [w for w in wins for _ in range(2 if mirror else 1)]
        out = {k: v.astype(float) for k, v in self.run_windows(to_input(np.stack(batch)), rows).items()}
        per = 2 if mirror else 1
        readings = [
            self._reading(w, {k: v[i * per : (i + 1) * per] for k, v in out.items()})
            for i, w in enumerate(wins)
        ]
        if len(readings) == 1:
            return readings[0]
        uv = np.stack([r.uv_px for r in readings])
        seen = np.isfinite(uv[..., 0])
        mean_uv = np.full_like(readings[0].uv_px, np.nan)
        keep = seen.sum(0) * 2 > len(readings)
        for j in np.flatnonzero(keep):
            mean_uv[j] = uv[seen[:, j], j].mean(0)
        return CropReading(
            mean_uv,
            np.mean([r.spread_crop_px for r in readings], axis=0),
            np.mean([r.present for r in readings], axis=0),
            self._head_of(readings),
            readings[0].uv_px,
        )

    def _head_of(self, readings: list[CropReading]) -> np.ndarray | None:
        """The attitude head's answer for read_crop's readings: the untouched window's (the
        first), or with `turned_reading_head` the mean of every reading that has one."""
        if not self.turned_reading_head:
            return readings[0].R_cam_target_head
        heads = [r.R_cam_target_head for r in readings if r.R_cam_target_head is not None]
        if len(heads) < 2:
            return heads[0] if heads else None
        R: np.ndarray = quat_to_matrix(mean_quat(np.stack([matrix_to_quat(h) for h in heads])))
        return R

    def _reading(self, win: CropWindow, out: dict[str, np.ndarray]) -> CropReading:
        """The network's outputs for one window (one row, or two: the crop and its mirror image,
        averaged as read_crop says) -> CropReading, keypoints in frame pixels."""
        if len(out["kp_crop_px"]) == 1:
            out = {k: v[0] for k, v in out.items()}
        else:
            assert self.mirror is not None  # two rows only for a mirror reading
            disagree = None
            for k in out:
                if k == "kp_crop_px":
                    m = mirror_crop_px(out[k][1], self.mirror, self.out_px)
                    disagree = (
                        np.linalg.norm(out[k][0] - m, axis=1)
                        > MIRROR_AGREE_CROP_PX * self.out_px / CROP_REF_PX
                    )
                elif self.R_att_ref is not None and k == self.meta["attitude_head"]["output"]:
                    m = out[k][1] * MIRROR_ATT
                else:  # per keypoint: presence, spread
                    m = out[k][1][self.mirror]
                out[k] = 0.5 * (out[k][0] + m)
            if disagree is not None:
                out["kp_present"][disagree] = 0.0
        kp = out["kp_crop_px"]
        present = out["kp_present"]
        spread = out["kp_spread_px"] if "kp_spread_px" in out else np.zeros(len(kp))
        uv = win.to_frame(kp)
        uv[(present < self.min_present) | (spread > MAX_SPREAD_CROP_PX * self.out_px / CROP_REF_PX)] = np.nan
        R_head = None
        if self.R_att_ref is not None:
            att = out[self.meta["attitude_head"]["output"]]
            if np.all(np.isfinite(att)):
                R_head = attitude_from_crop(win, self._K(), att, self.R_att_ref)
        return CropReading(uv, spread, present, R_head)

    def keypoints(self, image: np.ndarray, win: CropWindow) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One crop -> (frame pixels (K, 2) with NaN where absent, spread (K,) crop px, presence (K,))."""
        r = self.read_crop(image, win)
        return r.uv_px, r.spread_crop_px, r.present

    def solve(
        self,
        image: np.ndarray,
        R_direct: np.ndarray,
        T_direct: np.ndarray,
        fusion: dict[str, Any] | None = None,
        prior: tuple[np.ndarray, np.ndarray] | None = None,
        hint: tuple[np.ndarray, np.ndarray] | None = None,
        placed_reading: tuple[CropWindow, CropReading] | None = None,
    ) -> tuple[PnpResult, CropWindow] | tuple[None, None]:
        """Crop around the current pose, keypoints, pose (keypoints.map_pose: PnP, and with the
        export's ``oibar.fusion`` an attitude prior: the direct model's or the crop's own
        attitude head); then `refine_passes - 1` more times from the newest pose. The first
        window is the predicted pose's (`prior`, from the navigation filter) when there is one;
        with `placed_pass_refines` it is read as a refining pass, and a strong fit there is final
        when its window was well placed (`_well_placed`).
        When that gives no strong fit (STRONG_FIT_RMS_CROP_PX), the windows of SEARCH_STEPS
        around the direct model's pose are tried in turn (the direct model can be 1 m off
        sideways at 10 m on an unseen scene), then ZOOM_STEPS inside it, level after level
        (`zoom_search`, ZOOM_LEVELS), then the scan of the whole frame (`scan_search`,
        SCAN_SIDE_PX). Without a prediction, `hint` (the estimator's own latest strong fit, when
        the filter has not taken it yet) places the first crop instead. The prediction and the
        hint only place a crop, never the attitude prior, so a wrong one cannot feed itself back.
        The zoom and the scan (the cold search) stop where the frame's crops would pass
        `cold_crop_budget` and leave where they stopped for the next call to go on from, without
        SEARCH_STEPS (`_cold`; estimate drops it when it is too old): a caller that solves
        unrelated frames calls forget() between them, or builds the estimator without a budget.
        `placed_reading`: (the window `placed` places, its reading), made already (estimate
        reads it while the direct model runs), so neither is computed again here.
        Returns (PnpResult, its window): the first strong fit, else the best weak one
        (`_weak_rank`), else (None, None)."""
        K = self._K()
        f = self.meta.get("fusion") if fusion is None else fusion
        best: tuple[PnpResult, CropWindow] | None = None
        weak: tuple[PnpResult, CropWindow] | None = None

        def consider(r: PnpResult | None, win: CropWindow | None) -> bool:
            """Keep a strong fit (True: stop searching); remember the best weak one."""
            nonlocal best, weak
            if r is None or win is None:
                return False
            if fit_rms_crop_px(r, win) <= STRONG_FIT_RMS_CROP_PX:
                best = (r, win)
                return True
            if weak is None or self._weak_rank(r, win) < self._weak_rank(*weak):
                weak = (r, win)
            return False

        # a cold search carried from earlier frames goes on here; a prediction ends it
        cold = self._cold if prior is None else None
        self._cold = None
        crops = 0  # read for this frame, counted against the cold search's budget
        placed = prior if prior is not None else hint
        refined = False  # the placed read was a refining one, strong and well placed: final
        if placed is not None:
            # the window estimate read already (while the direct model ran) is this very one
            win_p = placed_reading[0] if placed_reading is not None else self._placed_window(placed)
            if win_p is not None:
                crops += 1
                r, pwin = self._one_pass(
                    image,
                    win_p,
                    R_direct,
                    f,
                    float(np.linalg.norm(placed[1])),
                    refining=self.placed_pass_refines,
                    reading=placed_reading[1] if placed_reading is not None else None,
                )
                refined = consider(r, pwin) and self.placed_pass_refines and self._well_placed(r, pwin)
        base: CropWindow | None = None
        # SEARCH_STEPS are never cut short (they run with a prediction too); a carried search skips
        # them: they found nothing on its first frame, and the fixture has barely moved since
        if best is None and cold is None:
            uv0 = project(K, self.points_m, R_direct, T_direct)
            if np.all(np.isfinite(uv0)):
                base = window_around(uv0, self.out_px, self.margin)
                for dx, dy, k in SEARCH_STEPS:
                    win = base.stepped(dx, dy, k)
                    crops += 1
                    if consider(
                        *self._one_pass(image, win, R_direct, f, float(np.linalg.norm(T_direct)) / k)
                    ):
                        break
            # the zoom and the scan only on a cold start or a lost track: with a prediction their
            # cost would come out of the 100 ms frame budget on every weak far frame of a healthy track
            if best is None and prior is None:
                if base is not None and self.zoom_search:
                    cold = ColdSearch(level=0, base=base)
                elif self.scan_search:
                    cold = ColdSearch(level=ZOOM_LEVELS)
        if best is None and cold is not None:
            budget = np.inf if self.cold_crop_budget is None else self.cold_crop_budget
            if not self._cold_search(image, cold, R_direct, T_direct, f, consider, budget - crops):
                self._cold = cold  # out of crops: the next frames go on (estimate flags `searching`)
        if best is None:
            return weak if weak is not None else (None, None)
        for _ in range(0 if refined else self.refine_passes - 1):
            R_best, T_best = best[0].pose()
            uv = project(K, self.points_m, R_best, T_best)
            r, rwin = self._one_pass(
                image,
                window_around(uv, self.out_px, self.margin),
                R_direct,
                f,
                float(np.linalg.norm(T_best)),
                refining=True,
            )
            if r is None or rwin is None or fit_rms_crop_px(r, rwin) > STRONG_FIT_RMS_CROP_PX:
                break
            best = (r, rwin)
        return best

    def _first_pass_pool(self) -> ThreadPoolExecutor:
        """The direct model's thread, made on first use in this process: a process forked from
        one that used it inherits the executor but not its thread, and would wait forever."""
        if self._first_pass_thread is None or self._first_pass_thread[0] != os.getpid():
            pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="oibar-first-pass")
            self._first_pass_thread = (os.getpid(), pool)
        return self._first_pass_thread[1]

    def _placed_window(self, placed: tuple[np.ndarray, np.ndarray] | None) -> CropWindow | None:
        """The window a predicted pose (or a hint) places: around its projected keypoints; None
        where it projects nowhere (behind the camera)."""
        if placed is None:
            return None
        uv_p = project(self._K(), self.points_m, placed[0], placed[1])
        return window_around(uv_p, self.out_px, self.margin) if np.all(np.isfinite(uv_p)) else None

    def _well_placed(self, r: PnpResult | None, win: CropWindow | None) -> bool:
        """Whether `win` is where the refining pass would have cut it around the fit `r`
        (WELL_PLACED_CROP_PX, WELL_PLACED_SIDE_FRAC): then its refining read is final."""
        if r is None or win is None:
            return False
        around = window_around(project(self._K(), self.points_m, *r.pose()), self.out_px, self.margin)
        off_crop_px = float(np.hypot(*np.subtract(around.center_px, win.center_px))) * win.scale
        return (
            off_crop_px <= WELL_PLACED_CROP_PX
            and abs(around.side_px / win.side_px - 1.0) <= WELL_PLACED_SIDE_FRAC
        )

    def _weak_rank(self, r: PnpResult, win: CropWindow) -> tuple[bool, float]:
        """Which weak fit to return when no strong one is found: one inside the range envelope
        before any outside it (a tiny zoom window can fit noise at 40 m with a lower RMS), then
        the lowest RMS."""
        range_m = float(np.linalg.norm(r.pose()[1]))
        inside = self.range_limits_m[0] <= range_m <= self.range_limits_m[1]
        return (not inside, fit_rms_crop_px(r, win))

    def _zoom_windows(
        self, image: np.ndarray, base: CropWindow, wide: bool = False
    ) -> list[tuple[CropWindow, float]]:
        """ZOOM_STEPS' windows (and WIDE_STEPS' with `wide`) read in one batch; the ZOOM_TRY
        that look most like the fixture (mean presence x exp(-mean spread / 4 px, CROP_REF_PX terms)) with
        their size factors, best first."""
        wins = self._zoom_candidates(base, wide)
        if not wins:
            return []
        score = self._fixture_likeness(image, [w for w, _ in wins])
        return [wins[i] for i in np.argsort(-score)[:ZOOM_TRY]]

    def _zoom_candidates(self, base: CropWindow, wide: bool) -> list[tuple[CropWindow, float]]:
        """The windows (with their size factors) one zoom level reads around `base`."""
        return [
            (base.stepped(dx, dy, k), k)
            for dx, dy, k in zoom_steps(wide)
            if base.side_px * k >= ZOOM_MIN_SIDE_PX  # smaller than a fixture within the envelope
        ]

    def _fixture_likeness(self, image: np.ndarray, wins: list[CropWindow]) -> np.ndarray:
        """How much each window looks like the fixture, read in one batch: mean presence x
        exp(-mean heat-map spread / 4 px, CROP_REF_PX terms)."""
        out = self.run_windows(np.concatenate([to_input(cut(image, w)) for w in wins]), wins)
        present = out["kp_present"].astype(float).mean(axis=1)
        spread = (
            out["kp_spread_px"].astype(float).mean(axis=1) if "kp_spread_px" in out else np.zeros(len(wins))
        )
        score: np.ndarray = present * np.exp(-spread * CROP_REF_PX / self.out_px / 4.0)
        return score

    def _cold_search(
        self,
        image: np.ndarray,
        c: ColdSearch,
        R_direct: np.ndarray,
        T_direct: np.ndarray,
        f: dict[str, Any] | None,
        consider: Any,
        crops_left: float,
    ) -> bool:
        """Go on with the cold search `c`: the zoom's levels (`_zoom_windows`), then the scan
        (SCAN_SIDE_PX windows over the whole frame, read SCAN_BATCH at a time, the SCAN_TRY most
        fixture-like solved). True when it is over (`consider` kept a strong fit, or nothing is
        left to try); False when the next read would take more than `crops_left` crops: `c` then
        says where to go on."""
        K = self._K()
        range_m = float(np.linalg.norm(T_direct))
        while c.level < ZOOM_LEVELS:  # the zoom
            assert c.base is not None
            if c.ranked is None:
                wide = c.level == 0 and c.base.side_px * 2.0 <= WIDE_MAX_SIDE_PX
                n = len(self._zoom_candidates(c.base, wide))
                if n > crops_left:
                    return False
                crops_left -= n
                c.ranked = self._zoom_windows(image, c.base, wide=wide)
            while c.tried < len(c.ranked):
                if crops_left < 1:
                    return False
                crops_left -= 1
                zwin, k = c.ranked[c.tried]
                c.tried += 1
                if consider(*self._one_pass(image, zwin, R_direct, f, range_m / (c.k_base * k))):
                    return True
            if c.ranked and c.level + 1 < ZOOM_LEVELS:  # zoom again, into the most fixture-like
                c.level, c.base, c.k_base = c.level + 1, c.ranked[0][0], c.k_base * c.ranked[0][1]
                c.ranked, c.tried = None, 0
            else:  # on to the scan
                c.level, c.base, c.ranked, c.tried = ZOOM_LEVELS, None, None, 0
        if not self.scan_search:
            return True
        h, w = image.shape[:2]
        wins = scan_windows((w, h), SCAN_SIDE_PX, SCAN_STRIDE, self.out_px)
        read = sum(len(s) for s in c.scan_scores)
        while read < len(wins):
            n = int(min(SCAN_BATCH, len(wins) - read, crops_left))
            if n < 1:
                return False
            c.scan_scores.append(self._fixture_likeness(image, wins[read : read + n]))
            read, crops_left = read + n, crops_left - n
        # ranked over every window scored, on this frame or the last ones: the fixture moves only
        # a few pixels in between (COLD_CARRY_MAX_AGE_S)
        ranked = [wins[i] for i in np.argsort(-np.concatenate(c.scan_scores), kind="stable")[:SCAN_TRY]]
        while c.tried < len(ranked):
            swin = ranked[c.tried]
            if crops_left < 1:
                return False
            crops_left -= 1
            r, rwin = self._one_pass(image, swin, R_direct, f, self._range_for_side_m(swin.side_px))
            if consider(r, rwin):
                return True
            if r is None:  # too few keypoints: a far fixture seen too small (SCAN_SHRINK)
                if crops_left < len(SCAN_SHRINK) + 1:
                    return False  # the next frame reads this window again, then shrinks it
                crops_left -= len(SCAN_SHRINK) + 1
                r, rwin = self._shrunk_scan_pass(image, swin, R_direct, f)
                if consider(r, rwin):
                    return True
            if r is not None:
                # a weak fit from a window of a guessed size is close (validation: within 10 % of
                # the range): read again in the window its own pose draws
                uv_r = project(K, self.points_m, *r.pose())
                if np.all(np.isfinite(uv_r)):
                    if crops_left < 1:
                        return False  # the next frame reads this window again, then redraws
                    crops_left -= 1
                    if consider(
                        *self._one_pass(
                            image,
                            window_around(uv_r, self.out_px, self.margin),
                            R_direct,
                            f,
                            float(np.linalg.norm(r.pose()[1])),
                        )
                    ):
                        return True
            c.tried += 1
        return True

    def _shrunk_scan_pass(
        self, image: np.ndarray, swin: CropWindow, R_direct: np.ndarray, f: dict[str, Any] | None
    ) -> tuple[PnpResult, CropWindow] | tuple[None, None]:
        """SCAN_SHRINK's windows inside scan window `swin`, read in one batch; the most
        fixture-like solved."""
        wins = [swin.stepped(dx, dy, SCAN_SHRINK_FACTOR) for dx, dy in SCAN_SHRINK]
        best = wins[int(np.argmax(self._fixture_likeness(image, wins)))]
        return self._one_pass(image, best, R_direct, f, self._range_for_side_m(best.side_px))

    def _range_for_side_m(self, side_px: float) -> float:
        """The range at which the fixture, seen head-on, fills a window of side_px (its
        keypoints' larger extent across the boresight x the crop margin): the scale the range
        error models are read at when nothing else says how far the fixture is."""
        extent_m = float(np.max(np.ptp(self.points_m[:, :2], axis=0)))
        return float(self._K()[0, 0]) * extent_m * self.margin / max(side_px, 1e-6)

    def _K(self) -> np.ndarray:
        assert self.K_frame is not None  # set from the keypoint model's oibar.camera (required)
        return self.K_frame

    def _one_pass(
        self,
        image: np.ndarray,
        win: CropWindow,
        R_direct: np.ndarray,
        f: dict[str, Any] | None,
        range_m: float,
        refining: bool = False,
        reading: CropReading | None = None,
    ) -> tuple[PnpResult, CropWindow] | tuple[None, None]:
        """One window to a fit; `reading`: this window's read_crop(image, win, refining), if
        made already."""
        if reading is None:
            reading = self.read_crop(image, win, refining)
        uv = reading.uv_px
        if refining:
            uv = self.refined_corners(image, win, uv)
        # the attitude prior: the head's reading of this crop when the fusion says so (0.6.0),
        # else the direct model's
        R_prior = R_direct
        if f and f.get("attitude_prior") == "head" and reading.R_cam_target_head is not None:
            R_prior = reading.R_cam_target_head
            if f.get("head_gain"):  # the head's tilt given back the size it shrank by (0.15.10)
                R_prior = tilt_scaled(R_prior, 1.0 / self._head_gain(f).gain(range_m))
        s_px: float | np.ndarray | None = float(f["sigma_crop_px"]) / win.scale if f else None
        if s_px is not None and f and f.get("kp_error_model"):
            s_px = s_px * self._error_model(f).scale(range_m)
        s_rad = np.radians(float(f["sigma_prior_deg"])) if f else None
        if s_rad is not None and f and f.get("prior_error_model"):
            s_rad *= self._prior_error_model(f).scale(range_m)
        r = map_pose(
            uv,
            self.points_m,
            self._K(),
            self.reproj_crop_px / win.scale,
            R_prior,
            s_px,
            s_rad,
            MIN_INLIERS,
        )
        if not r.ok:
            return None, None
        untouched = reading.untouched_uv_px  # set only by a refining pass's turned reading
        if self.turned_reading_measurement == "untouched" and untouched is not None and s_rad is not None:
            # a fit with the prior: its prior-free twin (the filter's measurement) from the untouched
            # window's keypoints, with the same corner step (TURNED_READING_MEASUREMENTS)
            alone = solve_pnp(
                self.refined_corners(image, win, untouched),
                self.points_m,
                self._K(),
                self.reproj_crop_px / win.scale,
                min_points=MIN_INLIERS,
            )
            r.no_prior = alone if alone.ok else None
        return r, win

    def refined_corners(self, image: np.ndarray, win: CropWindow, uv: np.ndarray) -> np.ndarray:
        """The fixture's sharp corners (CORNER_NAMES: the rim's, the connector's) moved onto the
        frame's own (keypoints.refine_corners_px) when the fixture spans at least
        `corner_refine_side_px` frame pixels (its window's side over the crop margin); the search
        window scales with it so that it stays inside the rim band and the connector (6 % and
        8 % of the fixture's width). Off (the keypoints as read) when the export says 0."""
        import cv2

        extent_px = win.side_px / self.margin
        if self.corner_refine_side_px <= 0 or extent_px < self.corner_refine_side_px:
            return uv
        half = int(np.clip(round(CORNER_HALF_WIN_PER_EXTENT * extent_px), *CORNER_HALF_WIN_PX))
        gray = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
        out, _ = refine_corners_px(gray, uv, self.corner_idx, half, CORNER_MAX_MOVE_PER_HALF_WIN * half)
        return out

    def _fusion_table(self, f: dict[str, Any], key: str, build: Any) -> Any:
        """`build(f[key])`, made once per table and held (holding the table keeps its identity
        from being reused); a malformed table is a ModelFileError naming the file."""
        table = f[key]
        cache: dict[str, tuple[Any, Any]] = self.__dict__.setdefault("_fusion_tables", {})
        if key not in cache or cache[key][0] is not table:
            try:
                cache[key] = (table, build(table))
            except (KeyError, TypeError, ValueError) as exc:
                raise ModelFileError(f"{self.path}: oibar.fusion.{key} is malformed ({exc})") from exc
        return cache[key][1]

    def _error_model(self, f: dict[str, Any]) -> KeypointErrorModel:
        """The fusion's KeypointErrorModel (one row per keypoint of this model)."""
        model: KeypointErrorModel = self._fusion_table(f, "kp_error_model", KeypointErrorModel)
        if model.rms_crop_px.shape[0] != len(self.points_m):
            raise ModelFileError(
                f"{self.path}: oibar.fusion.kp_error_model has {model.rms_crop_px.shape[0]} "
                f"keypoints, the model {len(self.points_m)}"
            )
        return model

    def _prior_error_model(self, f: dict[str, Any]) -> PriorErrorModel:
        """The fusion's PriorErrorModel."""
        model: PriorErrorModel = self._fusion_table(f, "prior_error_model", PriorErrorModel)
        return model

    def _head_gain(self, f: dict[str, Any]) -> HeadGainModel:
        """The fusion's HeadGainModel."""
        model: HeadGainModel = self._fusion_table(f, "head_gain", HeadGainModel)
        return model

    uses_prior = True
    turned_reading_deg = 0.0  # read_crop's turned readings (set from the export in __init__)
    turned_reading_head = False  # and the head read on each of them (idem)
    turned_reading_measurement = "mean"  # and whose keypoints the filter's fit uses (idem)
    placed_pass_refines = False  # a predicted crop read as the refining pass (idem)
    corner_refine_side_px = 0.0  # refined_corners' size gate, 0: off (idem)
    corner_idx = np.zeros(0, int)
    far_session: Any = None  # the far network's session (``oibar.far_network``), None: one network
    far_from_m = np.inf  # the head-on range from which it reads a window
    cold_crop_budget: int | None = COLD_CROP_BUDGET  # (set in __init__)
    overlap_first_pass = False  # the direct model on its own thread while the placed crop is read (idem)
    _first_pass_thread: tuple[int, ThreadPoolExecutor] | None = None  # (its process id, the thread)
    _cold: ColdSearch | None = None  # a cold search that goes on in the next frames (solve)

    def forget(self) -> None:
        self.fit_history.forget()
        self._cold = None

    def estimate(
        self,
        image_rgb_uint8: np.ndarray,
        t_s: float = 0.0,
        prior: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> PoseEstimate:
        """One frame -> pose; `prior` (R_cam_target, T_cam_target_m), the pose predicted for this
        frame (the daemon passes its filter's), places the first crop (see solve)."""
        if not np.isfinite(t_s):
            raise FrameError(f"frame time t_s must be finite, got {t_s}")
        self.check_frame(image_rgb_uint8)
        prior = _checked_prior(prior)
        t0 = time.perf_counter()
        self.fit_history.advance(float(t_s))
        # a cold search carried from earlier frames (solve) goes on while its scores still hold,
        # and never across a frame whose time does not advance (a new sequence)
        cold = self._cold
        if cold is not None and not cold.t_last_s < t_s <= cold.t_first_s + COLD_CARRY_MAX_AGE_S:
            self._cold = None
        if float(image_rgb_uint8[::4, ::4].std()) < MIN_FRAME_STD_DN:
            nan = np.full(3, np.nan)
            return PoseEstimate(
                nan,
                np.full(4, np.nan),
                np.full((3, 3), np.nan),
                float(t_s),
                (time.perf_counter() - t0) * 1e3,
                0.0,
                float("nan"),
                0.0,
                ("blank_frame",),
            )
        # without a prediction, the estimator's own latest strong fit places the first crop: the
        # filter waits for a run of them (fit_history) when the direct model disagrees, and each
        # cold frame would otherwise pay for the whole search again
        hint = self.fit_history.latest() if prior is None else None
        pool = self._first_pass_pool() if self.overlap_first_pass else None
        win_p = self._placed_window(prior if prior is not None else hint) if pool is not None else None
        placed_reading: tuple[CropWindow, CropReading] | None = None
        if pool is not None and win_p is not None:
            job = pool.submit(self.first.estimate, image_rgb_uint8, t_s)
            try:
                placed_reading = (win_p, self.read_crop(image_rgb_uint8, win_p, self.placed_pass_refines))
            finally:
                direct = job.result()  # never leave it running into the next frame
        else:
            direct = self.first.estimate(image_rgb_uint8, t_s)
        if not direct.finite or direct.confidence <= 0.0:
            direct.latency_ms = (time.perf_counter() - t0) * 1e3
            direct.flags = tuple(direct.flags) + ("no_first_pass",)
            return direct
        r, win = self.solve(
            image_rgb_uint8,
            direct.R_cam_target,
            direct.T_cam_target_m,
            prior=prior,
            hint=hint,
            placed_reading=placed_reading,
        )
        # the cold search ran out of this frame's crops and goes on in the next frames: the answer
        # (no strong fit, so its confidence is already low) is provisional
        searching: tuple[str, ...] = ()
        if self._cold is not None:
            searching = ("searching",)
            if np.isnan(self._cold.t_first_s):
                self._cold.t_first_s = float(t_s)
            self._cold.t_last_s = float(t_s)
        if r is None or win is None:
            latency_ms = (time.perf_counter() - t0) * 1e3
            direct.latency_ms = latency_ms
            direct.confidence *= FALLBACK_FACTOR
            direct.flags = tuple(direct.flags) + ("pnp_failed", "fallback_direct") + searching
            return direct
        R, T = r.pose()
        latency_ms = (time.perf_counter() - t0) * 1e3
        conf, rng_m, _, checks = self.plausibility(T, R, None)
        flags = list(checks)
        rms_crop = fit_rms_crop_px(r, win)
        conf *= float(np.exp(-0.5 * (rms_crop / REPROJ_SCALE_CROP_PX) ** 2))
        if rms_crop > REPROJ_SCALE_CROP_PX:
            flags.append("reprojection")
        if rms_crop > STRONG_FIT_RMS_CROP_PX:  # the search found nothing better (solve)
            conf *= FALLBACK_FACTOR
            flags.append("weak_fit")
        flags += searching
        dpos = float(np.linalg.norm(T - direct.T_cam_target_m)) / max(rng_m, 1e-6)
        datt = rotation_angle_deg(R.T @ direct.R_cam_target)
        strong = rms_crop <= STRONG_FIT_RMS_CROP_PX
        if dpos > DISAGREE_POS_FRACTION or datt > DISAGREE_ATT_DEG:
            # one frame cannot tell which is wrong; a run of strong fits that agree can (fit_history)
            if strong and self.fit_history.confirmed(t_s, T, R):
                flags.append("direct_overruled")
            else:
                conf *= FALLBACK_FACTOR
                flags.append("direct_disagrees")
        if strong:
            self.fit_history.add(t_s, T, R)
        q = matrix_to_quat(R)
        T_meas, R_meas = (
            measurement_without_prior(r, T, R) if self.filter_measurement == "prior_free" else (None, None)
        )
        return PoseEstimate(
            T_cam_target_m=T,
            q_cam_target=q,
            R_cam_target=R,
            t_s=float(t_s),
            latency_ms=latency_ms,
            confidence=float(np.clip(conf, 0.0, 1.0)),
            camera_range_m=rng_m,
            ortho_defect=0.0,
            flags=tuple(flags),
            T_meas_cam_target_m=T_meas,
            R_meas_cam_target=R_meas,
        )

    def __call__(self, frame: Image.Image | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        e = self.estimate(np.asarray(frame))
        return e.T_cam_target_m, e.q_cam_target

    def predict_batch(self, frames_uint8_small: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise TypeError("a keypoint model has no batch interface on resized frames; use estimate(frame)")


def benchmark(
    path: str | Path, threads: int = 2, seconds: float = 5.0, with_preprocess: bool = True
) -> dict[str, Any]:
    """Single-stream latency on this machine: one 744x480 frame at a time, as in flight."""
    est = PoseEstimator(path, threads)
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
    return {
        "threads": threads,
        "runs": len(lat),
        "mean_ms": float(lat_ms.mean()),
        "median_ms": float(np.median(lat_ms)),
        "p95_ms": float(np.percentile(lat_ms, 95)),
        "inferences_per_s": float(1e3 / lat_ms.mean()),
        "with_preprocess": with_preprocess,
    }
