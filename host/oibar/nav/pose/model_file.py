"""An exported OibarNet file: its ``oibar.*`` metadata and its onnxruntime session.

The ONNX file (oibar_models.export, oibar_models.kp_export) carries its own input size,
normalisation, camera intrinsics and output convention as ``oibar.*`` metadata; the estimator
reads everything from it, so any export works without code changes. A bad file is a
:class:`ModelFileError` naming it, raised when the estimator is built, never in flight.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

METADATA_PREFIX = "oibar."

# Camera-distance envelope used when the model's metadata does not state its training range
# (exports up to model version 0.1.0 do not): the synthetic campaign spans 0.4-10.4 m, widened
# so only physically absurd answers are flagged.
DEFAULT_RANGE_LIMITS_M = (0.2, 20.0)


class ModelFileError(RuntimeError):
    """The model file is missing, damaged, or not an OibarNet ONNX export."""


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


# The files an export names, which must lie beside it (its role -> the metadata key naming it):
# the first pass (a file name), the far network and the fixture finder ({"file": name}).
COMPANION_ROLES = {"first_pass": "first pass", "far_network": "far network", "finder": "finder"}


def companion_files(meta: dict[str, Any]) -> dict[str, str]:
    """The files an export's metadata names beside it, by role (COMPANION_ROLES' keys, in that
    order); a role the export does not have is left out."""
    out = {}
    for key in COMPANION_ROLES:
        v = meta.get(key)
        name = v.get("file") if isinstance(v, dict) else v
        if isinstance(name, str) and name:
            out[key] = name
    return out


def export_flag(path: Path, meta: dict[str, Any], key: str, given: bool | None) -> bool:
    """An on/off reading option: `given`, else as the export says (off without the key); a
    value that is not true or false is a damaged export."""
    flag = meta.get(key, False) if given is None else given
    if not isinstance(flag, bool):
        raise ModelFileError(f"{path}: oibar.{key} must be true or false, got {flag!r}")
    return flag


def range_limits(meta: dict[str, Any], given: tuple[float, float] | None) -> tuple[float, float]:
    """The camera-distance envelope: as given, else the export's training range, else the default."""
    limits = given if given is not None else tuple(meta.get("train_range_m", DEFAULT_RANGE_LIMITS_M))
    lo, hi = (float(v) for v in limits)
    if not 0 <= lo < hi:
        raise ValueError(f"range_limits_m must be (low, high) with 0 <= low < high, got {limits}")
    return lo, hi


def open_session(path: Path, threads: int, allow_spinning: bool) -> Any:
    """onnxruntime's CPU session for the file, set for one frame at a time on a small shared CPU."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    # A fixed thread count, no inter-op parallelism (the graph is a chain).
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
