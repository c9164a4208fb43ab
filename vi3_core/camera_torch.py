"""Pinhole rays in torch (the numpy back-projection is ``camera``)."""

from __future__ import annotations

import torch


def pixel_rays(K: torch.Tensor, h: int, w: int, stride: int = 1) -> torch.Tensor:
    """Rows K^-1 [u, v, 1] (z = 1, so a point at z-depth d is d * ray) of every ``stride``-th pixel centre of an
    h x w image, row-major: K [...,3,3] -> [..., P, 3] with P = ceil(h/stride) ceil(w/stride)."""
    v, u = torch.meshgrid(torch.arange(0, h, stride, dtype=K.dtype, device=K.device),
                          torch.arange(0, w, stride, dtype=K.dtype, device=K.device), indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], -1).reshape(-1, 3)
    return pix @ torch.linalg.inv(K).transpose(-1, -2)
