"""Pinhole back-projection on numpy arrays (the torch variant is ``camera_torch``). Pixel centres are at integer
coordinates (OpenCV convention)."""

from __future__ import annotations

import numpy as np


def backproject(depth: np.ndarray, K: np.ndarray, T_wc: np.ndarray, *,
                stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """World points of every ``stride``-th pixel of z-depth maps.

    depth [f,h,w] (metres or model units; NaN/<= 0 invalid), K [f,3,3], T_wc [f,4,4] camera-to-world. Returns
    points [f,P,3] float64 (NaN where depth is NaN) and the sampled depths [f,P], P = ceil(h/stride) ceil(w/stride).
    """
    d = np.asarray(depth, dtype=np.float64)[:, ::stride, ::stride]
    f, h, w = d.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64) * stride
    pix = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3)
    rays = pix @ np.swapaxes(np.linalg.inv(K), -1, -2)  # [f,P,3] rows K^-1 [u v 1]
    X = rays * d.reshape(f, -1, 1)
    return X @ np.swapaxes(T_wc[:, :3, :3], -1, -2) + T_wc[:, None, :3, 3], d.reshape(f, -1)
