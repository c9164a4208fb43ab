"""Metrics of the chained odom trajectory (``vi3_core.online``) against ground truth.

Gravity fixes roll and pitch of odom, so only the yaw and the position of the first pose are aligned (4 DoF, no
scale). The trajectory is scored per **segment**: the estimator starts a new one (``Trajectory.resets``, the first
stamp of each) wherever it placed a clip without a trustworthy IMU bridge from the one before, so positions across
that boundary are not comparable; each segment is aligned on its own first pose. Per segment, ATE is the RMS
position error after that alignment and drift the final position error per metre travelled (the ground truth's
path over the segment's time span, stretches without poses included: ``gt_path_length``); overall, ATE is the RMS
over every frame of the per-segment errors and drift the segments' final errors summed per metre of their summed
paths. The gravity error is the mean angle between the up axis of odom and the true one, seen from the body.

The per-clip scale errors |Scale (Traj.) - 1| of the chained run and of the same clips' own GT-free initialisation
are compared by their medians after the first ``SCALE_SKIP_CLIPS`` clips, while the window fills
(``median_after_skip``); how many claimed clips are far off is ``vi3_core.eval.claims``' job.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

from vi3_core import so3
from vi3_core.errors import DataError

if TYPE_CHECKING:
    from vi3_core.dataset.sequence import GroundTruthTrack

SCALE_SKIP_CLIPS = 3


@dataclass(frozen=True)
class SegmentMetrics:
    """One segment of the chained trajectory: t0, t1: its first and last stamps, s; frames: poses; distance_m: the
    metres the ground truth flew from t0 to t1 (``path_length``; between its compared frames when not given); ate_m:
    m; drift_pct: the final error in % of distance_m (NaN when the segment does not move)."""

    t0: float
    t1: float
    frames: int
    distance_m: float
    ate_m: float
    drift_pct: float


@dataclass(frozen=True)
class ChainedMetrics:
    """The whole trajectory: ate_m: m (RMS over every frame of the per-segment aligned errors); drift_pct: the
    segments' final errors summed, in % of distance_m (their GT path lengths summed, m); gravity_err_deg: deg;
    frames: poses compared; segments: per segment, in time order."""

    ate_m: float
    drift_pct: float
    gravity_err_deg: float
    distance_m: float
    frames: int
    segments: tuple[SegmentMetrics, ...]

    def as_dict(self) -> dict:
        """The fields, with ``segments`` the segment count and ``per_segment`` the list of segment dicts."""
        out = {k: v for k, v in asdict(self).items() if k != "segments"}
        return {**out, "segments": len(self.segments), "per_segment": [asdict(s) for s in self.segments]}


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


def segment_bounds(stamps: np.ndarray, starts) -> list[slice]:
    """The frames of each segment of a trajectory with ``stamps`` [N] s, new segments beginning at the stamps
    ``starts`` (the first frame at or after each; the first segment begins at frame 0)."""
    stamps = np.asarray(stamps, dtype=np.float64)
    cuts = np.searchsorted(stamps, np.asarray(list(starts), dtype=np.float64) - 1e-9)
    edges = np.unique(np.concatenate([[0], cuts[(cuts > 0) & (cuts < len(stamps))], [len(stamps)]]))
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def gt_path_length(gt: GroundTruthTrack, t0: float, t1: float) -> float:
    """Metres ``gt`` flies between t0 and t1 s, over every sample of the track in between: a chained trajectory's
    stretches without poses (clips not placed or dropped) count with the distance actually flown, not as a straight
    line."""
    inside = gt.t[(gt.t > t0) & (gt.t < t1)]
    p = gt.at(np.concatenate([[t0], inside, [t1]])).T_WB[:, :3, 3]
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def _segment(stamps: np.ndarray, T_OB: np.ndarray, T_WB: np.ndarray,
             path_length: Callable[[float, float], float] | None) -> tuple[SegmentMetrics, np.ndarray]:
    err = np.linalg.norm(align_yaw_first(T_OB, T_WB) - T_WB[:, :3, 3], axis=1)
    distance = (path_length(float(stamps[0]), float(stamps[-1])) if path_length is not None
                else float(np.linalg.norm(np.diff(T_WB[:, :3, 3], axis=0), axis=1).sum()))
    return SegmentMetrics(t0=float(stamps[0]), t1=float(stamps[-1]), frames=len(stamps), distance_m=distance,
                          ate_m=float(np.sqrt((err**2).mean())),
                          drift_pct=100.0 * float(err[-1]) / distance if distance > 0 else float("nan")), err


def chained_metrics(T_OB: np.ndarray, T_WB: np.ndarray, *, stamps: np.ndarray, segment_starts=(),
                    path_length: Callable[[float, float], float] | None = None) -> ChainedMetrics:
    """T_OB, T_WB: [N,4,4] estimated (odom) and GT (world, z up) body poses at ``stamps`` [N] s, N >= 2;
    segment_starts: stamps at which a new segment begins (``Trajectory.resets``); path_length(t0, t1): metres the
    ground truth flew between two stamps (``functools.partial(gt_path_length, track)``), the drift's denominator;
    None: the GT path through the compared frames only, which shortens stretches without poses."""
    stamps = np.asarray(stamps, dtype=np.float64)
    if not (len(T_OB) == len(T_WB) == len(stamps)) or len(T_OB) < 2:
        raise DataError(f"chained metrics need >= 2 matching poses and stamps, got {len(T_OB)} estimated, "
                        f"{len(T_WB)} GT and {len(stamps)} stamps")
    parts = [_segment(stamps[s], T_OB[s], T_WB[s], path_length) for s in segment_bounds(stamps, segment_starts)]
    segments = tuple(seg for seg, _ in parts)
    err = np.concatenate([e for _, e in parts])
    distance = sum(seg.distance_m for seg in segments)
    end_error = sum(float(e[-1]) for _, e in parts)
    up_est = T_OB[:, 2, :3]  # odom z axis in the body frame: row 2 of R_OB
    up_gt = T_WB[:, 2, :3]
    grav = np.degrees(so3.angle_between(up_est, up_gt))
    return ChainedMetrics(ate_m=float(np.sqrt((err**2).mean())),
                          drift_pct=100.0 * end_error / distance if distance > 0 else float("nan"),
                          gravity_err_deg=float(np.mean(grav)), distance_m=distance, frames=len(T_OB),
                          segments=segments)
