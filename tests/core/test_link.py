"""``vi3_core.online.link``: the scale ratio of two clips measured on the frames they share, from depth and poses,
with a sigma that covers its error; and the instrument's depth noise it is measured against."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from vi3_core import so3
from vi3_core.online.link import SharedFrames, depth_link, measure_link, pose_link
from vi3_core.sim.visual import DepthNoise
from vi3_core.types import Clip, Geometry, ImuSamples, UnitsLink

H, W = 60, 80


def _scene_depth(rng: np.random.Generator) -> np.ndarray:
    """A [1,H,W] metric depth map: a slanted plane with boxes, 2-8 m."""
    y, x = np.mgrid[0:H, 0:W]
    d = 3.0 + 2.0 * x / W + 1.0 * y / H
    d[10:30, 20:40] = 2.0
    d[35:55, 50:75] = 6.5 + rng.uniform(0, 1)
    return d[None].astype(np.float32)


def test_depth_link_recovers_the_scale_ratio_with_an_honest_sigma():
    """Two clips predict a shared frame at model scales 1/2 and 1/3 of the metres (ratio 2/3) with independent noise
    (5 % per pixel, 2 % smooth field): over 200 draws the ratio is unbiased and within 2 sigma 85-99.5 % of the time."""
    rng = np.random.default_rng(0)
    z = []
    for _ in range(200):
        metres = _scene_depth(rng)
        noise = DepthNoise(0.05, 0.02)
        prev, new = noise.apply(metres / 2.0, rng), noise.apply(metres / 3.0, rng)
        log_r, sigma, blocks = depth_link(prev, np.ones_like(prev), new, np.ones_like(new), sigma_floor=0.0)
        assert blocks == 16 and 0.002 < sigma < 0.05
        z.append((log_r - math.log(2.0 / 3.0)) / sigma)
    z = np.abs(np.array(z))
    assert abs(np.median(z)) < 1.0 and 0.85 <= np.mean(z <= 2.0) <= 0.995, np.mean(z <= 2.0)


def test_depth_link_needs_valid_blocks_and_matching_maps():
    rng = np.random.default_rng(1)
    d = _scene_depth(rng)
    empty = np.full_like(d, np.nan)
    assert "depth blocks valid" in depth_link(d, np.ones_like(d), empty, np.ones_like(d), sigma_floor=0.0)
    assert "different shapes" in depth_link(d, np.ones_like(d), d[:, :30], np.ones_like(d[:, :30]), sigma_floor=0.0)
    low_conf = np.zeros_like(d)
    low_conf[:, :5, :5] = 1.0  # only a corner is trusted in one map: too few blocks
    assert isinstance(depth_link(d, low_conf, d, np.ones_like(d), sigma_floor=0.0), str)
    log_r, sigma, _ = depth_link(d, np.ones_like(d), d * 1.25, np.ones_like(d), sigma_floor=0.01)
    assert log_r == pytest.approx(math.log(1.25), abs=1e-6) and sigma == pytest.approx(0.01, rel=1e-3)


def test_pose_link_from_the_displacement_of_two_shared_frames():
    T0, T1 = np.eye(4), so3.make_T(so3.exp(np.array([0.0, 0.1, 0.0])), np.array([0.3, 0.0, 0.1]))
    prev = np.stack([T0, T1])
    new = prev.copy()
    new[:, :3, 3] *= 1.5
    log_r, sigma = pose_link(prev, 0.001, new, 0.0015)
    assert log_r == pytest.approx(math.log(1.5)) and sigma == pytest.approx(math.hypot(math.sqrt(2) * 0.001 / 0.316,
                                                                                       math.sqrt(2) * 0.0015 / 0.474),
                                                                            rel=0.01)
    assert "one shared frame" in pose_link(prev[:1], 0.001, new[:1], 0.001)
    assert "moved too little" in pose_link(prev, 0.05, new, 0.05)


def _clip(stamps: np.ndarray, depth: np.ndarray, history_s: float = 0.0) -> tuple[Clip, Geometry]:
    n = len(stamps)
    imu = ImuSamples(np.linspace(stamps[0] - 0.01 - history_s, stamps[-1] + 0.01, 200), np.zeros((200, 3)),
                     np.zeros((200, 3)))
    T = np.repeat(np.eye(4)[None], n, 0)
    T[:, 0, 3] = np.linspace(0, 0.5, n)
    clip = Clip(stamps=stamps, images=np.zeros((n, 4, 4), np.uint8), K=np.eye(3), T_BC=np.eye(4), imu=imu,
                imu_history=imu, stamps_ns=np.round(stamps * 1e9).astype(np.int64))
    return clip, Geometry(T_wc=T, K=np.repeat(np.eye(3)[None], n, 0), depth=depth, conf=np.ones_like(depth))


def test_shared_frames_link_a_clip_that_starts_with_them_and_stand_in_for_dropped_ones():
    rng = np.random.default_rng(2)
    metres = np.concatenate([_scene_depth(rng)] * 4)
    first, geo_first = _clip(np.array([0.0, 0.1, 0.2, 0.3]), metres / 2.0)
    shared = SharedFrames.of(first, geo_first, k=1, sigma_v=0.001)
    assert shared.clip_start == 0.0 and np.array_equal(shared.stamps, [0.3]) and shared.stamps_ns[0] == 300_000_000
    nxt, geo_nxt = _clip(np.array([0.3, 0.4, 0.5, 0.6]), metres / 4.0)
    assert shared.starts(nxt)
    got = measure_link(shared, geo_nxt, 0.001, sigma_floor=0.005)
    assert got.source == "depth" and got.frames == 1 and got.link.log_ratio == pytest.approx(math.log(0.5), abs=1e-6)
    assert "0.5000 +- 0.50 %" in got.describe()
    # a later clip (the ones between dropped): the shared frame takes the place of its first frame, IMU from history
    later, _ = _clip(np.array([0.9, 1.0, 1.1, 1.2]), metres, history_s=1.0)
    assert not shared.starts(later)
    into = shared.into(later)
    assert np.array_equal(into.stamps, [0.3, 1.0, 1.1, 1.2]) and into.imu.t[0] <= 0.3
    assert np.array_equal(into.stamps_ns, [300_000_000, 1_000_000_000, 1_100_000_000, 1_200_000_000])
    assert shared.into(Clip(**{**later.__dict__, "imu_history": None})) is None  # no IMU back to the shared frame


def test_a_backbones_own_units_link_joins_the_depth_link_when_they_agree():
    """A backbone that says how its units moved (``UnitsLink``, the classical keyframes) to the clip the shared frame
    came from: its ratio (its sigma with the floor) joins the depth link's, weighted by their sigmas, where the two
    agree within 3 sigmas of both and of the two clips' trajectory against their depth (the units read the
    trajectories, the depth the plane sweeps); beyond, the link is refused, naming both; a units link to another clip
    is not used."""
    rng = np.random.default_rng(2)
    metres = np.concatenate([_scene_depth(rng)] * 4)
    first, geo_first = _clip(np.array([0.0, 0.1, 0.2, 0.3]), metres / 2.0)
    shared = SharedFrames.of(first, replace(geo_first, traj_depth_sigma=0.03), k=1, sigma_v=0.001)
    assert shared.traj_depth_sigma == 0.03
    nxt, geo_nxt = _clip(np.array([0.3, 0.4, 0.5, 0.6]), metres / 4.0)
    depth = measure_link(shared, geo_nxt, 0.001, sigma_floor=0.005)
    assert depth.source == "depth"
    d, sd = depth.link.log_ratio, depth.link.sigma
    units = UnitsLink(0.0, math.log(0.5) + 0.08, 0.01)  # 8 % from the depth's: within 3 x hypot(0.5, 1.1, 3) %
    got = measure_link(shared, replace(geo_nxt, units_link=units), 0.001, sigma_floor=0.005)
    su = math.hypot(0.01, 0.005)
    w = np.array([sd**-2, su**-2])
    assert got.source == "depth+units" and "depth+units of 1 frame(s)" in got.describe()
    assert got.link.sigma == pytest.approx(w.sum() ** -0.5)
    assert got.link.log_ratio == pytest.approx((w @ [d, units.log_ratio]) / w.sum())
    refused = measure_link(replace(shared, traj_depth_sigma=0.0), replace(geo_nxt, units_link=units), 0.001,
                           sigma_floor=0.005)
    assert isinstance(refused, str) and refused.startswith("depth (0.5000") and "units (0.5416" in refused
    elsewhere = measure_link(shared, replace(geo_nxt, units_link=replace(units, prev_start=0.1)), 0.001,
                             sigma_floor=0.005)
    assert elsewhere.source == "depth" and elsewhere.link.log_ratio == d
