"""SO(3)/SE(3) helpers on numpy arrays, batched over leading axes, built on scipy's Rotation.

Rotation vectors are axis * angle in radians; quaternions are (x, y, z, w) as in ROS messages.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def hat(w: np.ndarray) -> np.ndarray:
    """[...,3] -> [...,3,3] skew-symmetric matrices with hat(w) @ x = w x x."""
    w = np.asarray(w, dtype=np.float64)
    O = np.zeros(w.shape[:-1] + (3, 3))
    O[..., 0, 1], O[..., 0, 2] = -w[..., 2], w[..., 1]
    O[..., 1, 0], O[..., 1, 2] = w[..., 2], -w[..., 0]
    O[..., 2, 0], O[..., 2, 1] = -w[..., 1], w[..., 0]
    return O


def exp(w: np.ndarray) -> np.ndarray:
    """Exp: [...,3] rotation vectors -> [...,3,3] rotation matrices (Rodrigues; Taylor terms below 1e-4 rad)."""
    w = np.asarray(w, dtype=np.float64)
    th2 = (w * w).sum(-1)
    small = th2 < 1e-8
    th2s = np.where(small, 1.0, th2)
    th = np.sqrt(th2s)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(th) / th)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(th)) / th2s)
    # I + a K + b K^2 with K^2 = w w^T - th2 I, written into one array (numpy's per-call cost dominates 3x3 blocks)
    R = (b[..., None] * w)[..., :, None] * w[..., None, :]
    aw = a[..., None] * w
    c = 1.0 - b * th2
    R[..., 0, 0] += c
    R[..., 1, 1] += c
    R[..., 2, 2] += c
    R[..., 0, 1] -= aw[..., 2]
    R[..., 0, 2] += aw[..., 1]
    R[..., 1, 0] += aw[..., 2]
    R[..., 1, 2] -= aw[..., 0]
    R[..., 2, 0] -= aw[..., 1]
    R[..., 2, 1] += aw[..., 0]
    return R


def log(R: np.ndarray) -> np.ndarray:
    """Log: [...,3,3] rotation matrices -> [...,3] rotation vectors, angle in [0, pi].

    Closed form from the skew part; rows within 1e-3 rad of pi (axis ill-conditioned there) go through
    scipy's quaternion-based conversion.
    """
    R = np.asarray(R, dtype=np.float64)
    vee = np.empty(R.shape[:-1])
    np.subtract(R[..., 2, 1], R[..., 1, 2], out=vee[..., 0])
    np.subtract(R[..., 0, 2], R[..., 2, 0], out=vee[..., 1])
    np.subtract(R[..., 1, 0], R[..., 0, 1], out=vee[..., 2])
    # the trace, clip and norm spelled out: numpy's wrappers cost more than the arithmetic on small batches
    cos = np.minimum(np.maximum((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) * 0.5, -1.0), 1.0)
    sin = 0.5 * np.sqrt((vee * vee).sum(-1))
    th = np.arctan2(sin, cos)
    small = th < 1e-4
    factor = np.where(small, 0.5 + th * th / 12.0, 0.5 * th / np.where(small, 1.0, sin))
    out = factor[..., None] * vee
    near_pi = th > np.pi - 1e-3
    if np.any(near_pi):
        out[near_pi] = Rotation.from_matrix(R[near_pi]).as_rotvec()
    return out


def angle(R: np.ndarray) -> np.ndarray:
    """Geodesic angle [...] in radians of rotation matrices [...,3,3] (stable near 0 and pi)."""
    return np.linalg.norm(log(R), axis=-1)


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in radians between vectors a and b [...,3] (atan2 form: accurate for tiny angles)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def quat_to_R(q: np.ndarray) -> np.ndarray:
    """[...,4] quaternions (x, y, z, w), any norm -> [...,3,3]."""
    q = np.asarray(q, dtype=np.float64)
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(q.shape[:-1] + (3, 3))


def R_to_quat(R: np.ndarray) -> np.ndarray:
    """[...,3,3] -> [...,4] unit quaternions (x, y, z, w) with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat(canonical=True).reshape(R.shape[:-2] + (4,))


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """[...,3,3] -> the nearest rotation matrices [...,3,3] (Frobenius norm; the orthogonal polar factor U V^T of
    R = U S V^T, its determinant made +1). Composed rotations lose orthonormality to round-off, linearly with the
    number of products (a calibration file's rotation given to 8 digits is 1e-6 off; float32 poses are 6e-8 off):
    whatever is composed without end (the odom chain, a calibration applied to every clip) goes through this."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    d = np.sign(np.linalg.det(U @ Vt))
    return (U * np.concatenate([np.ones(d.shape + (2,)), d[..., None]], -1)[..., None, :]) @ Vt


def orthonormality_error(R: np.ndarray) -> float:
    """max |R^T R - I| over rotation matrices [...,3,3] (0 for none)."""
    R = np.asarray(R, dtype=np.float64)
    return float(np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(initial=0.0))


def make_T(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """[...,3,3] and [...,3] -> [...,4,4] homogeneous transforms."""
    R, p = np.asarray(R, dtype=np.float64), np.asarray(p, dtype=np.float64)
    T = np.zeros(np.broadcast_shapes(R.shape[:-2], p.shape[:-1]) + (4, 4))
    T[..., :3, :3], T[..., :3, 3], T[..., 3, 3] = R, p, 1.0
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms [...,4,4]."""
    T = np.asarray(T, dtype=np.float64)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_T(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def turn_T(T: np.ndarray, w: np.ndarray) -> np.ndarray:
    """A copy of the transform ``T`` [4,4] with its rotation turned by Exp(w) (w [3] rad, in the frame T maps into:
    R -> Exp(w) R), its translation kept: a camera mount T_BC turned about the body axes."""
    T = np.array(T, dtype=np.float64, copy=True)
    T[:3, :3] = exp(w) @ T[:3, :3]
    return T


def relative_to_first(T: np.ndarray) -> np.ndarray:
    """Re-anchor poses [n,4,4] (X -> world) so that the first is the identity: T_0^-1 T_i."""
    return np.einsum("ij,njk->nik", inv_T(T[0]), T)
