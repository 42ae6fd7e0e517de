"""The geometry that networks and optimisers need, in torch (batched, differentiable)."""

from __future__ import annotations

import torch


def invert(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms (..., 4, 4)."""
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) applied to (..., N, 3) -> (..., N, 3)."""
    return points @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


def project(points_cam: torch.Tensor, K: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """(..., N, 3) camera-frame points and (..., 3, 3) K -> (..., N, 2) pixels."""
    p = points_cam @ K.transpose(-1, -2)
    return p[..., :2] / p[..., 2:3].clamp(min=eps)


def rot6d_to_matrix(x: torch.Tensor) -> torch.Tensor:
    """(..., 6) = first two columns of R -> (..., 3, 3) by Gram-Schmidt (Zhou et al. 2019)."""
    a, b = x[..., :3], x[..., 3:]
    e1 = torch.nn.functional.normalize(a, dim=-1)
    b = b - (e1 * b).sum(-1, keepdim=True) * e1
    e2 = torch.nn.functional.normalize(b, dim=-1)
    e3 = torch.cross(e1, e2, dim=-1)
    return torch.stack([e1, e2, e3], dim=-1)


def matrix_to_rot6d(R: torch.Tensor) -> torch.Tensor:
    return torch.cat([R[..., :, 0], R[..., :, 1]], dim=-1)


def axis_angle_to_matrix(v: torch.Tensor) -> torch.Tensor:
    """Rodrigues for (..., 3) rotation vectors in radians; smooth at 0 (for autodiff)."""
    theta2 = (v * v).sum(-1, keepdim=True)[..., None]
    theta = theta2.clamp(min=1e-24).sqrt()
    small = theta2 < 1e-12
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp(min=1e-24))
    z = torch.zeros_like(v[..., 0])
    K = torch.stack([
        torch.stack([z, -v[..., 2], v[..., 1]], -1),
        torch.stack([v[..., 2], z, -v[..., 0]], -1),
        torch.stack([-v[..., 1], v[..., 0], z], -1),
    ], -2)
    eye = torch.eye(3, dtype=v.dtype, device=v.device).expand(K.shape)
    return eye + a * K + b * (K @ K)


def symmetric_distances_all(T1: torch.Tensor, T2: torch.Tensor, points: torch.Tensor,
                            symmetries: torch.Tensor) -> torch.Tensor:
    """(P, S) mean distances ||T1 S x - T2 x|| (mm); T1, T2: (P, 4, 4); points (N, 3); S (S, 4, 4)."""
    XS = points @ symmetries[:, :3, :3].transpose(-1, -2) + symmetries[:, None, :3, 3]
    p1 = torch.einsum("pij,snj->psni", T1[:, :3, :3], XS) + T1[:, None, None, :3, 3]
    p2 = transform_points(T2, points.expand(T2.shape[0], -1, -1))
    return (p1 - p2[:, None]).norm(dim=-1).mean(-1)
