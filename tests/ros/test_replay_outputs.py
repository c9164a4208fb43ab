"""The messages of a clip: the point cloud (back-projection into the clip frame, confidence and depth filtering), and
an output that cannot be built."""

from __future__ import annotations

import numpy as np

from msg_adapters.diagnostics import Level
from msg_adapters.types import jazzy_types
from vi3_core import so3
from vi3_core.types import Clip, Geometry, ImuSamples, InitResult, InitStatus
from vi3_ros.outputs import ClipPublisher, clip_status, cloud_points
from vi3_ros.params import resolve


def test_cloud_points_reproject_to_their_pixels():
    rng = np.random.default_rng(0)
    n, h, w = 3, 12, 16
    K = np.array([[20.0, 0, 7.5], [0, 21.0, 5.5], [0, 0, 1]])
    T = np.stack([so3.make_T(so3.exp(rng.normal(0, 0.2, 3)), rng.normal(0, 0.5, 3)) for _ in range(n)])
    T[0] = np.eye(4)
    depth = rng.uniform(1.0, 30.0, (n, h, w))
    depth[1, 2, 4] = np.nan
    conf = rng.uniform(0, 1, (n, h, w))
    geom = Geometry(T_wc=T, K=np.repeat(K[None], n, 0), depth=depth, conf=conf, metric=True)

    pts, c = cloud_points(geom, np.array([2]), stride=1, conf_quantile=0.0, max_depth=100.0)
    assert pts.shape == (h * w, 3) and pts.dtype == np.float32
    X = (np.linalg.inv(T[2]) @ np.c_[pts, np.ones(len(pts))].T)[:3]  # back into camera 2
    uv = (K @ X)[:2] / X[2]
    v, u = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    np.testing.assert_allclose(uv.T, np.c_[u.ravel(), v.ravel()], atol=1e-3)
    np.testing.assert_allclose(X[2], depth[2].ravel(), rtol=1e-5)
    np.testing.assert_allclose(c, conf[2].ravel(), rtol=1e-6)

    pts, c = cloud_points(geom, np.arange(n), stride=2, conf_quantile=0.5, max_depth=20.0)
    thr = np.quantile(conf[np.isfinite(depth)], 0.5)
    sub_d, sub_c = depth[:, ::2, ::2], conf[:, ::2, ::2]
    expected = np.isfinite(sub_d) & (sub_d <= 20.0) & (sub_c >= thr)
    assert len(pts) == expected.sum() and (c >= thr).all() and np.isfinite(pts).all()


def test_cloud_points_threshold_ignores_frames_without_depth():
    """A backbone that swept only some frames (the classical one in init mode) leaves the others NaN with zero
    confidence: those zeros must not pull the confidence quantile down to keep every pixel."""
    rng = np.random.default_rng(1)
    n, h, w = 8, 10, 12
    K = np.repeat(np.array([[15.0, 0, 5.5], [0, 15.0, 4.5], [0, 0, 1]])[None], n, 0)
    depth = np.full((n, h, w), np.nan)
    conf = np.zeros((n, h, w))
    depth[-1] = rng.uniform(1.0, 5.0, (h, w))
    conf[-1] = rng.uniform(0.1, 1.0, (h, w))
    geom = Geometry(T_wc=np.repeat(np.eye(4)[None], n, 0), K=K, depth=depth, conf=conf, metric=True)
    _, c = cloud_points(geom, np.array([n - 1]), stride=1, conf_quantile=0.3, max_depth=100.0)
    thr = np.quantile(conf[-1], 0.3)
    assert len(c) == (conf[-1] >= thr).sum() < h * w


def test_an_output_that_cannot_be_built_is_named_and_the_others_are_published():
    """Issue 39: a pose that failed the message's rotation check ended the clip as ``skipped: error`` (and every later
    clip the same way: the outputs stopped for good). A message that cannot be built is now named in the clip's
    status (level ERROR, ``output_errors``) and the clip's other messages are published."""
    n, h, w = 3, 6, 8
    K = np.array([[10.0, 0, 3.5], [0, 10.0, 2.5], [0, 0, 1]])
    T = np.repeat(np.eye(4)[None], n, 0)
    T[1, :3, :3] = np.diag([1.0, 1.0, -1.0])  # a mirror: no pose message can carry it
    geom = Geometry(T_wc=T, K=np.repeat(K[None], n, 0), depth=np.full((n, h, w), 2.0), conf=np.ones((n, h, w)))
    imu = ImuSamples(np.linspace(-0.1, 0.5, 7), np.zeros((7, 3)), np.tile([0.0, 0.0, 9.81], (7, 1)))
    clip = Clip(np.array([0.0, 0.2, 0.4]), np.zeros((n, h, w), np.uint8), K, np.eye(4), imu,
                stamps_ns=np.array([0, 200_000_000, 400_000_000]))
    sent = []
    publisher = ClipPublisher(resolve({}), types=jazzy_types(), publish=lambda key, msg, stamp: sent.append(key))
    publisher.geometry(clip, geom, prefix="")
    errors = publisher.take_errors()
    assert [key for key, _ in errors] == ["poses"] and errors[0][1].startswith("MalformedMessage: T rotation block")
    assert sent == ["depth", "depth_info", "points"] and publisher.take_errors() == []
    init = InitResult(InitStatus.UNOBSERVABLE, "too gentle")
    status = clip_status(0, clip, init, "none", 0.1, drops="", clip_frame="clip", output_errors=errors)
    assert status.level is Level.ERROR and status.values["output_errors"] == f"poses: {errors[0][1]}"
    assert status.message.startswith("none: too gentle; outputs not built") and status.message.endswith(": poses")
