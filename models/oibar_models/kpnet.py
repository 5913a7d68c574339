"""OibarNet-KP: heat maps of known fixture points on a full-resolution crop, for PnP.

Backbone: EfficientNet-Lite0 with its ImageNet weights (efficientnet_lite.py). A light top-down
path merges the stride-32/16/8/4 maps into one stride-4 map (64 channels) and a 3x3 + 1x1 head
turns it into one heat map per keypoint. Soft-argmax (the expectation of the softmax over the map)
gives sub-pixel positions, differentiable end to end; the softmax's spread is the keypoint's
uncertainty. A second small head says, per keypoint, whether it is inside the crop at all.

The keypoints are the fixture's own corners and centres (FIXTURE_KEYPOINTS), chosen so that
some stay in view down to contact (pin guides, connector corners, drogue centre) and the widest
span sets the range at 10 m (rim corners). All front-face points lie within 12 mm of one plane,
so their tilt barely shows: at 1.5 m a 1 deg tilt moves the rim corners by ~0.15 crop px, less
than the keypoints' own error. The drogue's throat, 0.18 m deep inside the funnel, moves ~0.6
crop px per degree at any range: it is the one point that carries the attitude (model 0.5.0).
It hides behind the funnel wall when seen more than ~29 deg off the fixture's axis
(KEYPOINT_VIEW_LIMIT_DEG, used for the training labels' visibility).

A third head (model 0.6.0) regresses the fixture's attitude as the crop shows it: the rotation
vector, in degrees, of R_crop_target R_ref^T, where R_crop_target is the target's attitude in
the crop's own camera (boresight through the window centre, turned with the window;
`oibar.nav.keypoints.R_crop_cam`) and R_ref the aligned vehicles' attitude. It can replace the
248x160 direct model as the attitude prior of the keypoint fit: beyond 8 m the keypoints alone
cannot tell a degree of tilt, and the prior decides the attitude there.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from oibar.geometry.fixture import FIXTURE_KEYPOINTS, KEYPOINT_VIEW_LIMIT_DEG

from .efficientnet_lite import EfficientNetLite, load_pretrained

STRIDE = 4
ATT_CHANNELS, ATT_GRID = 64, 4


class GridResize(nn.Module):
    """Resample a map to g x g (bilinear). At the shipped 128 px crop the stride-32 map is 4x4
    already (identity); other crop sizes work too, which adaptive pooling cannot export to ONNX
    when g does not divide the map."""

    def __init__(self, g: int):
        super().__init__()
        self.g = g

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.interpolate(x, size=(self.g, self.g), mode="bilinear", align_corners=False)


class KeypointNet(nn.Module):
    def __init__(self, n_keypoints: int = len(FIXTURE_KEYPOINTS), width: int = 64, pretrained: bool = True):
        super().__init__()
        bb = EfficientNetLite()
        if pretrained:
            load_pretrained(bb)
        # the ImageNet classifier proved the load; the dense head does not use it
        del bb._conv_head, bb._bn1, bb._fc
        self.backbone = bb
        self.lateral = nn.ModuleList(nn.Conv2d(c, width, 1) for c in bb.tap_channels)
        self.head = nn.Sequential(
            nn.Conv2d(width, width, 3, padding=1, bias=False),
            nn.BatchNorm2d(width),
            nn.ReLU(inplace=True),
            nn.Conv2d(width, n_keypoints, 1),
        )
        self.present = nn.Linear(bb.tap_channels[-1], n_keypoints)
        # attitude: the stride-32 map keeps a 4x4 layout (pooling it flat would lose where the
        # shading and the rim's foreshortening are), then two linear layers
        self.attitude = nn.Sequential(
            nn.Conv2d(bb.tap_channels[-1], ATT_CHANNELS, 1),
            nn.ReLU(inplace=True),
            GridResize(ATT_GRID),
            nn.Flatten(),
            nn.Linear(ATT_CHANNELS * ATT_GRID * ATT_GRID, 128),
            nn.ReLU(inplace=True),
            nn.Linear(128, 3),
        )
        self.n_keypoints = n_keypoints

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """RGB [0, 1] (N, 3, S, S) -> heat-map logits (N, K, S/4, S/4), presence logits (N, K),
        attitude in the crop (N, 3): rotation vector of R_crop_target R_ref^T, degrees."""
        return self.read_taps(self.backbone.features(x))

    def read_taps(self, taps: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The heads on the backbone's maps (`forward` after the backbone): a fine-tune that
        holds the maps themselves reads them once."""
        y = self.lateral[-1](taps[-1])
        for lat, tap in zip(reversed(self.lateral[:-1]), reversed(taps[:-1]), strict=True):
            y = F.interpolate(y, size=tap.shape[-2:], mode="bilinear", align_corners=False) + lat(tap)
        heat = self.head(y)
        present = self.present(taps[-1].mean(dim=(2, 3)))
        return heat, present, self.attitude(taps[-1])


def view_limits_deg(names: list[str] | tuple[str, ...]) -> list[float]:
    """Per keypoint, the largest angle off the fixture's axis it is seen from (inf: any)."""
    return [KEYPOINT_VIEW_LIMIT_DEG.get(n, float("inf")) for n in names]


def soft_argmax(heat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Logits (N, K, H, W) -> (positions (N, K, 2) in crop pixels, corner convention;
    spread (N, K) in crop pixels, the RMS distance of the distribution from its mean;
    log-probabilities (N, K, H, W))."""
    n, k, h, w = heat.shape
    logp = F.log_softmax(heat.reshape(n, k, h * w), dim=-1)
    p = logp.exp().reshape(n, k, h, w)
    xs = (torch.arange(w, dtype=heat.dtype, device=heat.device) + 0.5) * STRIDE
    ys = (torch.arange(h, dtype=heat.dtype, device=heat.device) + 0.5) * STRIDE
    px, py = p.sum(2), p.sum(3)  # marginals (N, K, W), (N, K, H)
    mx, my = (px * xs).sum(-1), (py * ys).sum(-1)
    vx = (px * (xs - mx[..., None]) ** 2).sum(-1)
    vy = (py * (ys - my[..., None]) ** 2).sum(-1)
    return torch.stack([mx, my], -1), torch.sqrt(vx + vy + 1e-12), logp.reshape(n, k, h, w)


class ExportWrapper(nn.Module):
    """What the ONNX graph computes: crop -> keypoints (crop px), their spread, presence 0..1,
    and with `attitude` the attitude in the crop (rotation vector, deg)."""

    def __init__(self, net: KeypointNet, attitude: bool = True):
        super().__init__()
        self.net, self.attitude = net, attitude

    def forward(self, image: torch.Tensor):
        heat, present, att_deg = self.net(image)
        kp, spread, _ = soft_argmax(heat)
        if not self.attitude:
            return kp, spread, torch.sigmoid(present)
        return kp, spread, torch.sigmoid(present), att_deg


class EnsembleWrapper(nn.Module):
    """Several networks read one crop as one graph with ExportWrapper's outputs (model 0.31.0's
    far network). Their heat-map distributions are mixed with equal weights: a keypoint's position
    is the mean of the members' (the mixture's mean), its spread the mixture's RMS spread (each
    member's spread and its distance from the mean), so a keypoint the members disagree on weighs
    less in the fit; presence and the attitude head's rotation vector are the members' means (the
    members read within a degree of each other, where a mean of rotation vectors is the mean
    rotation to well under their error)."""

    def __init__(self, nets: list[KeypointNet], attitude: bool = True):
        super().__init__()
        if len(nets) < 2:
            raise ValueError(f"an ensemble needs two networks or more, got {len(nets)}")
        self.members = nn.ModuleList(ExportWrapper(n, attitude) for n in nets)
        self.attitude = attitude

    def forward(self, image: torch.Tensor):
        outs = [m(image) for m in self.members]
        kp = torch.stack([o[0] for o in outs]).mean(0)
        second = torch.stack([o[1] ** 2 + ((o[0] - kp) ** 2).sum(-1) for o in outs]).mean(0)
        means = [kp, torch.sqrt(second), torch.stack([o[2] for o in outs]).mean(0)]
        if self.attitude:
            means.append(torch.stack([o[3] for o in outs]).mean(0))
        return tuple(means)
