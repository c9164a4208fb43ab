"""The five test-time-refinement losses (paper Sec. "Metrically anchoring 3DFMs"), in torch.

Conventions: poses are camera-to-world in the first camera frame C1; ``t`` is the alpha-scaled translation and
``depth`` the alpha-scaled z-depth, so every loss sees metric units; the IMU target is metric.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from vi3_core import so3_torch
from vi3_core.camera_torch import pixel_rays


def loss_pos(t: torch.Tensor, t_imu: torch.Tensor) -> torch.Tensor:
    """L_pos: mean over consecutive pairs of || (p_i - p_{i-1}) - dp^imu_{i-1} ||_1. t, t_imu: [n,3], m."""
    return (torch.diff(t, dim=0) - torch.diff(t_imu, dim=0)).abs().sum(-1).mean()


def loss_rot(R: torch.Tensor, R_imu: torch.Tensor) -> torch.Tensor:
    """L_rot: mean geodesic of (R_{i-1}^T R_i)^T dR^imu_{i-1} over consecutive pairs. R, R_imu: [n,3,3]."""
    rel = R[:-1].transpose(-1, -2) @ R[1:]
    rel_imu = R_imu[:-1].transpose(-1, -2) @ R_imu[1:]
    return so3_torch.geodesic(rel, rel_imu).mean()


def loss_anchor_pos(t: torch.Tensor) -> torch.Tensor:
    """L_a^p: || p_1 ||_1, the first frame's position (the coordinate origin)."""
    return t[0].abs().sum()


def loss_anchor_depth(depth_raw: torch.Tensor, depth_raw0: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """L_a^D: mean |D_i - D_i^(0)| of the raw (un-alpha-scaled) depth against the zero-shot depth, over valid
    pixels (a per-pixel mean rather than the map's L1 sum, so the paper's weight w_ad = 1 is resolution-free)."""
    return (depth_raw - depth_raw0).abs()[valid].mean()


def loss_dcons(R: torch.Tensor, t: torch.Tensor, K: torch.Tensor, depth: torch.Tensor, valid: torch.Tensor, *,
               stride: int = 4) -> torch.Tensor:
    """L_dcons (Eq. dcons): back-project frame j's depth to world points X_j, project them into every other
    frame i, and penalise | [pi_i(X_j)]_Z - D_i(pi_i(X_j)) |, keeping per pixel the minimum over i != j and
    averaging over pixels valid in at least one view (inside the image, in front, and interpolated only from
    valid source depths).

    R [n,3,3], t [n,3] camera-to-world; K [n,3,3]; depth, valid [n,h,w]; ``stride`` subsamples frame j's pixels
    (an unbiased estimate of the mean: every source depth map is still sampled at full resolution).
    """
    n, h, w = depth.shape
    rays = pixel_rays(K, h, w, stride)  # [n,P,3]
    d_j = depth[:, ::stride, ::stride].reshape(n, -1)
    ok_j = valid[:, ::stride, ::stride].reshape(n, -1)
    X_w = (rays * d_j[..., None]) @ R.transpose(-1, -2) + t[:, None]  # [n_j,P,3] world points
    # Into every camera i (row vectors): X_i = (X_w - t_i) R_i, pixels = X_i K_i^T -> [n_i, n_j, P, 3]
    X_i = (X_w[None] - t[:, None, None]) @ R[:, None]
    z = X_i[..., 2]
    uvw = X_i @ K.transpose(-1, -2)[:, None]
    uv = uvw[..., :2] / z.clamp_min(1e-6)[..., None]
    scale = torch.tensor([2.0 / w, 2.0 / h], dtype=uv.dtype, device=uv.device)
    grid = ((uv + 0.5) * scale - 1.0).reshape(n, -1, 1, 2)
    # One bilinear lookup of [depth, valid]: the interpolated mask is 1 only where all four taps are valid.
    src = torch.stack([torch.where(valid, depth, torch.zeros_like(depth)), valid.to(depth.dtype)], 1)
    sampled = F.grid_sample(src, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    sampled = sampled.reshape(n, 2, n, -1)
    in_image = (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
    inside = in_image & (z > 1e-6) & (sampled[:, 1] > 1.0 - 1e-6) & ok_j[None]
    inside = inside & ~torch.eye(n, dtype=torch.bool, device=depth.device)[..., None]
    err = torch.where(inside, (z - sampled[:, 0]).abs(), torch.full_like(z, float("inf")))
    best = err.min(dim=0).values  # [n_j, P]
    has = torch.isfinite(best)
    if not has.any():
        return depth.sum() * 0.0
    return best[has].mean()
