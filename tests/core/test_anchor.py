"""anchor(): modes, the fast result before refinement, weights restored after TTR, determinism, and clips whose
initialisation is not ok (real generated EuRoC-format clip, the embedded classical backbone)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from vi3_core.anchor import AnchorOptions, anchor
from vi3_core.backbones import make_backbone
from vi3_core.dataset.asl import read_asl
from vi3_core.dataset.generate import cached_sequence
from vi3_core.dataset.sequence import make_clip
from vi3_core.errors import ModeNotSupported
from vi3_core.init import InitOptions
from vi3_core.types import ImuSamples

STEPS = 12
#: These tests are about anchoring, not about which clips may claim a scale (tests/core/test_init.py): a single 0.7 s
#: clip rarely passes the error model's gate on its own, so the gate is opened here.
OPEN_GATE = InitOptions(max_scale_sigma=10.0)


@pytest.fixture(scope="module")
def clip(cache_dir):
    return make_clip(read_asl(cached_sequence(cache_dir, seconds=4.0, seed=0) / "mav0"), np.arange(20, 36, 2))


@pytest.fixture(scope="module")
def backbone():
    return make_backbone("classical")


@pytest.mark.slow
def test_ttr_reports_init_first_then_refines_and_restores_the_weights(clip, backbone):
    seen = []
    result = anchor(clip, backbone, mode="ttr", options=AnchorOptions(ttr_steps=STEPS), on_init=seen.append,
                    init_options=OPEN_GATE)
    assert len(seen) == 1 and seen[0].mode == "init" and seen[0].geometry.metric
    assert result.mode == "ttr" and result.status == "ok" and result.geometry.metric
    assert len(result.alphas) == STEPS and np.all(result.alphas > 0)
    assert set(result.losses) == {"rot", "pos", "dcons", "anchor_pos", "anchor_depth", "total"}
    assert all(np.all(np.isfinite(v)) for v in result.losses.values())
    assert result.losses["total"][-1] < result.losses["total"][0]
    assert result.timings["ttr_ms_per_iter"] > 0
    # Every clip starts from the pretrained weights: the trainable groups are back to their values (zero
    # corrections for the classical backbone).
    for p in backbone.param_groups().trainable(8):
        assert torch.count_nonzero(p) == 0
    again = anchor(clip, backbone, mode="ttr", options=AnchorOptions(ttr_steps=STEPS), init_options=OPEN_GATE)
    np.testing.assert_array_equal(again.geometry.T_wc, result.geometry.T_wc)
    np.testing.assert_array_equal(again.alphas, result.alphas)


@pytest.mark.slow
def test_init_mode_scales_translation_and_depth_only(clip, backbone):
    result = anchor(clip, backbone, mode="init", init_options=OPEN_GATE)
    s = result.init.scale
    assert result.mode == "init" and result.alpha == s and not result.losses
    np.testing.assert_allclose(result.geometry.T_wc[:, :3, 3], s * result.base.T_wc[:, :3, 3])
    np.testing.assert_allclose(result.geometry.T_wc[:, :3, :3], result.base.T_wc[:, :3, :3])
    np.testing.assert_allclose(result.geometry.depth, s * result.base.depth, rtol=1e-6)


@pytest.mark.slow
def test_a_clip_whose_init_is_not_ok_is_not_refined_and_says_why(clip, backbone):
    accel = clip.imu.accel.copy()
    accel[len(accel) // 2] = np.nan
    bad = dataclasses.replace(clip, imu=ImuSamples(clip.imu.t, clip.imu.gyro, accel))
    seen = []
    result = anchor(bad, backbone, mode="ttr", options=AnchorOptions(ttr_steps=STEPS), on_init=seen.append)
    assert result.mode == "none" and not result.losses and len(result.alphas) == 0
    assert result.status.startswith("rejected") and "NaN" in result.status
    assert seen and seen[0].mode == "none"
    assert not result.geometry.metric


def test_unsupported_mode_fails_before_any_work(clip, backbone):
    with pytest.raises(ModeNotSupported, match="cond"):
        anchor(clip, backbone, mode="cond")
    with pytest.raises(ValueError, match="unknown anchoring mode"):
        anchor(clip, backbone, mode="magic")
