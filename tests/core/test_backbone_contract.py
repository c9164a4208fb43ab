"""The backbone contract (``vi3_core.backbones.base``) as one reusable check, run here on ``classical``.

Adapter tests call ``check_backbone_contract(backbone, images, K)`` on their tiny random-weight models
(``from test_backbone_contract import check_backbone_contract``; pytest puts ``tests/`` on ``sys.path``).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from vi3_core.backbones import make_backbone
from vi3_core.backbones.base import CAP_COND_POSE, Backbone, BackboneInputs, Condition, Prediction
from vi3_core.dataset.asl import read_asl
from vi3_core.dataset.generate import cached_sequence
from vi3_core.dataset.sequence import make_clip
from vi3_core.errors import ModeNotSupported


def _params(backbone: Backbone) -> list[torch.nn.Parameter]:
    return [p for m in backbone.modules() for p in m.parameters()]


def check_backbone_contract(backbone: Backbone, images: np.ndarray, K: np.ndarray, *, last_blocks: int = 1,
                            atol: float = 1e-4) -> tuple[BackboneInputs, Prediction]:
    """Assert the contract on one clip: images [n,H,W(,3)] uint8, K [3,3]. Returns (inputs, base prediction).

    Shapes and dtypes of inputs and outputs, intrinsics at the working resolution, orthonormal camera-to-world
    rotations with frame 0 the identity, positive finite z-depth, finite confidence, the ``metric`` flag,
    ``predict`` = no-grad ``forward``, conditioning refused without the capability, and finite gradients that
    reach exactly ``param_groups().trainable(last_blocks)`` and no other parameter of ``modules()``.
    """
    n, H, W = images.shape[:3]
    inputs = backbone.preprocess(images, K)
    assert inputs.images.ndim == 4 and inputs.images.shape[:2] == (n, 3), inputs.images.shape
    h, w = inputs.images.shape[2:]
    assert h % backbone.patch_size == 0 and w % backbone.patch_size == 0, (h, w, backbone.patch_size)
    assert inputs.images.is_floating_point() and 0.0 <= float(inputs.images.min()) <= float(inputs.images.max()) <= 1.0
    assert tuple(inputs.K.shape) == (n, 3, 3) and tuple(inputs.src_hw) == (H, W)

    with torch.no_grad():
        pred = backbone.forward(inputs)
    assert tuple(pred.R_wc.shape) == (n, 3, 3) and tuple(pred.t_wc.shape) == (n, 3)
    assert tuple(pred.K.shape) == (n, 3, 3) and tuple(pred.depth.shape[0:1]) == (n,)
    assert pred.depth.shape == pred.conf.shape and pred.depth.ndim == 3
    assert pred.metric is backbone.metric
    R = pred.R_wc.double()
    eye = torch.eye(3, dtype=torch.float64).expand(n, 3, 3)
    assert torch.allclose(R.transpose(1, 2) @ R, eye, atol=atol), "R_wc is not orthonormal"
    assert torch.allclose(torch.linalg.det(R), torch.ones(n, dtype=torch.float64), atol=atol)
    assert torch.allclose(R[0], eye[0], atol=atol) and float(pred.t_wc[0].abs().max()) <= atol, "frame 0 != I"
    assert torch.isfinite(pred.depth).all() and (pred.depth > 0).all(), "depth must be finite and > 0"
    assert torch.isfinite(pred.conf).all()
    # K at the depth resolution: its principal point lies inside the depth map.
    dh, dw = pred.depth.shape[1:]
    assert (0 < pred.K[:, 0, 2]).all() and (pred.K[:, 0, 2] < dw).all() and (pred.K[:, 1, 2] < dh).all()

    geom = backbone.predict(images, K)
    assert np.allclose(geom.T_wc[0], np.eye(4), atol=atol)
    assert np.allclose(geom.depth, pred.depth.float().cpu().numpy(), rtol=1e-4, atol=1e-5)
    assert np.allclose(geom.T_wc[:, :3, 3], pred.t_wc.double().cpu().numpy(), atol=1e-5)

    if CAP_COND_POSE not in backbone.capabilities:
        with pytest.raises(ModeNotSupported):
            backbone.forward(inputs, Condition(T_wc=np.tile(np.eye(4), (n, 1, 1))))

    inputs = backbone.preprocess(images, K)  # the groups belong to the last preprocessed clip
    selected = backbone.param_groups().trainable(last_blocks)
    assert selected, "no trainable parameters: TTR needs at least the camera and depth heads"
    chosen = {id(p) for p in selected}
    for p in {id(p): p for p in [*_params(backbone), *selected]}.values():
        p.requires_grad_(id(p) in chosen)
        p.grad = None
    with torch.enable_grad():
        out = backbone.forward(inputs)
        loss = (out.t_wc.square().sum() + (out.R_wc - torch.eye(3, device=out.R_wc.device)).square().sum()
                + out.depth.float().log().square().mean())
        loss.backward()
    for p in selected:
        assert p.grad is not None and torch.isfinite(p.grad).all(), f"no finite gradient for {tuple(p.shape)}"
    assert any(float(p.grad.abs().max()) > 0 for p in selected), "all gradients are zero"
    for p in _params(backbone):
        if id(p) not in chosen:
            assert p.grad is None, f"gradient reached an unselected parameter {tuple(p.shape)}"
    return inputs, pred


def half_resolution(images: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """images [n,H,W(,3)] uint8 and K [3,3] at half the size (area resampling; pixel centres at integers)."""
    H, W = images.shape[1:3]
    small = np.stack([cv2.resize(im, (W // 2, H // 2), interpolation=cv2.INTER_AREA) for im in images])
    K = np.asarray(K, dtype=np.float64).copy()
    K[:2, :2] *= 0.5
    K[:2, 2] = (K[:2, 2] + 0.5) * 0.5 - 0.5
    return small, K


@pytest.fixture(scope="module")
def small_clip(cache_dir) -> tuple[np.ndarray, np.ndarray]:
    """4 frames (stride 2) of the generated room sequence, undistorted and halved to 376x240: (images, K)."""
    clip = make_clip(read_asl(cached_sequence(cache_dir, seconds=4.0, seed=0) / "mav0"), np.arange(20, 28, 2))
    return half_resolution(clip.images, clip.K)


@pytest.mark.slow
def test_classical_satisfies_the_contract(small_clip):
    backbone = make_backbone("classical")
    inputs, pred = check_backbone_contract(backbone, *small_clip)
    assert inputs.status == "ok", inputs.reason
    assert pred.depth.shape[1:] == (60, 94)  # 376x240 at the default downscale of 4


def test_contract_check_rejects_a_backbone_that_breaks_frame_zero(small_clip):
    """The check is not vacuous: a classical backbone whose frame 0 is moved fails it."""

    class Shifted(type(make_backbone("classical"))):
        def forward(self, inputs, condition=None):
            pred = super().forward(inputs, condition)
            pred.t_wc = pred.t_wc + 0.1
            return pred

    with pytest.raises(AssertionError, match="frame 0"):
        check_backbone_contract(Shifted(), *small_clip)


def test_registry_rejects_unknown_names():
    with pytest.raises(ValueError, match="unknown backbone"):
        make_backbone("nope")
