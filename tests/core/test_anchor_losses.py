"""The five TTR losses: zero at their optimum, positive away from it, differentiable."""

from __future__ import annotations

import numpy as np
import torch

from vi3_core import so3
from vi3_core.anchor import losses
from vi3_core.anchor.options import AnchorOptions
from vi3_core.anchor.ttr import path_length_ratio, ttr_losses
from vi3_core.backbones.base import Prediction
from vi3_core.types import ImuTrajectory

H, W, N = 24, 32, 4


def _scene(seed: int = 0):
    """Cameras looking at a fronto-parallel textured plane z = 4 m (in C1); exact depth per camera."""
    rng = np.random.default_rng(seed)
    R = so3.exp(rng.normal(0, 0.03, (N, 3)))
    R[0] = np.eye(3)
    t = np.concatenate([np.zeros((1, 3)), rng.normal(0, 0.15, (N - 1, 3))])
    K = np.tile(np.array([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]]), (N, 1, 1))
    v, u = np.meshgrid(np.arange(H) + 0.0, np.arange(W) + 0.0, indexing="ij")
    rays_c = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K[0]).T  # [H,W,3] same K for all
    rays_w = np.einsum("nij,hwj->nhwi", R, rays_c)
    lam = (4.0 - t[:, None, None, 2]) / rays_w[..., 2]  # ray length to the plane, in ray units
    depth = lam  # rays have z = 1 in the camera, so the ray parameter is the z-depth
    as_t = lambda a: torch.tensor(a, dtype=torch.float64)
    return as_t(R), as_t(t), as_t(K), as_t(depth)


def test_pose_losses_zero_at_target_and_positive_away():
    R, t, _, _ = _scene()
    assert losses.loss_pos(t, t) == 0 and losses.loss_rot(R, R) < 1e-7
    t2 = t.clone()
    t2[2] += torch.tensor([0.05, 0.0, 0.0], dtype=torch.float64)
    assert losses.loss_pos(t2, t) > 0.01
    # A rigid transform shared by prediction and target cancels (consecutive-pair losses).
    Rg = torch.tensor(so3.exp(np.array([0.1, 0.2, -0.3])), dtype=torch.float64)
    assert losses.loss_pos(t + 1.0, t) < 1e-12
    assert losses.loss_rot(Rg @ R, R) < 1e-6
    R2 = R.clone()
    R2[3] = R2[3] @ torch.tensor(so3.exp(np.array([0.0, 0.02, 0.0])), dtype=torch.float64)
    assert abs(float(losses.loss_rot(R2, R)) - 0.02 / (N - 1)) < 1e-6


def test_anchor_losses():
    R, t, _, depth = _scene()
    valid = torch.ones_like(depth, dtype=torch.bool)
    assert losses.loss_anchor_pos(t) == 0
    assert losses.loss_anchor_pos(t + 0.1) > 0.29
    assert losses.loss_anchor_depth(depth, depth, valid) == 0
    assert abs(float(losses.loss_anchor_depth(depth * 1.1, depth, valid)) - 0.1 * float(depth.mean())) < 1e-9


def test_depth_consistency_zero_for_consistent_geometry_and_positive_otherwise():
    R, t, K, depth = _scene()
    valid = torch.ones_like(depth, dtype=torch.bool)
    consistent = float(losses.loss_dcons(R, t, K, depth, valid, stride=1))
    assert consistent < 1e-4  # bilinear interpolation of a slanted plane's depth only
    # Scaling depth without the poses breaks consistency (in proportion to the baseline); scaling both keeps it.
    assert losses.loss_dcons(R, t, K, depth * 1.2, valid) > 100 * consistent
    assert losses.loss_dcons(R, 2.0 * t, K, 2.0 * depth, valid) < 2e-4
    bumped = depth.clone()
    bumped[1, 8:16, 8:16] += 0.5
    assert losses.loss_dcons(R, t, K, bumped, valid, stride=1) > 1e-3
    # Invalid pixels are ignored.
    invalid = valid.clone()
    invalid[1, 8:16, 8:16] = False
    assert losses.loss_dcons(R, t, K, bumped, invalid, stride=1) < 1e-3


def test_total_loss_gradients_reach_alpha_and_predictions():
    R, t, K, depth = _scene()
    target = ImuTrajectory(R=R.numpy(), p=t.numpy(), v=np.zeros((N, 3)),
                           T_wc=so3.make_T(R.numpy(), t.numpy()))
    t_raw = (t / 3.0).clone().requires_grad_()
    d_raw = (depth / 3.0).clone().requires_grad_()
    log_alpha = torch.tensor(np.log(2.5), dtype=torch.float64, requires_grad=True)
    pred = Prediction(R_wc=R, t_wc=t_raw, K=K, depth=d_raw, conf=torch.ones_like(depth))
    valid = torch.ones_like(depth, dtype=torch.bool)
    terms = ttr_losses(pred, log_alpha.exp(), target, d_raw.detach(), valid, AnchorOptions())
    terms["total"].backward()
    assert log_alpha.grad < 0  # alpha = 2.5 < 3: the pose loss pulls alpha up
    assert torch.isfinite(t_raw.grad).all() and torch.isfinite(d_raw.grad).all()
    assert abs(path_length_ratio(t.numpy(), t_raw.detach().numpy()) - 3.0) < 1e-12
