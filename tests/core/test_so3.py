"""SO(3) helpers (numpy and torch) against scipy, including tiny and near-pi angles."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vi3_core import so3, so3_torch


def _rotvecs(rng, n=200):
    axis = rng.standard_normal((n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi - 2e-3, n - 6), [0.0, 1e-9, 1e-6, 1e-4, np.pi - 1e-4, np.pi - 1e-7]])
    return axis * angles[:, None]


def test_numpy_exp_log_match_scipy():
    w = _rotvecs(np.random.default_rng(0))
    R_ref = Rotation.from_rotvec(w).as_matrix()
    np.testing.assert_allclose(so3.exp(w), R_ref, atol=1e-12)
    w_back = so3.log(R_ref)
    # Near pi the rotation vector's sign is ambiguous: compare the rotations they represent.
    np.testing.assert_allclose(Rotation.from_rotvec(w_back).as_matrix(), R_ref, atol=1e-9)
    ok = np.linalg.norm(w, axis=1) < np.pi - 1e-3
    np.testing.assert_allclose(w_back[ok], w[ok], atol=1e-9)


def test_numpy_batch_shapes_and_quaternions():
    w = _rotvecs(np.random.default_rng(1), 24).reshape(2, 12, 3)
    R = so3.exp(w)
    assert R.shape == (2, 12, 3, 3)
    q = so3.R_to_quat(R)
    assert q.shape == (2, 12, 4) and np.all(q[..., 3] >= 0)
    np.testing.assert_allclose(so3.quat_to_R(q), R, atol=1e-12)
    np.testing.assert_allclose(so3.angle(R), np.linalg.norm(w, axis=-1), atol=1e-8)


def test_transforms_inverse_and_relative():
    rng = np.random.default_rng(2)
    T = so3.make_T(so3.exp(_rotvecs(rng, 10)[:5]), rng.standard_normal((5, 3)))
    np.testing.assert_allclose(so3.inv_T(T) @ T, np.tile(np.eye(4), (5, 1, 1)), atol=1e-12)
    rel = so3.relative_to_first(T)
    np.testing.assert_allclose(rel[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(T[0] @ rel[3], T[3], atol=1e-12)


def test_angle_between_small_and_large():
    a = np.array([0.0, 0.0, 1.0])
    for ang in [1e-9, 1e-4, 0.5, np.pi - 1e-6]:
        b = Rotation.from_rotvec([ang, 0, 0]).apply(a)
        assert so3.angle_between(a, b) == pytest.approx(ang, rel=1e-6, abs=1e-12)


def test_torch_maps_match_scipy():
    w = _rotvecs(np.random.default_rng(3))
    ok = np.linalg.norm(w, axis=1) < np.pi - 1e-2  # torch log is documented accurate away from pi
    R_t = so3_torch.exp(torch.from_numpy(w))
    np.testing.assert_allclose(R_t.numpy(), Rotation.from_rotvec(w).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(so3_torch.log(R_t).numpy()[ok], w[ok], atol=1e-6)


def test_torch_gradients_finite_at_identity():
    w = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    R = so3_torch.exp(w)
    loss = so3_torch.log(R).sum() + so3_torch.geodesic(R, torch.eye(3, dtype=torch.float64).expand(4, 3, 3)).sum()
    loss.backward()
    assert torch.isfinite(w.grad).all()
    # d/dw sum(log(exp(w))) = 1 at the identity
    np.testing.assert_allclose(w.grad.numpy(), 1.0, atol=1e-9)


def test_torch_geodesic_gradient_matches_finite_difference():
    torch.manual_seed(0)
    w = (0.3 * torch.randn(3, dtype=torch.float64)).requires_grad_()
    R_b = so3_torch.exp(torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64))
    f = lambda x: so3_torch.geodesic(so3_torch.exp(x), R_b)
    assert torch.autograd.gradcheck(f, (w,))
