"""VGGT-Omega adapter (facebookresearch/vggt-omega; gated weights ``facebook/VGGT-Omega``).

Upstream conventions (verified in ``vggt_omega/models/vggt_omega.py``, ``heads/`` and ``utils/pose_enc.py``):
patch size 16; the camera head returns one 9-d encoding per frame (translation, quaternion, two fields of
view) decoding to camera-from-world extrinsics in OpenCV axes; the dense head returns z-depth
[B,S,H,W,1] (exp activation) and an ``expp1`` confidence. The inter-frame attention lives in
``aggregator.inter_frame_blocks`` (global blocks and a few register-only blocks, all attending across
frames). The TTR depth group is the dense head without its confidence-only projection ``proj_conf``.
Output is up to scale (``metric=False``).
"""

from __future__ import annotations

import torch

from vi3_core.backbones import _hub
from vi3_core.backbones.base import CAP_TTR, BackboneInputs, Condition, ParamGroups, Prediction

INSTALL = "pip install git+https://github.com/facebookresearch/vggt-omega"
#: The 512-px checkpoint inside the gated Hugging Face repo (request access there, then `hf download`).
DEFAULT_REPO = "facebook/VGGT-Omega"
WEIGHT_FILES = ("vggt_omega_1b_512.pt", "model.pt", "model.safetensors")


class VGGTOmegaBackbone(_hub.UpstreamBackbone):
    """VGGT-Omega-1B-512. ``checkpoint``: a local ``.pt`` file or directory, or the gated HF repo id (found
    in the cache). ``resolution``: upstream's ``image_resolution`` (``balanced`` mode keeps about
    (resolution / 16)^2 patches at the image's aspect ratio)."""

    name = "vggt_omega"
    metric = False
    capabilities = frozenset({CAP_TTR})
    patch_size = 16

    def __init__(self, *, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32,
                 checkpoint: str = DEFAULT_REPO, random_init: bool = False, resolution: int = 512) -> None:
        super().__init__(device=device, dtype=dtype)
        models = _hub.require("vggt_omega.models", backbone=self.name, install=INSTALL)
        self._pose_enc = _hub.require("vggt_omega.utils.pose_enc", backbone=self.name, install=INSTALL)
        self.resolution = resolution
        net = models.VGGTOmega(patch_size=self.patch_size)
        if random_init:
            # Upstream leaves the attention key-bias masks (buffers) NaN until a checkpoint fills them; its
            # ViT initialiser sets them (q, v biases on, k bias off) together with the linear layers.
            net.apply(_hub.require("vggt_omega.models.layers.vision_transformer", backbone=self.name,
                                   install=INSTALL).init_weights_vit)
        else:
            weights = _hub.resolve_checkpoint(checkpoint, backbone=self.name, weight_files=WEIGHT_FILES)
            _hub.load_weights(net, weights, backbone=self.name)
        self.install_net(net)

    def target_hw(self, H: int, W: int) -> tuple[int, int]:
        return _hub.hw_pixel_budget(H, W, pixels=self.resolution ** 2, patch=self.patch_size, strict=False)

    def forward(self, inputs: BackboneInputs, condition: Condition | None = None) -> Prediction:
        self.check_condition(condition, inputs)
        images = inputs.images[None]
        tokens, patch_start = _hub.aggregate(self.net.aggregator, images, device=self.device, dtype=self.dtype)
        pose_enc = self.net.camera_head(tokens, patch_token_start=patch_start)
        depth, conf = self.net.dense_head(tokens, images=images, patch_token_start=patch_start)
        extrinsics, K = self._pose_enc.encoding_to_camera(pose_enc, images.shape[-2:])
        R_wc, t_wc = _hub.anchor_w2c(extrinsics[0, :, :3, :3], extrinsics[0, :, :3, 3])
        return _hub.prediction(R_wc, t_wc, K[0], depth[0, ..., 0], conf[0])

    def param_groups(self) -> ParamGroups:
        # The dense head's confidence projection shapes neither depth nor poses: it stays frozen.
        head = self.net.dense_head
        depth = [p for name, p in head.named_parameters() if not name.startswith("proj_conf.")]
        return ParamGroups(camera_head=_hub.params(self.net.camera_head), depth_head=depth,
                           global_blocks=[_hub.params(b) for b in self.net.aggregator.inter_frame_blocks])
