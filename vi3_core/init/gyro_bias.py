"""Gyroscope bias from the backbone's relative rotations (paper Eq. bg), an all-pairs refinement, and the check
that the two agree.

Assumes the bias is constant over the clip and the backbone's rotations are unbiased. A backbone whose rotations
are wrong by more than the gyro drift leaves residuals of that size after the fit (``rotation_check``): a clip
whose relative rotations disagree with the bias-corrected gyro by degrees is a backbone failure.

Both estimates assume small rotations between the frames they compare (Eq. bg splits an interval's rotation evenly
over its samples; the refinement's Jacobian is -dT I). A clip whose first frames stand in for dropped clips (shared
frames, ``vi3_core.online``) has a long interval after them, over which the body may turn by a radian: the estimates
then use only the pairs that straddle no such gap (``steady_pairs``), and the check still covers every pair.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from vi3_core import so3
from vi3_core.preintegration import Grid, frame_rotations, merged_grid
from vi3_core.types import ImuSamples


def body_rotations(R_wc: np.ndarray, T_BC: np.ndarray) -> np.ndarray:
    """Backbone camera rotations R_C1Ci [n,3,3] -> body rotations R_B1Bi = R_BC R_C1Ci R_CB."""
    R_BC = T_BC[:3, :3]
    return R_BC @ R_wc @ R_BC.T


GAP_FACTOR = 2.0  # a frame interval this many times the median one is a gap (frames that stand in for dropped clips)


def gaps(stamps: np.ndarray) -> np.ndarray:
    """[n-1] bool: the frame intervals of ``stamps`` [n] s longer than GAP_FACTOR times their median."""
    dT = np.diff(stamps)
    return dT > GAP_FACTOR * np.median(dT)


def steady_pairs(stamps: np.ndarray) -> np.ndarray:
    """[P] bool over every frame pair i < j (``_pair_indices`` order): the pair straddles no gap (``gaps``)."""
    i, j = _pair_indices(len(stamps))
    before = np.concatenate([[0], np.cumsum(gaps(stamps))])  # gaps before each frame
    return before[j] == before[i]


def gyro_bias_eq(R_vis: np.ndarray, gyro_mean: np.ndarray, dT: np.ndarray, dt_imu: float) -> np.ndarray:
    """Eq. bg on each consecutive pair, averaged over the n-1 pairs (over those that are no gap, when some are).

    R_vis: [n,3,3] body rotations from the backbone; gyro_mean: [n-1,3] average raw gyro per interval (rad/s);
    dT: [n-1] frame intervals (s); dt_imu: IMU period (s), so m = dT / dt_imu samples per interval.
    """
    dR = np.swapaxes(R_vis[:-1], 1, 2) @ R_vis[1:]
    m = dT / dt_imu
    per_sample = so3.exp(so3.log(dR) / m[:, None])
    b = -so3.log(np.swapaxes(so3.exp(gyro_mean * dt_imu), 1, 2) @ per_sample) / dt_imu  # Eq. bg
    steady = dT <= GAP_FACTOR * np.median(dT)
    return b[steady].mean(axis=0) if steady.any() else b.mean(axis=0)


def refine_gyro_bias(imu: ImuSamples, stamps: np.ndarray, R_vis: np.ndarray, bg: np.ndarray, iters: int, *,
                     grid: Grid | None = None) -> np.ndarray:
    """Gauss-Newton on sum_{i<j} |Log(dR_imu_ij(bg)^T dR_vis_ij)|^2 over all frame pairs.

    Uses d dR_imu_ij / d bg ~ -dT_ij I (exact as rotations vanish), so each step is a weighted mean of the
    pair residuals: delta = -sum dT_ij r_ij / sum dT_ij^2 (the same dT^2 weighting as Eq. gls). The fixed
    point is exact whatever the Jacobian's error; the iteration converges while that error is < 100 %.
    """
    grid = grid or merged_grid(imu, stamps)
    pairs = _FramePairs.of(stamps, R_vis)
    dT = np.where(steady_pairs(stamps), pairs.dT, 0.0)  # pairs across a gap carry no weight
    weight = dT[:, None] / (dT**2).sum()
    for _ in range(iters):
        r = pairs.residual(frame_rotations(grid, bg))
        bg = bg - (weight * r).sum(0)
    return bg


@dataclass(frozen=True)
class _FramePairs:
    """Every frame pair i < j [P] with dT [P] s and the backbone's relative rotations dR_vis [P,3,3]."""

    i: np.ndarray
    j: np.ndarray
    dT: np.ndarray
    dR_vis: np.ndarray

    @staticmethod
    def of(stamps: np.ndarray, R_vis: np.ndarray) -> _FramePairs:
        i, j = _pair_indices(len(stamps))
        return _FramePairs(i, j, stamps[j] - stamps[i], np.swapaxes(R_vis[i], 1, 2) @ R_vis[j])

    def residual(self, R: np.ndarray) -> np.ndarray:
        """[P,3] rad: Log(dR_imu_ij^T dR_vis_ij) for the gyro's rotations R [n,3,3] at the frames."""
        return so3.log(np.swapaxes(R[self.j], 1, 2) @ R[self.i] @ self.dR_vis)


@functools.lru_cache(maxsize=16)
def _pair_indices(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(i, j) [n (n-1) / 2] of every frame pair i < j, read-only (shared between calls)."""
    i, j = np.triu_indices(n, k=1)
    i.flags.writeable = j.flags.writeable = False
    return i, j


@dataclass(frozen=True)
class RotationCheck:
    """How the backbone's relative rotations agree with the gyro integrated with a bias estimate, over all frame pairs
    i < j: residual [P,3] rad (Log(dR_imu_ij^T dR_vis_ij)), i, j [P] frame indices, dT [P] s."""

    residual: np.ndarray
    i: np.ndarray
    j: np.ndarray
    dT: np.ndarray

    def worst(self) -> tuple[float, int, int]:
        """(largest residual angle in degrees, i, j) of the pair that disagrees most."""
        ang = np.linalg.norm(self.residual, axis=1)
        k = int(np.argmax(ang))
        return float(np.degrees(ang[k])), int(self.i[k]), int(self.j[k])

    def bias_sigma(self, n: int) -> float:
        """1-sigma (rad/s, per axis) of the all-pairs bias estimate from the per-frame rotation noise that the residuals
        show: with r_ij = e_j - e_i, the estimate -sum dT_ij r_ij / sum dT_ij^2 weighs frame m's error e_m by c_m =
        sum_(pairs ending at m) dT - sum_(pairs starting at m) dT; sigma_e^2 = mean |r_ij|^2 / 6 (two frames, three
        axes)."""
        c = np.bincount(self.j, self.dT, minlength=n) - np.bincount(self.i, self.dT, minlength=n)
        sigma_e = np.sqrt(float((self.residual**2).sum(1).mean()) / 6.0)
        return float(sigma_e * np.sqrt((c**2).sum()) / (self.dT**2).sum())


def rotation_check(imu: ImuSamples, stamps: np.ndarray, R_vis: np.ndarray, bg: np.ndarray, *,
                   grid: Grid | None = None) -> RotationCheck:
    """Residuals of the backbone's body rotations R_vis [n,3,3] against the gyro integrated with ``bg`` [3] rad/s over
    every frame pair (the quantity ``refine_gyro_bias`` minimises)."""
    grid = grid or merged_grid(imu, stamps)
    pairs = _FramePairs.of(stamps, R_vis)
    return RotationCheck(residual=pairs.residual(frame_rotations(grid, bg)), i=pairs.i, j=pairs.j, dT=pairs.dT)
