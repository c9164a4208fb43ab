"""pi3 and Pi3X adapters (yyfz233/Pi3 code; weights ``yyfz233/Pi3`` and ``yyfz233/Pi3X``).

Upstream conventions (verified in ``pi3/models/pi3.py`` and ``pi3/models/pi3x.py``):
- ``camera_poses`` are camera-to-world 4x4 in OpenCV axes with no reference frame (permutation-equivariant
  model): the adapter re-anchors them at frame 0;
- ``local_points`` are camera-frame points (x*z, y*z, z) with z = exp(.), so depth = local_points[..., 2] is
  z-depth; there are no predicted intrinsics, so K is fitted to the predicted per-pixel rays;
- ``conf`` is a logit: the adapter returns sigmoid(conf);
- the decoder alternates frame (even index) and global (odd index) attention blocks.
Pi3X multiplies its pose translations by its metric factor *in place* inside ``forward_head``, which breaks
autograd through the poses; this adapter runs the encoder/decoder of upstream and evaluates the point, camera
and confidence heads itself, without the metric head and without any in-place update.

Pi3X conditioning (``encode``): poses are re-expressed relative to frame 0; with no depth prior the
translations are divided by s = mean_{i>=1} ||t_i|| unless max_{i>=1} ||t_i|| < 0.02 (then s = 1);
the network then predicts in that normalised gauge. The adapter fits the scale that maps its predicted
camera centres onto the metric condition centres (least squares, detached; ~= s when the model honours the
condition; s itself when there is no baseline) and returns translations and depth in metres.
"""

from __future__ import annotations

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

INSTALL = "pip install git+https://github.com/yyfz/Pi3"
#: Pi3X treats a clip whose largest condition translation is below this (metres) as static.
PI3X_STATIC_TRANSLATION = 0.02


class Pi3Backbone(_hub.UpstreamBackbone):
    """pi3. ``resolution``: the pixel budget of the model input (255000 in upstream preprocessing)."""

    name = "pi3"
    metric = False
    capabilities = frozenset({CAP_TTR})
    patch_size = 14
    module_path, class_name, default_checkpoint = "pi3.models.pi3", "Pi3", "yyfz233/Pi3"

    def __init__(self, *, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32,
                 checkpoint: str | None = None, random_init: bool = False, resolution: int = 255000) -> None:
        super().__init__(device=device, dtype=dtype)
        module = _hub.require(self.module_path, backbone=self.name, install=INSTALL)
        self.resolution = resolution
        net = getattr(module, self.class_name)()
        if not random_init:
            weights = _hub.resolve_checkpoint(checkpoint or self.default_checkpoint, backbone=self.name)
            _hub.load_weights(net, weights, backbone=self.name)
        self.install_net(net)

    def target_hw(self, H: int, W: int) -> tuple[int, int]:
        return _hub.hw_pixel_budget(H, W, pixels=self.resolution, patch=self.patch_size, strict=True)

    def forward(self, inputs: BackboneInputs, condition: Condition | None = None) -> Prediction:
        self.check_condition(condition, inputs)
        with _hub.autocast(self.device, self.dtype):
            out = self.net(inputs.images[None])
        return _prediction(out["local_points"][0].float(), out["conf"][0, ..., 0].float(),
                           out["camera_poses"][0].float(), cond_centres=None)

    def param_groups(self) -> ParamGroups:
        return ParamGroups(camera_head=_hub.params(self.net.camera_decoder, self.net.camera_head),
                           depth_head=_hub.params(self.net.point_decoder, self.net.point_head),
                           global_blocks=[_hub.params(b) for b in self.net.decoder[1::2]])


class Pi3XBackbone(Pi3Backbone):
    """Pi3X: pi3 plus pose / intrinsics conditioning (``Condition``), returned in metres when conditioned."""

    name = "pi3x"
    capabilities = frozenset({CAP_TTR, CAP_COND_POSE, CAP_COND_INTRINSICS})
    module_path, class_name, default_checkpoint = "pi3.models.pi3x", "Pi3X", "yyfz233/Pi3X"

    def forward(self, inputs: BackboneInputs, condition: Condition | None = None) -> Prediction:
        n, _, H, W = inputs.images.shape
        T_cond, K = self.check_condition(condition, inputs)  # upstream requires rays whenever it gets poses
        net, ps = self.net, self.net.patch_start_idx
        imgs = ((inputs.images - net.image_mean) / net.image_std)[None]
        on = torch.ones(1, n, dtype=torch.bool, device=self.device)
        with _hub.autocast(self.device, self.dtype):
            hidden, poses, _, pose_mask, _ = net.encode(
                imgs, with_prior=T_cond is not None, intrinsics=None if K is None else K[None],
                poses=None if T_cond is None else T_cond[None], mask_add_depth=~on,
                mask_add_ray=on if K is not None else ~on, mask_add_pose=on if T_cond is not None else ~on)
            hidden, pos = net.decode(hidden.reshape(1, n, -1, net.dec_embed_dim), n, H, W, poses, pose_mask)
            point, camera, conf = (net.point_decoder(hidden, xpos=pos), net.camera_decoder(hidden, xpos=pos),
                                   net.conf_decoder(hidden, xpos=pos))
        ph, pw = H // self.patch_size, W // self.patch_size
        xy, z = net.point_head(point[:, ps:].float(), patch_h=ph, patch_w=pw)
        z = torch.exp(z.clamp(max=15.0))  # upstream's depth activation
        local = torch.cat([xy * z, z], dim=1).permute(0, 2, 3, 1)
        logit = net.conf_head(conf[:, ps:].float(), patch_h=ph, patch_w=pw)[0][:, 0]
        T_wc = net.camera_head(camera[:, ps:].float(), ph, pw).reshape(n, 4, 4)
        return _prediction(local, logit, T_wc, cond_centres=None if T_cond is None else T_cond[:, :3, 3])


def _prediction(local_points: torch.Tensor, conf_logit: torch.Tensor, T_wc: torch.Tensor,
                cond_centres: torch.Tensor | None) -> Prediction:
    """local_points [n,h,w,3] camera frame, conf_logit [n,h,w], T_wc [n,4,4] unanchored camera-to-world.
    ``cond_centres``: metric condition camera centres [n,3] (frame 0 at the origin) to restore metres; the
    fallback scale is Pi3X's own translation normaliser (see the module docstring)."""
    R_wc, t_wc = _hub.anchor_c2w(T_wc[:, :3, :3], T_wc[:, :3, 3])
    depth = local_points[..., 2]
    K = _hub.intrinsics_from_rays(local_points[..., :2] / depth[..., None])
    fallback = 1.0
    if cond_centres is not None:
        norms = cond_centres[1:].norm(dim=-1)
        if norms.numel() and float(norms.max()) >= PI3X_STATIC_TRANSLATION:
            fallback = float(norms.mean())
    return _hub.prediction(R_wc, t_wc, K, depth, torch.sigmoid(conf_logit), cond_centres=cond_centres,
                           fallback=fallback)
