"""Gyroscope bias from the backbone's relative rotations (paper Eq. bg), and an all-pairs refinement.

Assumes the bias is constant over the clip and the backbone's rotations are unbiased; fails (returns a
poor estimate, it cannot detect it) when the backbone's rotations are wrong by more than the gyro drift.
"""

from __future__ import annotations

import numpy as np

from vi3_core import so3
from vi3_core.preintegration import Grid, integrate_rotations, merged_grid
from vi3_core.types import ImuSamples


def body_rotations(R_wc: np.ndarray, T_BC: np.ndarray) -> np.ndarray:
    """Backbone camera rotations R_C1Ci [n,3,3] -> body rotations R_B1Bi = R_BC R_C1Ci R_CB."""
    R_BC = T_BC[:3, :3]
    return R_BC @ R_wc @ R_BC.T


def gyro_bias_eq(R_vis: np.ndarray, gyro_mean: np.ndarray, dT: np.ndarray, dt_imu: float) -> np.ndarray:
    """Eq. bg on each consecutive pair, averaged over the n-1 pairs.

    R_vis: [n,3,3] body rotations from the backbone; gyro_mean: [n-1,3] average raw gyro per interval (rad/s);
    dT: [n-1] frame intervals (s); dt_imu: IMU period (s), so m = dT / dt_imu samples per interval.
    """
    dR = np.swapaxes(R_vis[:-1], 1, 2) @ R_vis[1:]
    m = dT / dt_imu
    per_sample = so3.exp(so3.log(dR) / m[:, None])
    b = -so3.log(np.swapaxes(so3.exp(gyro_mean * dt_imu), 1, 2) @ per_sample) / dt_imu  # Eq. bg
    return b.mean(axis=0)


def refine_gyro_bias(imu: ImuSamples, stamps: np.ndarray, R_vis: np.ndarray, bg: np.ndarray, iters: int, *,
                     grid: Grid | None = None) -> np.ndarray:
    """Gauss-Newton on sum_{i<j} |Log(dR_imu_ij(bg)^T dR_vis_ij)|^2 over all frame pairs.

    Uses d dR_imu_ij / d bg ~ -dT_ij I (exact as rotations vanish), so each step is a weighted mean of the
    pair residuals: delta = -sum dT_ij r_ij / sum dT_ij^2 (the same dT^2 weighting as Eq. gls). The fixed
    point is exact whatever the Jacobian's error; the iteration converges while that error is < 100 %.
    """
    n = len(stamps)
    i, j = np.triu_indices(n, k=1)
    dT = (stamps[j] - stamps[i])[:, None]
    dR_vis = np.swapaxes(R_vis[i], 1, 2) @ R_vis[j]
    grid = grid or merged_grid(imu, stamps)
    for _ in range(iters):
        R = integrate_rotations(grid, bg)[grid.frame_idx]
        r = so3.log(np.swapaxes(np.swapaxes(R[i], 1, 2) @ R[j], 1, 2) @ dR_vis)
        bg = bg - (dT * r).sum(0) / (dT**2).sum()
    return bg
