"""VGGT adapter (facebookresearch/vggt, weights ``facebook/VGGT-1B``).

Upstream conventions (verified in ``vggt/models/vggt.py`` and ``vggt/utils/pose_enc.py``): the camera head
returns a 9-d ``pose_enc`` per frame (translation, quaternion, two fields of view) that decodes to
camera-from-world extrinsics [R|t] in OpenCV axes plus intrinsics with the principal point at the image
centre; the depth head returns z-depth [B,S,H,W,1] with an ``expp1`` confidence (1 + exp, higher is better).
Frame 0 is the training reference but is only approximately the identity, so the adapter inverts the
extrinsics and re-anchors them at frame 0. The TTR camera group leaves out the head's first-iteration
input token, which the iterative refinement detaches. Output is up to scale (``metric=False``).
"""

from __future__ import annotations

import torch

from vi3_core.backbones import _hub
from vi3_core.backbones.base import CAP_TTR, BackboneInputs, Condition, ParamGroups, Prediction

INSTALL = "pip install git+https://github.com/facebookresearch/vggt"


class VGGTBackbone(_hub.UpstreamBackbone):
    """VGGT-1B. ``resolution`` is the model input width (518 in upstream preprocessing); ``random_init``
    builds the architecture without loading weights (tests, timing)."""

    name = "vggt"
    metric = False
    capabilities = frozenset({CAP_TTR})
    patch_size = 14

    def __init__(self, *, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32,
                 checkpoint: str = "facebook/VGGT-1B", random_init: bool = False, resolution: int = 518) -> None:
        super().__init__(device=device, dtype=dtype)
        models = _hub.require("vggt.models.vggt", backbone=self.name, install=INSTALL)
        self._pose_enc = _hub.require("vggt.utils.pose_enc", backbone=self.name, install=INSTALL)
        self.resolution = resolution
        net = models.VGGT()
        if not random_init:
            weights = _hub.resolve_checkpoint(checkpoint, backbone=self.name)
            _hub.load_weights(net, weights, backbone=self.name)
        self.install_net(net)

    def target_hw(self, H: int, W: int) -> tuple[int, int]:
        return _hub.hw_fixed_width(H, W, width=self.resolution, patch=self.patch_size)

    def forward(self, inputs: BackboneInputs, condition: Condition | None = None) -> Prediction:
        self.check_condition(condition, inputs)
        images = inputs.images[None]
        tokens, patch_start = _hub.aggregate(self.net.aggregator, images, device=self.device, dtype=self.dtype)
        pose_enc = self.net.camera_head(tokens)[-1]  # last refinement iteration
        depth, conf = self.net.depth_head(tokens, images=images, patch_start_idx=patch_start)
        extrinsics, K = self._pose_enc.pose_encoding_to_extri_intri(pose_enc, images.shape[-2:])
        R_wc, t_wc = _hub.anchor_w2c(extrinsics[0, :, :3, :3], extrinsics[0, :, :3, 3])
        return _hub.prediction(R_wc, t_wc, K[0], depth[0, ..., 0], conf[0])

    def param_groups(self) -> ParamGroups:
        # The camera head refines its pose iteratively and detaches each iteration's input, so its learned
        # first-iteration input (``empty_pose_tokens``) never receives a gradient from the final pose.
        camera = [p for name, p in self.net.camera_head.named_parameters() if name != "empty_pose_tokens"]
        return ParamGroups(camera_head=camera,
                           depth_head=_hub.params(self.net.depth_head),
                           global_blocks=[_hub.params(b) for b in self.net.aggregator.global_blocks])

    def set_gradient_checkpointing(self, enabled: bool) -> None:
        # Upstream checkpoints its frame/global blocks only while the aggregator is in training mode; its
        # blocks have no dropout, so training mode changes nothing else.
        super().set_gradient_checkpointing(enabled)
        self.net.aggregator.train(enabled)
