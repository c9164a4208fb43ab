"""Differentiable SO(3) maps in torch (the one torch implementation; tested against scipy).

Both maps use Taylor expansions near zero so that values and gradients stay finite at the identity.
"""

from __future__ import annotations

import torch

_EPS = 1e-4


def hat(w: torch.Tensor) -> torch.Tensor:
    """[...,3] -> [...,3,3] skew-symmetric matrices."""
    z = torch.zeros_like(w[..., 0])
    return torch.stack([
        torch.stack([z, -w[..., 2], w[..., 1]], -1),
        torch.stack([w[..., 2], z, -w[..., 0]], -1),
        torch.stack([-w[..., 1], w[..., 0], z], -1),
    ], -2)


def exp(w: torch.Tensor) -> torch.Tensor:
    """Exp: [...,3] rotation vectors -> [...,3,3] (Rodrigues; Taylor series for angles < 1e-4)."""
    th2 = (w * w).sum(-1, keepdim=True)[..., None]
    small = th2 < _EPS**2
    th2_safe = torch.where(small, torch.ones_like(th2), th2)
    th = th2_safe.sqrt()
    a = torch.where(small, 1.0 - th2 / 6.0, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24.0, (1.0 - torch.cos(th)) / th2_safe)
    K = hat(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(K.shape)
    return eye + a * K + b * (K @ K)


def log(R: torch.Tensor) -> torch.Tensor:
    """Log: [...,3,3] -> [...,3] rotation vectors. Accurate away from pi (where the axis is ambiguous)."""
    vee = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    cos = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) * 0.5).clamp(-1.0 + 1e-7, 1.0 - 1e-7)
    sin = 0.5 * vee.norm(dim=-1)
    th = torch.atan2(sin, cos)
    small = th < _EPS
    th_safe = torch.where(small, torch.ones_like(th), th)
    sin_safe = torch.where(small, torch.ones_like(sin), sin)
    factor = torch.where(small, 0.5 + th * th / 12.0, 0.5 * th_safe / sin_safe)
    return factor[..., None] * vee


def geodesic(R_a: torch.Tensor, R_b: torch.Tensor) -> torch.Tensor:
    """Angle [...] in radians of R_a^T R_b, with a gradient that stays finite at zero."""
    return log(R_a.transpose(-1, -2) @ R_b).norm(dim=-1)
