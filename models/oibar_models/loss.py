"""Kendall, Gal & Cipolla's learned-uncertainty pose loss (SPEC section 5):

    L = L_r exp(-2 s_r) + L_t exp(-2 s_t) + 2 (s_r + s_t)

s_r, s_t are learnable log standard deviations of the attitude and position terms; L_r and L_t
are sums over the batch of the L2 norms of the 6D-attitude and position (m) errors. The weights
balance the two tasks without a hand-tuned factor (metres against unit-free 6D numbers).

`range_normalised=True` divides each position error by the true range ||t|| (our deviation,
config `train.pos_loss`): the paper judges position in % of range, and in metres the 10 m frames
would dominate while the last metre, where docking happens, barely counts.
"""

from __future__ import annotations

import torch
import torch.nn as nn


class UncertaintyPoseLoss(nn.Module):
    def __init__(self, init_s_r: float = 0.0, init_s_t: float = 0.0, range_normalised: bool = False):
        super().__init__()
        self.range_normalised = range_normalised
        self.s_k = nn.Parameter(torch.tensor(0.0))  # keypoint term (used only with train.kp_loss)
        self.s_r = nn.Parameter(torch.tensor(float(init_s_r)))
        self.s_t = nn.Parameter(torch.tensor(float(init_s_t)))

    def keypoint_term(self, kp_hat: torch.Tensor, kp_true: torch.Tensor, valid: torch.Tensor) -> tuple:
        """Sum over the batch of the mean L2 distance (normalised image units, [-1, 1] across the
        image) between predicted and projected keypoints, visible ones only; weighted by its own
        learned log-std like the two pose terms."""
        d = torch.linalg.vector_norm(kp_hat - kp_true, dim=-1) * valid
        L_k = (d.sum(-1) / valid.sum(-1).clamp_min(1.0)).sum()
        return L_k * torch.exp(-2 * self.s_k) + 2 * self.s_k, L_k.detach()

    def forward(
        self, T_hat_m: torch.Tensor, r6_hat: torch.Tensor, T_m: torch.Tensor, r6: torch.Tensor
    ) -> dict:
        dt = torch.linalg.vector_norm(T_hat_m - T_m, dim=-1)
        if self.range_normalised:
            dt = dt / torch.linalg.vector_norm(T_m, dim=-1).clamp_min(0.1)
        L_t = dt.sum()
        L_r = torch.linalg.vector_norm(r6_hat - r6, dim=-1).sum()
        loss = L_r * torch.exp(-2 * self.s_r) + L_t * torch.exp(-2 * self.s_t) + 2 * (self.s_r + self.s_t)
        return {"loss": loss, "L_r": L_r.detach(), "L_t": L_t.detach()}
