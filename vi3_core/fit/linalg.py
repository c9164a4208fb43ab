"""Small dense linear algebra of the fits: least squares and inverses through LAPACK at low call cost, the Student-t
quantile of the scale's interval, and a basis of gravity's tangent plane."""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy.linalg import lapack

Z975 = 1.959964


def lstsq(A: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The minimum-norm least-squares solution x [n] of A [m,n] x = y [m] (m >= n), the rank taken where the condition
    number reaches 1 / (eps max(m, n)), as ``np.linalg.lstsq(A, y, rcond=None)``; by LAPACK's complete orthogonal
    factorisation (gelsy), a quarter of the cost of numpy's SVD on the fit's small systems."""
    m, n = A.shape
    cond = np.finfo(np.float64).eps * max(m, n)
    x, info = lapack.dgelsy(A, y, np.zeros(n, np.int32), cond, _gelsy_lwork(m, n, cond))[1::3]
    if info != 0:
        raise np.linalg.LinAlgError(f"lstsq: LAPACK gelsy failed (info {info}) on a {m}x{n} system")
    return x[:n]


def inv(H: np.ndarray) -> np.ndarray:
    """H^-1 [n,n] by LU (LAPACK getrf/getri, as ``np.linalg.inv`` at a third of its call cost), the pseudo-inverse
    where H is exactly singular."""
    lu, piv, info = lapack.dgetrf(H)
    if info == 0:
        Hi, info = lapack.dgetri(lu, piv)
        if info == 0:
            return Hi
    return np.linalg.pinv(H)


@functools.lru_cache(maxsize=64)
def _gelsy_lwork(m: int, n: int, cond: float) -> int:
    work, info = lapack.dgelsy_lwork(m, n, 1, cond)
    return int(work)


def t975(dof: float) -> float:
    """Student-t 97.5 % quantile for ``dof`` degrees of freedom (Cornish-Fisher, within 1e-3 from 3 dof up)."""
    z = Z975
    return z + (z**3 + z) / (4.0 * dof) + (5 * z**5 + 16 * z**3 + 3 * z) / (96.0 * dof**2)


def tangent_basis(
u: np.ndarray) -> np.ndarray:
    """Two unit vectors [3,2] orthogonal to the unit vector u and to each other."""
    ux, uy, uz = u.tolist()  # plain floats: numpy's per-call cost dwarfs the arithmetic here
    size = [abs(ux), abs(uy), abs(uz)]
    axis = size.index(min(size))  # the axis least aligned with u
    ex, ey, ez = (1.0 if a == axis else 0.0 for a in range(3))
    b1x, b1y, b1z = uy * ez - uz * ey, uz * ex - ux * ez, ux * ey - uy * ex
    norm = math.sqrt(b1x * b1x + b1y * b1y + b1z * b1z)
    b1x, b1y, b1z = b1x / norm, b1y / norm, b1z / norm
    return np.array([[b1x, uy * b1z - uz * b1y], [b1y, uz * b1x - ux * b1z], [b1z, ux * b1y - uy * b1x]])



__all__ = ["Z975", "inv", "lstsq", "t975", "tangent_basis"]
