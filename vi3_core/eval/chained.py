"""Metrics of the chained odom trajectory (``vi3_core.online``) against ground truth.

Gravity fixes roll and pitch of odom, so only the yaw and the position of the first pose are aligned (4 DoF, no
scale): ATE is the RMS position error after that alignment, drift the final position error per metre travelled
(ground-truth path length), and the gravity error the mean angle between the up axis of odom and the true one,
both seen from the body. The per-clip scale errors |Scale (Traj.) - 1| of the chained run and of the same clips'
own GT-free initialisation (what the paper's per-clip pipeline outputs, computed in the same run) are compared by
their medians after the first ``SCALE_SKIP_CLIPS`` clips, while the window fills, and by how many clips (all of
them) claim a scale more than ``SCALE_OUTLIER`` off: a confident wrong scale, the failure a flight stack cares about.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from vi3_core import so3
from vi3_core.errors import DataError

SCALE_SKIP_CLIPS = 3
SCALE_OUTLIER = 0.1
NO_CLIPS = np.zeros(0)


@dataclass(frozen=True)
class ChainedMetrics:
    """ate_m: m; drift_pct: % of distance_m (GT path length, m); gravity_err_deg: deg; resets: state resets
    after the first clip; frames: poses compared; scale_err_median: median |Scale (Traj.) - 1| of the chained
    clips after the first SCALE_SKIP_CLIPS; independent_scale_err_median: the same for the clips' own GT-free
    initialisation (NaN where no clip has a value); scale_outliers, independent_scale_outliers: clips whose
    |Scale (Traj.) - 1| > SCALE_OUTLIER, chained and independent."""

    ate_m: float
    drift_pct: float
    gravity_err_deg: float
    resets: int
    distance_m: float
    frames: int
    scale_err_median: float = float("nan")
    independent_scale_err_median: float = float("nan")
    scale_outliers: int = 0
    independent_scale_outliers: int = 0

    def as_dict(self) -> dict:
        return asdict(self)


def align_yaw_first(T_OB: np.ndarray, T_WB: np.ndarray) -> np.ndarray:
    """Positions [N,3] of T_OB [N,4,4] in W after the rotation about z and the translation that bring the first
    pose onto T_WB[0]'s position and heading (yaw of R_WB0 R_OB0^T)."""
    dR = T_WB[0, :3, :3] @ T_OB[0, :3, :3].T
    yaw = math.atan2(dR[1, 0] - dR[0, 1], dR[0, 0] + dR[1, 1])
    Rz = so3.exp(np.array([0.0, 0.0, yaw]))
    return (T_OB[:, :3, 3] - T_OB[0, :3, 3]) @ Rz.T + T_WB[0, :3, 3]


def scored_tail(errors: np.ndarray) -> np.ndarray:
    """The per-clip errors [n] that the scale medians score: finite values after the first SCALE_SKIP_CLIPS."""
    tail = np.asarray(errors, dtype=np.float64)[SCALE_SKIP_CLIPS:]
    return tail[np.isfinite(tail)]


def median_after_skip(errors: np.ndarray) -> float:
    """Median of ``scored_tail(errors)`` (NaN if empty)."""
    tail = scored_tail(errors)
    return float(np.median(tail)) if tail.size else float("nan")


def count_outliers(errors: np.ndarray) -> int:
    """Clips [n] whose scale error exceeds SCALE_OUTLIER (NaN: no scale claimed, not counted)."""
    errors = np.asarray(errors, dtype=np.float64)
    return int((errors[np.isfinite(errors)] > SCALE_OUTLIER).sum())


def chained_metrics(T_OB: np.ndarray, T_WB: np.ndarray, *, resets: int, scale_err: np.ndarray = NO_CLIPS,
                    independent_scale_err: np.ndarray = NO_CLIPS) -> ChainedMetrics:
    """T_OB, T_WB: [N,4,4] estimated (odom) and GT (world, z up) body poses at the same stamps, N >= 2;
    scale_err, independent_scale_err: [n_clips] per-clip |Scale (Traj.) - 1| (NaN: no value), in clip order."""
    if len(T_OB) != len(T_WB) or len(T_OB) < 2:
        raise DataError(f"chained metrics need >= 2 matching poses, got {len(T_OB)} estimated and {len(T_WB)} GT")
    p = align_yaw_first(T_OB, T_WB)
    err = np.linalg.norm(p - T_WB[:, :3, 3], axis=1)
    distance = float(np.linalg.norm(np.diff(T_WB[:, :3, 3], axis=0), axis=1).sum())
    up_est = T_OB[:, 2, :3]  # odom z axis in the body frame: row 2 of R_OB
    up_gt = T_WB[:, 2, :3]
    grav = np.degrees(so3.angle_between(up_est, up_gt))
    return ChainedMetrics(ate_m=float(np.sqrt((err**2).mean())),
                          drift_pct=float(100.0 * err[-1] / distance) if distance > 0 else float("nan"),
                          gravity_err_deg=float(np.mean(grav)), resets=int(resets), distance_m=distance,
                          frames=len(T_OB), scale_err_median=median_after_skip(scale_err),
                          independent_scale_err_median=median_after_skip(independent_scale_err),
                          scale_outliers=count_outliers(scale_err),
                          independent_scale_outliers=count_outliers(independent_scale_err))
