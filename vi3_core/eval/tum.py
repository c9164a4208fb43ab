"""TUM trajectory export (``timestamp tx ty tz qx qy qz qw`` per line) for ``evo``.

Every file of a clip is in that clip's first camera frame C1 (metres, seconds), so
``evo_ape tum clip000_gt.txt clip000_vi3.txt`` without ``--align``/``--correct_scale`` reproduces the paper's
unaligned Trans metric, and ``evo_traj tum clip000_*.txt --ref clip000_gt.txt -p`` plots them together.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from vi3_core import so3
from vi3_core.dataset.sequence import GroundTruthTrack
from vi3_core.errors import DataError
from vi3_core.eval.clip_eval import ClipEval

TUM_HEADER = "timestamp tx ty tz qx qy qz qw"


def write_tum(path: str | Path, stamps: np.ndarray, T: np.ndarray) -> Path:
    """Write poses ``T`` [n,4,4] (camera-to-world) at ``stamps`` [n] (s) to ``path`` in TUM format."""
    stamps, T = np.asarray(stamps, dtype=np.float64), np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) != len(stamps):
        raise DataError(f"write_tum({path}): need [n] stamps and [n,4,4] poses, got {stamps.shape} and {T.shape}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = np.column_stack([stamps, T[:, :3, 3], so3.R_to_quat(T[:, :3, :3])])
    np.savetxt(path, rows, fmt="%.9f", header=TUM_HEADER)
    return path


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file -> stamps [n] and poses [n,4,4]; DataError naming the file when its text is not one (a value
    that is no number, a quaternion that is no rotation)."""
    try:
        rows = np.atleast_2d(np.loadtxt(path, comments="#"))
        R = so3.quat_to_R(rows[:, 4:8]) if rows.shape[1] == 8 else None
    except ValueError as err:
        raise DataError(f"{path}: not a TUM trajectory ({err})") from None
    if R is None:
        raise DataError(f"{path}: TUM lines need 8 columns (t tx ty tz qx qy qz qw), found {rows.shape[1]}")
    return rows[:, 0], so3.make_T(R, rows[:, 1:4])


def reference_track(path: str | Path) -> GroundTruthTrack:
    """The ground truth of a TUM file of IMU body poses in a gravity-aligned, z-up world (``vi3 eval --reference``):
    velocities from the positions, biases unknown. DataError naming the file when it is not one (too few poses,
    stamps not increasing, a rotation that is not one)."""
    try:
        stamps, T = read_tum(path)
    except OSError as err:
        raise DataError(f"{path}: not a TUM trajectory ({err})") from None
    if len(stamps) < 2 or np.any(np.diff(stamps) <= 0) or not np.isfinite(T).all():
        raise DataError(f"{path}: a reference needs >= 2 poses with increasing stamps and finite values")
    return GroundTruthTrack(stamps, T, t_ns=np.round(stamps * 1e9).astype(np.int64))


def export_tum(out_dir: str | Path, evals: Sequence[ClipEval]) -> list[Path]:
    """Write ``clipKKK_<name>.txt`` for every trajectory of every clip (``ClipEval.trajectories``: gt, base, imu,
    init, vi3 where available). Returns the paths written."""
    out_dir = Path(out_dir)
    return [write_tum(out_dir / f"clip{k:03d}_{name}.txt", e.stamps, T)
            for k, e in enumerate(evals) for name, T in e.trajectories().items()]


def export_chained(out_dir: str | Path, run) -> list[Path]:
    """Write the chained odom trajectory (``runner.OnlineRun``) as ``odom_vi3.txt`` (body poses in odom) and
    ``odom_gt.txt`` (GT body poses at the same stamps); compare with ``evo_ape tum odom_gt.txt odom_vi3.txt -a``
    (evo's alignment is 6-DoF; ``vi3 eval`` aligns only yaw and position)."""
    out_dir = Path(out_dir)
    return [write_tum(out_dir / "odom_vi3.txt", run.stamps, run.T_OB),
            write_tum(out_dir / "odom_gt.txt", run.stamps, run.T_WB)]
