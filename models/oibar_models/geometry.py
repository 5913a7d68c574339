"""The network's rotation geometry in torch (traceable, exported to ONNX): the 6D attitude
representation and the matrix -> quaternion conversion inside the graph.

Everything numpy (rotations, quaternions, the camera, projection, intrinsics) lives in
oibar.geometry, shared with flight, the simulator and the lab toolbox; its conventions hold here:
quaternions are scalar-first (w, x, y, z), Hamilton, w >= 0; R_a_b maps frame-b vectors into
frame a; camera axes OpenCV (+X right, +Y down, +Z forward).

The 6D attitude representation (Zhou et al. 2019) is the first two columns of R_cam_target,
stacked as (r00, r10, r20, r01, r11, r21).
"""

from __future__ import annotations

import numpy as np
import torch


# ----------------------------------------------------------------------------- torch (traceable)
def rot6d_from_matrix(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 6): the first two columns."""
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


def matrix_from_rot6d(r6: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Gram-Schmidt of the two predicted columns -> rotation matrix (..., 3, 3), columns b1 b2 b3."""
    a1, a2 = r6[..., 0:3], r6[..., 3:6]
    b1 = a1 / (torch.linalg.vector_norm(a1, dim=-1, keepdim=True) + eps)
    a2p = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = a2p / (torch.linalg.vector_norm(a2p, dim=-1, keepdim=True) + eps)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def quat_from_matrix(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) -> (..., 4) unit quaternion (w, x, y, z), w >= 0.

    Branch-free Shepperd: all four candidates are formed and the best-conditioned one (largest
    diagonal term) is gathered, so the same graph exports to ONNX without control flow."""
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    t = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    cand = torch.stack(
        [
            torch.stack([t[..., 0], m21 - m12, m02 - m20, m10 - m01], -1),  # 4w * q
            torch.stack([m21 - m12, t[..., 1], m10 + m01, m02 + m20], -1),  # 4x * q
            torch.stack([m02 - m20, m10 + m01, t[..., 2], m21 + m12], -1),  # 4y * q
            torch.stack([m10 - m01, m02 + m20, m21 + m12, t[..., 3]], -1),  # 4z * q
        ],
        -2,
    )
    idx = torch.argmax(t, dim=-1, keepdim=True)  # (..., 1)
    idx = idx.unsqueeze(-1).expand(*idx.shape[:-1], 1, 4)
    q = torch.gather(cand, -2, idx).squeeze(-2)
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


# ----------------------------------------------------------------------------- numpy
def rot6d_from_matrix_np(R: np.ndarray) -> np.ndarray:
    """The numpy twin of rot6d_from_matrix: (..., 3, 3) -> (..., 6)."""
    R = np.asarray(R)
    return np.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)
