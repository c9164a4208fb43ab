"""Test-time refinement (paper Sec. "Metrically anchoring 3DFMs"): a learnable alpha > 0 on the raw
translation and depth, plus the backbone's camera head, depth head and last L global blocks, trained for K AdamW
steps against the IMU target trajectory with the five losses. The backbone's weights are restored afterwards,
so every clip starts from the pretrained model."""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from vi3_core.anchor import losses
from vi3_core.anchor.options import AnchorOptions
from vi3_core.backbones.base import Backbone, BackboneInputs, Prediction
from vi3_core.types import Geometry, ImuTrajectory

LOSS_NAMES = ("rot", "pos", "dcons", "anchor_pos", "anchor_depth", "total")


@dataclass
class TTRResult:
    """geometry: refined metric Geometry; alpha: final scale; alphas: [K] alpha per step; losses: name -> [K]
    values (unweighted, plus the weighted total); seconds: wall time of the K steps; step_ms: [K] wall time of
    each step (the first steps of a process include one-time kernel warm-up)."""

    geometry: Geometry
    alpha: float
    alphas: np.ndarray
    losses: dict[str, np.ndarray]
    seconds: float
    step_ms: np.ndarray


def path_length_ratio(t_imu: np.ndarray, t_model: np.ndarray) -> float:
    """alpha_0 = sum_i |p_i^imu| / sum_i |p_i^M| (the paper's initialisation of alpha)."""
    den = float(np.linalg.norm(t_model, axis=1).sum())
    return float(np.linalg.norm(t_imu, axis=1).sum()) / den if den > 0 else 1.0


@contextlib.contextmanager
def trainable_scope(backbone: Backbone, params: list[torch.nn.Parameter]):
    """Freeze every parameter of the backbone except ``params``; restore values and flags on exit."""
    all_params = [p for m in backbone.modules() for p in m.parameters()]
    flags = [p.requires_grad for p in all_params]
    saved = [p.detach().clone() for p in params]
    modes = [m.training for m in backbone.modules()]
    try:
        for m in backbone.modules():
            m.eval()
        for p in all_params:
            p.requires_grad_(False)
        for p in params:
            p.requires_grad_(True)
        yield
    finally:
        with torch.no_grad():
            for p, v in zip(params, saved):
                p.copy_(v)
        for p, f in zip(all_params, flags):
            p.requires_grad_(f)
        for m, mode in zip(backbone.modules(), modes):
            m.train(mode)


def ttr_losses(pred: Prediction, alpha: torch.Tensor, target: ImuTrajectory, depth0: torch.Tensor,
               valid: torch.Tensor, options: AnchorOptions) -> dict[str, torch.Tensor]:
    """The five losses and their weighted total for one forward pass (alpha scales translation and depth).

    Eq. dcons is evaluated on the raw (model-unit) geometry: it constrains shape, and alpha is left to the IMU
    pose terms. Evaluated in metres its value grows with alpha, so w_d L_dcons pulls alpha toward zero (with
    the classical backbone on a slow clip, oracle-initialised TTR drifted from scale 0.996 to 0.898).
    """
    T = torch.as_tensor(target.T_wc, dtype=pred.t_wc.dtype, device=pred.t_wc.device)
    t = alpha * pred.t_wc
    out = {
        "rot": losses.loss_rot(pred.R_wc, T[:, :3, :3]),
        "pos": losses.loss_pos(t, T[:, :3, 3]),
        "dcons": losses.loss_dcons(pred.R_wc, pred.t_wc, pred.K, pred.depth, valid, stride=options.dcons_stride),
        "anchor_pos": losses.loss_anchor_pos(t),
        "anchor_depth": losses.loss_anchor_depth(pred.depth, depth0, valid),
    }
    out["total"] = (options.w_rot * out["rot"] + options.w_pos * out["pos"] + options.w_dcons * out["dcons"]
                    + options.w_anchor_pos * out["anchor_pos"] + options.w_anchor_depth * out["anchor_depth"])
    return out


def refine(backbone: Backbone, inputs: BackboneInputs, base: Prediction, target: ImuTrajectory,
           options: AnchorOptions) -> TTRResult:
    """Run K steps of TTR from the base prediction and return the refined metric geometry."""
    torch.manual_seed(options.seed)
    params = backbone.param_groups().trainable(options.last_blocks)
    backbone.set_gradient_checkpointing(options.gradient_checkpointing)
    alpha0 = path_length_ratio(target.T_wc[:, :3, 3], base.t_wc.detach().double().cpu().numpy())
    log_alpha = torch.nn.Parameter(torch.tensor(math.log(alpha0), dtype=base.t_wc.dtype, device=base.t_wc.device))
    depth0 = base.depth.detach()
    valid = torch.isfinite(depth0) & (depth0 > 0)
    groups = [{"params": [log_alpha], "lr": options.lr_alpha, "weight_decay": 0.0}]
    if params:
        groups.append({"params": params, "lr": options.lr or backbone.ttr_lr, "weight_decay": options.weight_decay})
    history = {k: np.zeros(options.ttr_steps) for k in LOSS_NAMES}
    alphas = np.zeros(options.ttr_steps)
    step_ms = np.zeros(options.ttr_steps)
    t_start = time.perf_counter()
    with trainable_scope(backbone, params):
        opt = torch.optim.AdamW(groups)
        for k in range(options.ttr_steps):
            t_step = time.perf_counter()
            opt.zero_grad(set_to_none=True)
            pred = backbone.forward(inputs)
            terms = ttr_losses(pred, log_alpha.exp(), target, depth0, valid, options)
            terms["total"].backward()
            opt.step()
            for name, value in terms.items():
                history[name][k] = float(value.detach())
            alphas[k] = float(log_alpha.detach().exp())
            step_ms[k] = 1e3 * (time.perf_counter() - t_step)
        seconds = time.perf_counter() - t_start
        with torch.no_grad():
            alpha = float(log_alpha.exp())
            geometry = backbone.forward(inputs).geometry(scale=alpha)
    geometry.metric = True
    return TTRResult(geometry=geometry, alpha=alpha, alphas=alphas, losses=history, seconds=seconds,
                     step_ms=step_ms)
