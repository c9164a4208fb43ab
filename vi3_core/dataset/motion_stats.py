"""How a recording moves: percentiles of speed, body acceleration and angular rate of an ASL folder with IMU and
ground truth (a real EuRoC ``mav0`` or a generated one), the numbers the motion presets are matched with.

    python -m vi3_core.dataset.motion_stats MAV0 [MAV0 ...] [--start S] [--end S] [--json]

speed: |v_WB| of the ground-truth rows. Body acceleration: |R_WB (a_IMU - b_a) + g_W|, the kinematic acceleration
(gravity removed) from the IMU with the GT attitude (slerp) and accelerometer bias; angular rate: |w_IMU - b_g|.
Both are low-passed at ``CUTOFF_HZ`` (zero-phase Butterworth) so that airframe vibration and sensor noise do not
count as motion, and taken over the IMU samples the GT covers. ``--start``/``--end``: a window in seconds from the
first GT row (e.g. to leave out take-off and landing).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from scipy.signal import butter, sosfiltfilt
from scipy.spatial.transform import Rotation, Slerp

from vi3_core.dataset import asl
from vi3_core.dataset.sequence import G_W
from vi3_core.errors import DataError

CUTOFF_HZ = 5.0
PERCENTILES = (10, 50, 90)


def motion_stats(path, *, start_s: float = 0.0, end_s: float = np.inf) -> dict[str, object]:
    """{"speed_mps", "accel_mps2", "angular_rate_radps": [p10, p50, p90], "gt_seconds", "imu_seconds"} of the
    ASL folder ``path`` over [start_s, end_s] s from its first GT row. Raises DataError without GT or IMU in it."""
    mav0 = asl.find_mav0(path)
    imu_ns, imu = asl.read_imu(mav0)
    gt = asl.read_groundtruth(mav0)
    if gt is None:
        raise DataError(f"{mav0}: no state_groundtruth_estimate0/; motion statistics need the ground truth")
    t0 = gt.t_ns[0]
    rows = (gt.t_ns >= t0 + start_s * 1e9) & (gt.t_ns <= t0 + min(end_s, 1e12) * 1e9)
    gt_t = gt.t[rows]
    keep = (imu.t >= gt_t[0]) & (imu.t <= gt_t[-1]) if len(gt_t) else np.zeros(len(imu), bool)
    fs = 1.0 / float(np.median(np.diff(imu.t))) if len(imu) > 1 else 0.0
    if keep.sum() < 32 or fs <= 2 * CUTOFF_HZ:
        raise DataError(f"{mav0}: too few IMU samples ({int(keep.sum())} at {fs:.0f} Hz) within the ground truth "
                        f"window; need >= 32 above {2 * CUTOFF_HZ:g} Hz")
    t, gyro, accel = imu.t[keep], imu.gyro[keep], imu.accel[keep]
    R_WB = Slerp(gt.t, Rotation.from_matrix(gt.T_WB[:, :3, :3]))(t).as_matrix()

    def bias(b):  # an unknown bias (None, or NaN in the file) counts as 0: the motion, not the sensor, is described
        return np.zeros((len(t), 3)) if b is None else \
            np.nan_to_num(np.stack([np.interp(t, gt.t, b[:, k]) for k in range(3)], 1), nan=0.0)

    sos = butter(4, CUTOFF_HZ, fs=fs, output="sos")
    a_W = sosfiltfilt(sos, np.einsum("nij,nj->ni", R_WB, accel - bias(gt.ba)) + G_W, axis=0)
    w_B = sosfiltfilt(sos, gyro - bias(gt.bg), axis=0)

    def pct(x: np.ndarray) -> list[float]:
        return [round(float(v), 3) for v in np.percentile(np.linalg.norm(x, axis=1), PERCENTILES)]

    return {"speed_mps": pct(gt.v_WB[rows]), "accel_mps2": pct(a_W), "angular_rate_radps": pct(w_B),
            "gt_seconds": round(float(gt_t[-1] - gt_t[0]), 2), "imu_seconds": round(float(t[-1] - t[0]), 2)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m vi3_core.dataset.motion_stats", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="+", help="ASL folders (mav0 or its parent) with IMU and ground truth")
    p.add_argument("--start", type=float, default=0.0, help="window start, s after the first GT row (default 0)")
    p.add_argument("--end", type=float, default=np.inf, help="window end, s after the first GT row (default: all)")
    p.add_argument("--json", action="store_true", help="one JSON object per path")
    args = p.parse_args(argv)
    for path in args.paths:
        try:
            stats = motion_stats(path, start_s=args.start, end_s=args.end)
        except DataError as err:
            print(f"motion_stats: error: {err}", file=sys.stderr)
            return 2
        if args.json:
            print(json.dumps({"path": path, **stats}))
        else:
            print(f"{path}: p10/p50/p90 speed {stats['speed_mps']} m/s, body acceleration {stats['accel_mps2']} "
                  f"m/s^2, angular rate {stats['angular_rate_radps']} rad/s (GT {stats['gt_seconds']} s, "
                  f"IMU {stats['imu_seconds']} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
