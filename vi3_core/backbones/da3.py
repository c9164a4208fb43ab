"""Depth Anything 3 adapter (ByteDance-Seed/Depth-Anything-3, PyPI ``depth-anything-3``; weights
``depth-anything/DA3-LARGE-1.1`` and siblings).

Upstream conventions (verified in ``depth_anything_3/model/da3.py``, ``cam_enc.py``, ``dualdpt.py``,
``model/dinov2/vision_transformer.py`` and ``api.py``):
- the API wrapper ``DepthAnything3.forward`` runs under ``torch.no_grad``/``inference_mode``, so the adapter
  calls the inner ``DepthAnything3Net`` with ImageNet-normalised images and ``ref_view_strategy="first"``
  (frame 0 is the reference view; with 3+ views upstream would otherwise pick one by token statistics);
- ``extrinsics`` out (and in) are world-to-camera [R|t] in OpenCV axes, ``intrinsics`` in pixels;
- ``depth`` is z-depth [B,S,H,W] (exp), ``depth_conf`` is ``expp1`` (higher is better);
- the backbone's blocks from ``alt_start`` on alternate frame (even index) and global (odd index) attention;
- the DualDPT head also has an auxiliary ray branch (``*_aux``) that the camera-decoder path discards: it is
  left out of the TTR depth group.
Conditioning: the wrapper (not the network) normalises input extrinsics: re-expressed relative to frame 0,
translations divided by s = max(median_i ||c_i||, 0.1) over all camera centres c_i (frame 0 included),
and afterwards rescales the prediction to the input by a Umeyama fit. The adapter applies the same input
normalisation, then fits the scale of its predicted camera centres onto the metric condition centres
(least squares, detached; s itself with no baseline) and returns translations and depth in metres.
"""

from __future__ import annotations

import json

import torch

from vi3_core.backbones import _hub
from vi3_core.backbones.base import (
    CAP_COND_INTRINSICS,
    CAP_COND_POSE,
    CAP_TTR,
    BackboneInputs,
    Condition,
    ParamGroups,
    Prediction,
)
from vi3_core.errors import BackboneUnavailable

INSTALL = "pip install depth-anything-3"
#: Lower bound of the wrapper's pose-scale normaliser (``_normalize_extrinsics``).
MIN_POSE_SCALE = 0.1
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class DA3Backbone(_hub.UpstreamBackbone):
    """Depth Anything 3 any-view models (da3-small/base/large/giant). ``model_name`` picks the upstream
    preset; by default it is read from the checkpoint's ``config.json`` (``da3-large`` for random init).
    ``resolution``: longest input side (upstream ``process_res``, 504)."""

    name = "da3"
    metric = False
    capabilities = frozenset({CAP_TTR, CAP_COND_POSE, CAP_COND_INTRINSICS})
    patch_size = 14

    def __init__(self, *, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32,
                 checkpoint: str = "depth-anything/DA3-LARGE-1.1", random_init: bool = False,
                 model_name: str | None = None, resolution: int = 504) -> None:
        super().__init__(device=device, dtype=dtype)
        cfg = _hub.require("depth_anything_3.cfg", backbone=self.name, install=INSTALL)
        registry = _hub.require("depth_anything_3.registry", backbone=self.name, install=INSTALL)
        self.resolution = resolution
        weights = None if random_init else _hub.resolve_checkpoint(checkpoint, backbone=self.name)
        if model_name is None and weights is not None and (weights.parent / "config.json").is_file():
            model_name = json.loads((weights.parent / "config.json").read_text()).get("model_name")
        model_name = model_name or "da3-large"
        if model_name not in registry.MODEL_REGISTRY:
            raise BackboneUnavailable(f"backbone 'da3': unknown preset {model_name!r}; upstream has "
                                      f"{', '.join(registry.MODEL_REGISTRY)}")
        net = cfg.create_object(cfg.load_config(registry.MODEL_REGISTRY[model_name]))
        if getattr(net, "cam_dec", None) is None:
            raise BackboneUnavailable(f"backbone 'da3': preset {model_name!r} has no camera decoder (mono, metric "
                                      f"or nested model); use an any-view model such as da3-large")
        if weights is not None:  # checkpoints are saved from the API wrapper, which holds the net as `model`
            _hub.load_weights(net, weights, backbone=self.name, strip_prefix="model.")
        self.install_net(net)
        self._mean = torch.tensor(IMAGENET_MEAN, device=self.device).view(1, 1, 3, 1, 1)
        self._std = torch.tensor(IMAGENET_STD, device=self.device).view(1, 1, 3, 1, 1)

    def target_hw(self, H: int, W: int) -> tuple[int, int]:
        return _hub.hw_long_side(H, W, long_side=self.resolution, patch=self.patch_size)

    def forward(self, inputs: BackboneInputs, condition: Condition | None = None) -> Prediction:
        T_cond, K_cond = self.check_condition(condition, inputs)
        x = (inputs.images[None] - self._mean) / self._std
        extrinsics = intrinsics = None
        s_norm = 1.0
        if T_cond is not None:  # the wrapper's input normalisation (module docstring)
            centres = T_cond[:, :3, 3]
            s_norm = max(float(centres.norm(dim=-1).median()), MIN_POSE_SCALE)
            extrinsics = _w2c(torch.cat([T_cond[:, :3, :3], centres[..., None] / s_norm], dim=-1))[None]
            intrinsics = K_cond[None]
        with _hub.autocast(self.device, self.dtype):
            out = self.net(x, extrinsics=extrinsics, intrinsics=intrinsics, export_feat_layers=[],
                           ref_view_strategy="first")
        E = out["extrinsics"][0].float()
        R_wc, t_wc = _hub.anchor_w2c(E[:, :3, :3], E[:, :3, 3])
        return _hub.prediction(R_wc, t_wc, out["intrinsics"][0].float(), out["depth"][0].float(),
                               out["depth_conf"][0].float(), cond_centres=None if T_cond is None else T_cond[:, :3, 3],
                               fallback=s_norm)

    def param_groups(self) -> ParamGroups:
        vit = self.net.backbone.pretrained
        blocks = [b for i, b in enumerate(vit.blocks) if i >= vit.alt_start and i % 2 == 1]
        # DualDPT's auxiliary (ray) branch, modules named ``*_aux``, shapes neither depth nor poses here.
        depth = [p for name, p in self.net.head.named_parameters() if "_aux" not in name]
        return ParamGroups(camera_head=_hub.params(self.net.cam_dec), depth_head=depth,
                           global_blocks=[_hub.params(b) for b in blocks])


def _w2c(T_wc: torch.Tensor) -> torch.Tensor:
    """Camera-to-world [n,3,4] -> world-to-camera [n,4,4]."""
    R_cw = T_wc[:, :3, :3].transpose(-1, -2)
    t_cw = -(R_cw @ T_wc[:, :3, 3:])
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], device=T_wc.device).expand(T_wc.shape[0], 1, 4)
    return torch.cat([torch.cat([R_cw, t_cw], dim=-1), bottom], dim=-2)
