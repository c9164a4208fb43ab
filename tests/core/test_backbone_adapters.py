"""3DFM adapters (vggt, vggt_omega, pi3, pi3x, da3) and their shared plumbing.

The model tests build the real upstream architectures with random weights at a tiny resolution (2-6 patches
per frame, 3 frames) and run only where the upstream package is importable; elsewhere they skip with the
reason. The plumbing tests (preprocessing, re-anchoring, scale fit, checkpoint and package errors) always run.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch
from test_backbone_contract import check_backbone_contract

from vi3_core.backbones import _hub, make_backbone
from vi3_core.backbones.base import CAP_COND_INTRINSICS, CAP_COND_POSE, Condition, ParamGroups
from vi3_core.errors import BackboneUnavailable, CalibrationError, DataError, ModeNotSupported
from vi3_core.so3 import exp as so3_exp
from vi3_core.so3 import make_T

N_FRAMES, SRC_H, SRC_W = 3, 48, 64
K_SRC = np.array([[50.0, 0.0, 31.5], [0.0, 52.0, 23.5], [0.0, 0.0, 1.0]])

#: name -> (upstream module that must import, install hint word, tiny constructor options)
ADAPTERS = {
    "vggt": ("vggt.models.vggt", "facebookresearch/vggt", dict(resolution=28)),
    "vggt_omega": ("vggt_omega.models", "facebookresearch/vggt-omega", dict(resolution=32)),
    "pi3": ("pi3.models.pi3", "yyfz/Pi3", dict(resolution=28 * 42)),
    "pi3x": ("pi3.models.pi3x", "yyfz/Pi3", dict(resolution=28 * 42)),
    "da3": ("depth_anything_3.model.da3", "depth-anything-3", dict(resolution=42, model_name="da3-small")),
}


def _importable(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ImportError:  # parent package missing
        return False


def _images(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, size=(N_FRAMES, SRC_H, SRC_W, 3), dtype=np.uint8)


def _condition(scale: float) -> Condition:
    """Metric camera-to-world poses of a short sideways path, frame 0 = identity, translations x ``scale``."""
    T = np.stack([make_T(so3_exp(np.array([0.0, 0.05 * i, 0.02 * i])), scale * np.array([0.3 * i, 0.05 * i, 0.1]))
                  for i in range(N_FRAMES)])
    T[0] = np.eye(4)
    return Condition(T_wc=T)


# ----------------------------------------------------------------------------------------------------------
# Plumbing (always runs)
# ----------------------------------------------------------------------------------------------------------

def test_resize_crop_rescales_intrinsics_consistently():
    """A pixel at a known ray lands where the rescaled K projects that ray, for colour and grey input."""
    H, W, hw = 60, 90, (28, 56)
    u0, v0 = 60.0, 20.0
    img = np.zeros((1, H, W, 3), np.uint8)
    img[0, int(v0) - 3:int(v0) + 4, int(u0) - 3:int(u0) + 4] = 255
    K = np.array([[80.0, 0, 44.5], [0, 80.0, 29.5], [0, 0, 1]])
    for arr in (img, img[..., 0]):
        x, Kt = _hub.resize_crop(arr, K, hw, device=torch.device("cpu"))
        assert x.shape == (1, 3, *hw) and x.dtype == torch.float32 and 0.0 <= float(x.min()) <= float(x.max()) <= 1
        ray = np.linalg.solve(K, [u0, v0, 1.0])
        u, v, _ = Kt[0].double().numpy() @ ray
        wgt = x[0, 0].double().numpy()
        yy, xx = np.mgrid[0:hw[0], 0:hw[1]]
        cx, cy = (wgt * xx).sum() / wgt.sum(), (wgt * yy).sum() / wgt.sum()  # blob centroid
        assert abs(cx - u) <= 0.25 and abs(cy - v) <= 0.25, (cx, cy, u, v)


@pytest.mark.parametrize("H,W", [(480, 752), (752, 480), (48, 64)])
def test_target_sizes_are_patch_multiples(H, W):
    for patch in (14, 16):
        h, w = _hub.hw_fixed_width(H, W, width=518 if patch == 14 else 512, patch=patch)
        assert h % patch == 0 and w % patch == 0 and h <= w
        h, w = _hub.hw_pixel_budget(H, W, pixels=255000, patch=patch, strict=True)
        assert h % patch == 0 and w % patch == 0 and h * w <= 255000
        assert abs((h / w) / (H / W) - 1) < 0.1
        h, w = _hub.hw_long_side(H, W, long_side=504, patch=patch)
        assert h % patch == 0 and w % patch == 0 and abs(max(h, w) - 504) <= patch / 2
    assert _hub.hw_fixed_width(480, 752, width=518, patch=14) == (336, 518)  # VGGT's own preprocessing
    assert _hub.hw_pixel_budget(480, 752, pixels=512 ** 2, patch=16, strict=False) == (416, 640)


def test_anchoring_puts_frame_zero_at_identity_and_keeps_relative_motion():
    rng = np.random.default_rng(1)
    T = np.stack([make_T(so3_exp(rng.normal(size=3)), rng.normal(size=3)) for _ in range(4)])
    expected = np.linalg.inv(T[0]) @ T
    R, t = _hub.anchor_c2w(torch.tensor(T[:, :3, :3]), torch.tensor(T[:, :3, 3]))
    np.testing.assert_allclose(R.numpy(), expected[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(t.numpy(), expected[:, :3, 3], atol=1e-12)
    E = np.linalg.inv(T)  # world-to-camera
    R, t = _hub.anchor_w2c(torch.tensor(E[:, :3, :3]), torch.tensor(E[:, :3, 3]))
    np.testing.assert_allclose(R.numpy(), expected[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(t.numpy(), expected[:, :3, 3], atol=1e-12)


def test_fit_metric_scale_recovers_scale_and_falls_back_without_baseline():
    t = torch.tensor([[0.0, 0, 0], [1.0, 0.2, 0], [2.0, -0.1, 0.3]])
    s = _hub.fit_metric_scale(t, 3.7 * t + 1e-3 * torch.randn(3, 3), fallback=9.0)
    assert abs(float(s) - 3.7) < 1e-2
    assert float(_hub.fit_metric_scale(torch.zeros(3, 3), t, fallback=0.5)) == 0.5


def test_prediction_is_metric_only_with_condition_centres():
    """The adapters' common ending: model units without a condition; with one, translation and depth scaled by the
    least-squares fit onto the condition centres, or by the model's normaliser when there is no baseline."""
    t = torch.tensor([[0.0, 0, 0], [1.0, 0.2, 0], [2.0, -0.1, 0.3]])
    R = K = torch.eye(3).expand(3, 3, 3)
    depth, conf = torch.ones(3, 4, 5), torch.ones(3, 4, 5)
    up = _hub.prediction(R, t, K, depth, conf)
    assert up.metric is False and up.t_wc is t and up.depth is depth
    metric = _hub.prediction(R, t, K, depth, conf, cond_centres=2.5 * t, fallback=9.0)
    assert metric.metric is True and metric.conf is conf
    assert torch.allclose(metric.t_wc, 2.5 * t) and torch.allclose(metric.depth, 2.5 * depth)
    static = _hub.prediction(R, torch.zeros(3, 3), K, depth, conf, cond_centres=torch.zeros(3, 3), fallback=9.0)
    assert static.metric is True and torch.allclose(static.depth, 9.0 * depth)


class _Stub(_hub.UpstreamBackbone):
    """An adapter without a network: enough for preprocessing and condition checks."""

    name = "stub"
    capabilities = frozenset({CAP_COND_POSE, CAP_COND_INTRINSICS})

    def target_hw(self, H: int, W: int) -> tuple[int, int]:
        return 28, 42

    def forward(self, inputs, condition=None):
        raise NotImplementedError

    def param_groups(self) -> ParamGroups:
        return ParamGroups()


def test_check_condition_validates_and_falls_back_to_the_calibrated_K():
    stub = _Stub()
    inputs = stub.preprocess(_images(), K_SRC)
    assert stub.check_condition(None, inputs) == (None, None)
    cond = _condition(2.0)
    T, K = stub.check_condition(cond, inputs)
    assert T.dtype == K.dtype == torch.float32 and T.shape == (N_FRAMES, 4, 4)
    np.testing.assert_allclose(T.numpy(), cond.T_wc, atol=1e-6)  # frame 0 is already the identity
    assert torch.equal(K, inputs.K)  # no condition K: the calibrated one at the model resolution
    K_cond = np.tile(K_SRC * [[2.0], [2.0], [1.0]], (N_FRAMES, 1, 1))
    _, K = stub.check_condition(Condition(T_wc=cond.T_wc, K=K_cond), inputs)
    np.testing.assert_allclose(K.numpy(), K_cond, rtol=1e-6)
    with pytest.raises(CalibrationError, match="condition K"):
        stub.check_condition(Condition(T_wc=cond.T_wc, K=K_SRC), inputs)  # [3,3], not one per frame
    with pytest.raises(DataError, match="condition T_wc"):
        stub.check_condition(Condition(T_wc=cond.T_wc[:2]), inputs)
    stub.capabilities = frozenset({CAP_COND_POSE})
    with pytest.raises(ModeNotSupported, match="intrinsics"):
        stub.check_condition(Condition(T_wc=cond.T_wc, K=K_cond), inputs)


def test_preprocess_rejects_bad_images_and_intrinsics():
    stub = _Stub()
    with pytest.raises(DataError, match="uint8"):
        stub.preprocess(_images().astype(np.float32), K_SRC)
    with pytest.raises(DataError, match="n >= 1"):
        stub.preprocess(_images()[:0], K_SRC)
    with pytest.raises(CalibrationError, match="K must be"):
        stub.preprocess(_images(), K_SRC * [[-1.0], [1.0], [1.0]])
    assert stub.diagnostics() == {}  # adapters report nothing beyond the prediction


def test_aggregate_runs_under_autocast_and_hands_float32_tokens_to_the_heads():
    class Aggregator(torch.nn.Module):
        def forward(self, images):
            self.autocast = torch.is_autocast_enabled("cpu")
            x = images.flatten(3)
            return [x.bfloat16(), None, x], 1

    agg = Aggregator()
    tokens, start = _hub.aggregate(agg, torch.rand(1, 2, 3, 4, 4), device=torch.device("cpu"), dtype=torch.bfloat16)
    assert agg.autocast and start == 1 and tokens[1] is None
    assert tokens[0].dtype == tokens[2].dtype == torch.float32
    _hub.aggregate(agg, torch.rand(1, 2, 3, 4, 4), device=torch.device("cpu"), dtype=torch.float32)
    assert not agg.autocast


def test_intrinsics_from_rays_recovers_pinhole_focal():
    h, w, fx, fy = 20, 30, 41.0, 37.0
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xy = np.stack([(u - (w - 1) / 2) / fx, (v - (h - 1) / 2) / fy], -1)[None]
    K = _hub.intrinsics_from_rays(torch.tensor(xy))[0].numpy()
    np.testing.assert_allclose([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], [fx, fy, (w - 1) / 2, (h - 1) / 2], rtol=1e-9)


def test_missing_package_error_names_install_command():
    with pytest.raises(BackboneUnavailable, match="pip install git\\+https://example.org/x"):
        _hub.require("vi3_no_such_package_abc", backbone="x", install="pip install git+https://example.org/x")


@pytest.mark.parametrize("name", sorted(ADAPTERS))
def test_adapter_without_upstream_raises_with_install_command(name):
    module, hint, _ = ADAPTERS[name]
    if _importable(module):
        pytest.skip(f"{module} is importable here; the missing-package path cannot be exercised")
    with pytest.raises(BackboneUnavailable, match=hint) as err:
        make_backbone(name, checkpoint="org/model")
    assert "pip install" in str(err.value)


def test_missing_checkpoint_names_expected_location(tmp_path, monkeypatch):
    with pytest.raises(BackboneUnavailable, match="neither an existing file"):
        _hub.resolve_checkpoint(str(tmp_path / "absent" / "model.pt"), backbone="x")
    empty = tmp_path / "ckpt"
    empty.mkdir()
    with pytest.raises(BackboneUnavailable, match="holds none of"):
        _hub.resolve_checkpoint(empty, backbone="x")
    weights = empty / "model.pt"
    torch.save({"w": torch.ones(1)}, weights)
    assert _hub.resolve_checkpoint(empty, backbone="x") == weights
    if not _importable("huggingface_hub"):
        pytest.skip("huggingface_hub is not installed: the Hugging Face cache lookup cannot be exercised")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub"))
    with pytest.raises(BackboneUnavailable, match="models--someorg--somemodel"):
        _hub.resolve_checkpoint("someorg/somemodel", backbone="x")


def test_offline_hf_cache_snapshot_is_found_and_loaded(tmp_path, monkeypatch):
    """A repo id resolves to the weight file of a snapshot in the Hugging Face cache layout, offline."""
    if not (_importable("huggingface_hub") and _importable("safetensors")):
        pytest.skip("huggingface_hub / safetensors are not installed: the cache lookup cannot be exercised")
    from safetensors.torch import save_file

    repo = tmp_path / "hub" / "models--someorg--tiny"
    snapshot = repo / "snapshots" / ("a" * 40)
    snapshot.mkdir(parents=True)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text("a" * 40)
    net = torch.nn.Linear(3, 2)
    save_file({k: torch.full_like(v, 3.0) for k, v in net.state_dict().items()}, str(snapshot / "model.safetensors"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub"))
    weights = _hub.resolve_checkpoint("someorg/tiny", backbone="x")
    assert weights == snapshot / "model.safetensors"
    _hub.load_weights(net, weights, backbone="x")
    assert torch.all(net.weight == 3.0)


def test_load_weights_strips_wrapper_prefix_and_rejects_mismatch(tmp_path):
    net = torch.nn.Linear(2, 3)
    path = tmp_path / "w.pt"
    torch.save({f"model.{k}": torch.full_like(v, 2.0) for k, v in net.state_dict().items()}, path)
    _hub.load_weights(net, path, backbone="x", strip_prefix="model.")
    assert torch.all(net.weight == 2.0)
    with pytest.raises(BackboneUnavailable, match="do not match"):
        _hub.load_weights(net, path, backbone="x")


# ----------------------------------------------------------------------------------------------------------
# Real upstream architectures (random weights), when importable
# ----------------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module", params=sorted(ADAPTERS))
def backbone(request):
    module, hint, options = ADAPTERS[request.param]
    if not _importable(module):
        pytest.skip(f"upstream {module!r} for backbone {request.param!r} is not importable ({hint} not installed)")
    torch.manual_seed(0)
    return make_backbone(request.param, random_init=True, **options)


def test_contract_and_gradients_reach_exactly_the_selected_groups(backbone):
    """The shared contract check (shapes, frame 0 = I, orthonormal rotations, positive z-depth, predict =
    forward, conditioning refused without the capability, finite gradients on exactly the selected
    parameters), then: depth at the model input resolution and a non-zero gradient in every selected group."""
    last = 2
    groups = backbone.param_groups()
    assert groups.camera_head and groups.depth_head and len(groups.global_blocks) >= 2 * last
    try:
        inputs, pred = check_backbone_contract(backbone, _images(), K_SRC, last_blocks=last, atol=1e-5)
        assert pred.depth.shape == (N_FRAMES, *inputs.images.shape[-2:])
        assert not torch.isnan(pred.K).any()  # random weights may give an infinite focal (zero FoV), not NaN
        named = [("camera_head", groups.camera_head), ("depth_head", groups.depth_head),
                 *((f"global_block[{len(groups.global_blocks) - last + i}]", b)
                   for i, b in enumerate(groups.global_blocks[-last:]))]
        for name, group in named:
            assert any(float(p.grad.abs().sum()) > 0 for p in group), f"{backbone.name}: zero gradient in {name}"
        first = groups.global_blocks[0]
        assert all(p.grad is None and not p.requires_grad for p in first), "an unselected global block was trained"
    finally:
        for module in backbone.modules():
            for p in module.parameters():
                p.requires_grad_(False)
                p.grad = None


def test_condition_returns_metres_and_follows_the_condition_scale(backbone):
    inputs = backbone.preprocess(_images(), K_SRC)
    if CAP_COND_POSE not in backbone.capabilities:
        with pytest.raises(ModeNotSupported):
            backbone.forward(inputs, _condition(1.0))
        return
    with torch.no_grad():
        a = backbone.forward(inputs, _condition(1.0))
        b = backbone.forward(inputs, _condition(10.0))
    assert a.metric and b.metric
    np.testing.assert_allclose(a.R_wc[0].numpy(), np.eye(3), atol=1e-5)
    np.testing.assert_allclose(a.t_wc[0].numpy(), np.zeros(3), atol=1e-5)
    # Scale restored: the metric centres are the least-squares image of the prediction on the condition's.
    t_cond = torch.as_tensor(_condition(1.0).T_wc[:, :3, 3], dtype=torch.float32)
    assert abs(float((a.t_wc * (a.t_wc - t_cond)).sum())) < 1e-3 * float(t_cond.square().sum())
    # The model sees the same normalised poses at both scales, so the metric output scales with them.
    np.testing.assert_allclose(b.t_wc.numpy(), 10 * a.t_wc.numpy(), rtol=1e-3, atol=1e-5)
    np.testing.assert_allclose(b.depth.numpy(), 10 * a.depth.numpy(), rtol=1e-3)
    # Differentiable under conditioning too (Pi3X's in-place translation rescale is avoided).
    params = backbone.param_groups().camera_head
    for p in params:
        p.requires_grad_(True)
    try:
        pred = backbone.forward(inputs, _condition(1.0))
        (pred.t_wc.square().sum() + pred.depth.mean()).backward()
        assert any(p.grad is not None and float(p.grad.abs().sum()) > 0 for p in params)
    finally:
        for p in params:
            p.requires_grad_(False)
            p.grad = None
