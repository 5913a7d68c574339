"""OibarNet: backbone -> dropout -> global average pooling -> two fully-connected heads
(position 3-vector in metres, attitude as Zhou et al.'s 6D representation), SPEC section 5.

Backbones (all written here and trained from scratch: no pretrained weights are reachable):
  squeezenet  SqueezeNet 1.1 layout (fire modules), with batch norm for training from scratch
  darknet19   YOLOv2's Darknet-19 feature extractor (the paper's baseline)
  darknet53   YOLOv3's Darknet-53 (residual)
  resnet101   ResNet-101 (bottleneck blocks 3-4-23-3; the paper's best)
  oibar_lite  ours: a small residual net sized for 2 CPU cores at >= 30 inferences/s
The input is an RGB image in [0, 1] at the configured size; normalisation is part of the graph
so the exported model needs no separate constants.
"""

from __future__ import annotations

import torch
import torch.nn as nn

from .geometry import matrix_from_rot6d, quat_from_matrix

INPUT_MEAN = (0.5, 0.5, 0.5)  # from-scratch training: a fixed, documented normalisation
INPUT_STD = (0.25, 0.25, 0.25)


def conv_bn(cin: int, cout: int, k: int = 3, s: int = 1, act: str = "relu", groups: int = 1) -> nn.Sequential:
    layers = [nn.Conv2d(cin, cout, k, s, k // 2, groups=groups, bias=False), nn.BatchNorm2d(cout)]
    if act == "relu":
        layers.append(nn.ReLU(inplace=True))
    elif act == "leaky":
        layers.append(nn.LeakyReLU(0.1, inplace=True))
    return nn.Sequential(*layers)


# ----------------------------------------------------------------------------- SqueezeNet 1.1
class Fire(nn.Module):
    def __init__(self, cin: int, squeeze: int, expand: int):
        super().__init__()
        self.squeeze = conv_bn(cin, squeeze, 1)
        self.e1 = conv_bn(squeeze, expand, 1)
        self.e3 = conv_bn(squeeze, expand, 3)

    def forward(self, x):
        s = self.squeeze(x)
        return torch.cat([self.e1(s), self.e3(s)], 1)


def squeezenet() -> tuple[nn.Module, int]:
    pool = lambda: nn.MaxPool2d(3, 2, ceil_mode=True)  # noqa: E731
    net = nn.Sequential(
        conv_bn(3, 64, 3, 2),
        pool(),
        Fire(64, 16, 64),
        Fire(128, 16, 64),
        pool(),
        Fire(128, 32, 128),
        Fire(256, 32, 128),
        pool(),
        Fire(256, 48, 192),
        Fire(384, 48, 192),
        Fire(384, 64, 256),
        Fire(512, 64, 256),
    )
    return net, 512


# ----------------------------------------------------------------------------- Darknet-19 / -53
def darknet19() -> tuple[nn.Module, int]:
    L = lambda a, b, k=3: conv_bn(a, b, k, act="leaky")  # noqa: E731
    mp = lambda: nn.MaxPool2d(2, 2)  # noqa: E731
    net = nn.Sequential(
        L(3, 32),
        mp(),
        L(32, 64),
        mp(),
        L(64, 128),
        L(128, 64, 1),
        L(64, 128),
        mp(),
        L(128, 256),
        L(256, 128, 1),
        L(128, 256),
        mp(),
        L(256, 512),
        L(512, 256, 1),
        L(256, 512),
        L(512, 256, 1),
        L(256, 512),
        mp(),
        L(512, 1024),
        L(1024, 512, 1),
        L(512, 1024),
        L(1024, 512, 1),
        L(512, 1024),
    )
    return net, 1024


class DarkResidual(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.body = nn.Sequential(conv_bn(c, c // 2, 1, act="leaky"), conv_bn(c // 2, c, 3, act="leaky"))

    def forward(self, x):
        return x + self.body(x)


def darknet53() -> tuple[nn.Module, int]:
    layers: list[nn.Module] = [conv_bn(3, 32, 3, act="leaky")]
    c = 32
    for n in (1, 2, 8, 8, 4):
        layers.append(conv_bn(c, 2 * c, 3, 2, act="leaky"))
        c *= 2
        layers += [DarkResidual(c) for _ in range(n)]
    return nn.Sequential(*layers), 1024


# ----------------------------------------------------------------------------- ResNet-101
class Bottleneck(nn.Module):
    def __init__(self, cin: int, width: int, stride: int):
        super().__init__()
        cout = 4 * width
        self.body = nn.Sequential(
            conv_bn(cin, width, 1), conv_bn(width, width, 3, stride), conv_bn(width, cout, 1, act="none")
        )
        self.skip = (
            nn.Identity() if (cin == cout and stride == 1) else conv_bn(cin, cout, 1, stride, act="none")
        )
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x):
        return self.relu(self.body(x) + self.skip(x))


def resnet101() -> tuple[nn.Module, int]:
    layers: list[nn.Module] = [conv_bn(3, 64, 7, 2), nn.MaxPool2d(3, 2, 1)]
    cin = 64
    for width, n, stride in ((64, 3, 1), (128, 4, 2), (256, 23, 2), (512, 3, 2)):
        for i in range(n):
            layers.append(Bottleneck(cin, width, stride if i == 0 else 1))
            cin = 4 * width
    return nn.Sequential(*layers), 2048


# ----------------------------------------------------------------------------- ours: oibar_lite
class BasicBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.body = nn.Sequential(conv_bn(cin, cout, 3, stride), conv_bn(cout, cout, 3, act="none"))
        self.skip = (
            nn.Identity() if (cin == cout and stride == 1) else conv_bn(cin, cout, 1, stride, act="none")
        )
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x):
        return self.relu(self.body(x) + self.skip(x))


def oibar_lite(width: float = 1.0, in_ch: int = 3) -> tuple[nn.Module, int]:
    """Two cheap stride-2 convolutions, then four residual stages (output stride 32). At 248x160
    and width 1 it has 1.6 M parameters and runs at 60-150 inferences/s on 2 shared CPU cores
    with onnxruntime (measured, docs/model_history.md)."""
    ch = [max(8, int(round(c * width / 8)) * 8) for c in (16, 32, 48, 96, 192)]
    layers: list[nn.Module] = [conv_bn(in_ch, ch[0], 3, 2), conv_bn(ch[0], ch[1], 3, 2)]
    cin = ch[1]
    for cout, n in zip(ch[1:], (1, 2, 2, 2), strict=True):
        for i in range(n):
            layers.append(BasicBlock(cin, cout, 2 if (i == 0 and cout != ch[1]) else 1))
            cin = cout
    return nn.Sequential(*layers), cin


BACKBONES = {
    "squeezenet": squeezenet,
    "darknet19": darknet19,
    "darknet53": darknet53,
    "resnet101": resnet101,
    "oibar_lite": oibar_lite,
}


# ----------------------------------------------------------------------------- OibarNet
class OibarNet(nn.Module):
    """forward(image) -> (T_cam_target_m (N, 3), rot6d (N, 6)).

    The position head predicts a standardised value that fixed buffers (mean and spread of the
    training labels) turn back into metres, so the graph's output is already in metres; the 6D
    head starts at the mean attitude. Both only condition the start of training."""

    def __init__(
        self,
        backbone: str = "oibar_lite",
        width: float = 1.0,
        dropout: float = 0.2,
        coord_channels: bool = False,
        pos_mean_m=(0.0, 0.1, 5.0),
        pos_std_m=(0.5, 0.5, 3.0),
        rot6d_mean=(1.0, 0.0, 0.0, 0.0, 1.0, 0.0),
        pos_param: str = "metres",
        uvlogz_mean=(0.0, 0.0, 1.4),
        uvlogz_std=(0.1, 0.1, 0.8),
        keypoints: int = 0,
    ):
        super().__init__()
        if pos_param not in ("metres", "uvlogz"):
            raise ValueError(f"unknown pos_param {pos_param!r}; choose metres or uvlogz")
        self.pos_param = pos_param
        if backbone not in BACKBONES:
            raise ValueError(f"unknown backbone {backbone!r}; choose one of {sorted(BACKBONES)}")
        self.backbone_name = backbone
        self.coord_channels = coord_channels
        in_ch = 5 if coord_channels else 3
        if backbone == "oibar_lite":
            self.backbone, feat = oibar_lite(width, in_ch)
        else:
            self.backbone, feat = BACKBONES[backbone]()
            if coord_channels:  # widen the stem's first convolution to take the (u, v) maps
                first = self.backbone[0][0]
                self.backbone[0][0] = nn.Conv2d(
                    in_ch, first.out_channels, first.kernel_size, first.stride, first.padding, bias=False
                )
        # Optional soft-argmax branch (our addition, model.keypoints > 0): K heat maps on the
        # stride-16 features, each reduced to its expected image position (u, v). Global average
        # pooling keeps *what* is seen but blurs *where*; a GAP network trained on our data
        # learned range well but barely followed lateral shifts (docs/model_history.md). The 2K
        # coordinates join the pooled features in front of the same two heads.
        self.keypoints = int(keypoints)
        if self.keypoints:
            if backbone == "oibar_lite":
                self.kp_tap, mid_ch = (
                    7,
                    self.backbone[6].body[1][0].out_channels,
                )  # end of the stride-16 stage
            else:
                self.kp_tap, mid_ch = len(self.backbone), feat
            self.kp_conv = nn.Sequential(conv_bn(mid_ch, mid_ch, 3), nn.Conv2d(mid_ch, self.keypoints, 1))
        self.feature_dim = feat + 2 * self.keypoints
        self.dropout = nn.Dropout(dropout)  # the paper: dropout, then GAP
        self.pool = nn.AdaptiveAvgPool2d(1)
        self.head_t = nn.Linear(self.feature_dim, 3)
        self.head_r = nn.Linear(self.feature_dim, 6)
        self.register_buffer("input_mean", torch.tensor(INPUT_MEAN).view(1, 3, 1, 1))
        self.register_buffer("input_std", torch.tensor(INPUT_STD).view(1, 3, 1, 1))
        self.register_buffer("pos_mean_m", torch.tensor(pos_mean_m, dtype=torch.float32))
        self.register_buffer("pos_std_m", torch.tensor(pos_std_m, dtype=torch.float32))
        self.register_buffer("uvlogz_mean", torch.tensor(uvlogz_mean, dtype=torch.float32))
        self.register_buffer("uvlogz_std", torch.tensor(uvlogz_std, dtype=torch.float32))
        nn.init.zeros_(self.head_t.weight)
        nn.init.zeros_(self.head_t.bias)
        nn.init.normal_(self.head_r.weight, std=1e-3)
        with torch.no_grad():
            self.head_r.bias.copy_(torch.tensor(rot6d_mean, dtype=torch.float32))

    def features(self, image: torch.Tensor) -> torch.Tensor:
        x = (image - self.input_mean) / self.input_std
        if self.coord_channels:
            n, _, h, w = x.shape
            v = torch.linspace(-1, 1, h, device=x.device, dtype=x.dtype).view(1, 1, h, 1).expand(n, 1, h, w)
            u = torch.linspace(-1, 1, w, device=x.device, dtype=x.dtype).view(1, 1, 1, w).expand(n, 1, h, w)
            x = torch.cat([x, u, v], 1)
        if not self.keypoints:
            return self.pool(self.dropout(self.backbone(x))).flatten(1)
        mid = self.backbone[: self.kp_tap](x)
        f = self.pool(self.dropout(self.backbone[self.kp_tap :](mid))).flatten(1)
        return torch.cat([f, soft_argmax(self.kp_conv(mid))], 1)

    def decode_position(self, raw: torch.Tensor) -> torch.Tensor:
        """Position head output (standardised) -> T_cam_target in metres."""
        if self.pos_param == "metres":
            return raw * self.pos_std_m + self.pos_mean_m
        p = raw * self.uvlogz_std + self.uvlogz_mean
        z = torch.exp(p[..., 2:3].clamp(-5.0, 5.0))
        return torch.cat([p[..., 0:2] * z, z], -1)

    def heads(self, f: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.decode_position(self.head_t(f)), self.head_r(f)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.heads(self.features(image))


def soft_argmax(logits: torch.Tensor) -> torch.Tensor:
    """(N, K, h, w) heat-map logits -> (N, 2K): the expected (u..., v...) of each map's softmax,
    in [-1, 1] across the image (cell centres)."""
    n, k, h, w = logits.shape
    p = torch.softmax(logits.flatten(2), -1).view(n, k, h, w)
    gu = torch.linspace(-1 + 1 / w, 1 - 1 / w, w, device=logits.device, dtype=logits.dtype)
    gv = torch.linspace(-1 + 1 / h, 1 - 1 / h, h, device=logits.device, dtype=logits.dtype)
    u = (p.sum(2) * gu).sum(-1)
    v = (p.sum(3) * gv).sum(-1)
    return torch.cat([u, v], 1)


def widen_heads_from(net: OibarNet, state: dict) -> dict:
    """A checkpoint of the same net without the keypoint branch -> a state dict for ``net``:
    the heads' extra input columns start at zero, so the widened net starts out computing
    exactly what the old one did."""
    out = dict(state)
    for name in ("head_t", "head_r"):
        w_old = state[f"{name}.weight"]
        w_new = torch.zeros_like(getattr(net, name).weight)
        w_new[:, : w_old.shape[1]] = w_old
        out[f"{name}.weight"] = w_new
    for k, v in net.state_dict().items():
        if k.startswith("kp_conv.") and k not in out:
            out[k] = v
    return out


class TemporalOibarNet(nn.Module):
    """The paper's temporal study: a BiLSTM (1-3 layers) on the per-frame CNN features of a
    clip, then the same two heads per frame. forward(clip (N, T, 3, H, W)) -> (N, T, 3), (N, T, 6).
    Hook only: the study itself (train the CNN, freeze it, train this on feature sequences) is
    not run yet."""

    def __init__(self, cnn: OibarNet, layers: int = 1, hidden: int = 128, freeze_cnn: bool = True):
        super().__init__()
        if not 1 <= layers <= 3:
            raise ValueError("the paper's study uses 1 to 3 BiLSTM layers")
        self.cnn = cnn
        if freeze_cnn:
            for p in self.cnn.parameters():
                p.requires_grad_(False)
        self.lstm = nn.LSTM(cnn.feature_dim, hidden, num_layers=layers, batch_first=True, bidirectional=True)
        self.head_t = nn.Linear(2 * hidden, 3)
        self.head_r = nn.Linear(2 * hidden, 6)
        with torch.no_grad():  # start from the CNN's own answer for the mean feature
            self.head_r.bias.copy_(cnn.head_r.bias)

    def forward(self, clip: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        n, t = clip.shape[:2]
        f = self.cnn.features(clip.flatten(0, 1)).view(n, t, -1)
        h, _ = self.lstm(f)
        return self.cnn.decode_position(self.head_t(h)), self.head_r(h)


class PoseOutputs(nn.Module):
    """The exported graph: image -> position_m, q_cam_target (w, x, y, z; w >= 0),
    R_cam_target, rot6d."""

    def __init__(self, net: OibarNet):
        super().__init__()
        self.net = net

    def forward(self, image: torch.Tensor):
        t, r6 = self.net(image)
        R = matrix_from_rot6d(r6)
        return t, quat_from_matrix(R), R, r6


def build_model(
    mcfg, pos_mean_m=None, pos_std_m=None, rot6d_mean=None, uvlogz_mean=None, uvlogz_std=None
) -> OibarNet:
    kw = {"pos_param": getattr(mcfg, "pos_param", "metres"), "keypoints": getattr(mcfg, "keypoints", 0)}
    for name, val in (("uvlogz_mean", uvlogz_mean), ("uvlogz_std", uvlogz_std)):
        if val is not None:
            kw[name] = tuple(float(x) for x in val)
    if pos_mean_m is not None:
        kw["pos_mean_m"] = tuple(float(x) for x in pos_mean_m)
    if pos_std_m is not None:
        kw["pos_std_m"] = tuple(float(x) for x in pos_std_m)
    if rot6d_mean is not None:
        kw["rot6d_mean"] = tuple(float(x) for x in rot6d_mean)
    return OibarNet(mcfg.backbone, mcfg.width, mcfg.dropout, mcfg.coord_channels, **kw)


def count_parameters(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())
