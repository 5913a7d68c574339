"""Experiment configuration: one YAML file per experiment (models/configs/*.yaml).

Every field has a default here, so a config only states what differs. Unknown keys are an error
(a typo must not silently fall back to a default). Paths in a config are relative to the
repository root unless absolute.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import yaml

from oibar.geometry.fixture import fixture_corners_t

REPO_ROOT = Path(__file__).resolve().parents[2]


class ConfigError(ValueError):
    """A config file is missing, unreadable or holds unknown / ill-typed keys."""


@dataclass
class DataConfig:
    root: str = "data/synthetic"  # output of `make dataset` (oibar_hil.dataset)
    train_seqs: list[int] = field(default_factory=lambda: [2, 3, 4, 5, 6, 7, 9, 10, 11, 12])
    test_seqs: list[int] = field(default_factory=lambda: [1, 8])  # the paper: test only
    extra_test_dirs: list[str] = field(default_factory=list)  # e.g. an envelope sequence
    val_fraction: float = 0.2  # the paper's 80/20 split by sub-sequences
    chunk_lengths: list[int] = field(default_factory=lambda: [64, 128, 256, 512, 1024])
    split_seed: int = 0
    frame_stride: int = 1  # keep every n-th frame (quick experiments)
    cache_dir: str = "data/cache"  # decoded, resized frames (uint8 .npy) per sequence
    verify_hashes: bool = False  # re-hash every frame against the manifest first


@dataclass
class AugmentConfig:
    enabled: bool = True
    p_photometric: float = 0.8
    brightness: float = 0.3  # +- fraction
    contrast: float = 0.3  # +- fraction
    colour: float = 0.1  # +- per-channel gain
    noise_sigma_max: float = 0.03  # Gaussian noise, fraction of full scale
    p_blur: float = 0.3
    blur_sigma_max_px: float = 1.0  # at the network's input size
    p_pose: float = 0.7
    inplane_deg: float = 15.0  # rotation about the optical axis (principal point)
    offplane_deg: float = 4.0  # camera pitch / yaw: image shift + homography


@dataclass
class ModelConfig:
    backbone: str = "oibar_lite"  # see nets.BACKBONES
    width: float = 1.0  # channel multiplier (oibar_lite)
    input_width_px: int = 248  # 744x480 / 3: keeps the aspect and square pixels
    input_height_px: int = 160
    dropout: float = 0.2  # the paper
    coord_channels: bool = False  # append normalised (u, v) maps to the input
    # How the position head is parameterised (the graph's output is metres either way):
    #   metres: standardised (x, y, z);  uvlogz: (x/z, y/z, ln z), i.e. where the fixture is in
    #   the image and how far, which a convolutional net reads off far more directly
    pos_param: str = "metres"
    keypoints: int = 0  # >0: soft-argmax branch with this many heat maps (nets.py)
    # points of the fixture (F_t, metres) whose projections supervise the first heat maps when
    # train.kp_loss is on: the origin (drogue centre) and the four corners of the 0.50 x 0.36 m rim
    keypoints_3d_m: list = field(default_factory=lambda: [[0.0, 0.0, 0.0]] + fixture_corners_t().tolist())
    temporal_layers: int = 0  # >0: BiLSTM back-end on the CNN features (study)


@dataclass
class TrainConfig:
    epochs: int = 100  # the paper
    batch_size: int = 32
    lr_max: float = 1e-3
    lr_min: float = 1e-5
    lr_cycles: int = 5  # the paper: cyclical learning rate, 5 cycles
    lr_cycle_decay: float = 0.5  # peak of each cycle relative to the previous one
    weight_decay: float = 0.0
    init_s_r: float = 0.0  # learned log-std of the attitude term
    init_s_t: float = 0.0  # learned log-std of the position term
    # L_t over the batch: metres (the paper's ||t_hat - t||) or range_normalised (||t_hat - t|| /
    # ||t||, the paper's evaluation metric: otherwise the 10 m frames dominate the gradient)
    pos_loss: str = "metres"
    # start from another run's weights (a checkpoint of the same backbone; heads widened when this
    # config adds the keypoint branch): a second training stage
    init_from: str = ""
    # supervise heat maps with the projected fixture points (our addition): a direct, dense
    # signal for *where* the fixture is, which the pose heads then read
    kp_loss: bool = False
    workers: int = 1  # DataLoader worker processes
    threads: int = 0  # torch intra-op threads (0: leave torch's default)
    seed: int = 0
    max_steps_per_epoch: int = 0  # >0: cap (smoke runs, time-boxed runs)
    val_max_frames: int = 0  # >0: evaluate validation on a subset per epoch
    device: str = "auto"  # auto | cpu | cuda


@dataclass
class ExportConfig:
    opset: int = 17
    model_version: str = "0.1.0"
    onnx_path: str = ""  # default: models/<name>.onnx
    int8: bool = False  # also write a statically quantised INT8 model


class RunPaths:
    """Paths of a config relative to the repository root, and its run folder (runs/<name>)."""

    name: str
    run_dir: str

    def path(self, p: str) -> Path:
        q = Path(p)
        return q if q.is_absolute() else REPO_ROOT / q

    @property
    def run_path(self) -> Path:
        return self.path(self.run_dir or f"runs/{self.name}")


@dataclass
class ExperimentConfig(RunPaths):
    name: str = "oibarnet_lite"
    run_dir: str = ""  # default: runs/<name>
    data: DataConfig = field(default_factory=DataConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    export: ExportConfig = field(default_factory=ExportConfig)

    @property
    def onnx_file(self) -> Path:
        return self.path(self.export.onnx_path or f"models/{self.name}.onnx")

    def to_dict(self) -> dict:
        return asdict(self)


def _build(cls, data: dict, where: str):
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; known: {sorted(known)}")
    kwargs = {}
    for name, value in data.items():
        f = known[name]
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default):
            kwargs[name] = _build(type(default), value or {}, f"{where}.{name}")
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise ConfigError(f"{where}.{name}: expected true/false, got {value!r}")
            kwargs[name] = value
        elif isinstance(default, (int, float)) and not isinstance(default, bool):
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                raise ConfigError(f"{where}.{name}: expected a number, got {value!r}")
            kwargs[name] = type(default)(value)
        elif isinstance(default, list):
            if not isinstance(value, list):
                raise ConfigError(f"{where}.{name}: expected a list, got {value!r}")
            kwargs[name] = value
        else:
            kwargs[name] = value
    return cls(**kwargs)


def from_dict(data: dict, where: str = "config") -> ExperimentConfig:
    return _build(ExperimentConfig, data, where)


def read_yaml(path: str | Path, overrides: dict | None = None) -> dict:
    """A YAML config file as a dict, `overrides` (nested dict) merged over it; ConfigError naming
    the file when it is missing or not YAML."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file not found: {p}")
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML ({exc})") from exc
    return _merge(data, overrides) if overrides else data


def load_config(path: str | Path, overrides: dict | None = None) -> ExperimentConfig:
    """Read a YAML experiment config. `overrides` (nested dict) wins over the file."""
    return from_dict(read_yaml(path, overrides), where=str(path))


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out.get(k) or {}, v) if isinstance(v, dict) else v
    return out


def parse_override(items: list[str]) -> dict:
    """`train.epochs=3 data.root=/tmp/x` -> nested dict (values parsed as YAML scalars)."""
    out: dict = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"override {item!r}: expected section.key=value")
        key, value = item.split("=", 1)
        node = out
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = yaml.safe_load(value)
    return out
