"""Back-projection (numpy) and pixel rays (torch) agree with projection and with each other."""

import numpy as np
import torch

from vi3_core import so3
from vi3_core.camera import backproject
from vi3_core.camera_torch import pixel_rays


def test_backprojected_points_project_back_to_their_pixels():
    rng = np.random.default_rng(0)
    f, h, w, stride = 2, 10, 14, 3
    depth = rng.uniform(1.0, 4.0, (f, h, w))
    depth[1, 3, 3] = np.nan
    K = np.tile(np.array([[30.0, 0.0, 7.2], [0.0, 31.0, 4.9], [0.0, 0.0, 1.0]]), (f, 1, 1))
    T = so3.make_T(so3.exp(rng.normal(0, 0.2, (f, 3))), rng.normal(0, 1, (f, 3)))
    P, d = backproject(depth, K, T, stride=stride)
    assert P.shape == (f, 4 * 5, 3) and d.shape == (f, 20)
    X = np.einsum("fji,fpj->fpi", T[:, :3, :3], P - T[:, None, :3, 3])  # back into each camera
    uv = np.einsum("fij,fpj->fpi", K, X)
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    ok = np.isfinite(d)
    assert (~ok).sum() == 1
    pixels = np.broadcast_to(np.stack([u, v], -1).reshape(-1, 2), (f, 20, 2))
    np.testing.assert_allclose((uv[..., :2] / uv[..., 2:])[ok], pixels[ok], atol=1e-9)
    np.testing.assert_allclose(X[..., 2][ok], d[ok], atol=1e-12)


def test_torch_rays_match_numpy_backprojection_at_unit_depth():
    K = np.array([[[50.0, 0.0, 20.5], [0.0, 48.0, 11.0], [0.0, 0.0, 1.0]]])
    rays = pixel_rays(torch.tensor(K), 9, 13, stride=2).numpy()
    P, _ = backproject(np.ones((1, 9, 13)), K, np.eye(4)[None], stride=2)
    np.testing.assert_allclose(rays, P, atol=1e-12)
    np.testing.assert_allclose(rays[..., 2], 1.0)
