"""Oracle initialisation from ground truth (GT gravity, v1 and gyro bias), as the paper's GT-vs-GT-free
tables use it. Only for evaluation: it needs ``clip.gt``. ``gt_init_state`` is the GT state in B1 that the
evaluation's init metrics compare against too."""

from __future__ import annotations

import numpy as np

from vi3_core.errors import DataError
from vi3_core.fit.position import fit_positions
from vi3_core.init import validate
from vi3_core.init.initializer import initialise_clip
from vi3_core.init.options import InitOptions
from vi3_core.preintegration import preintegrate
from vi3_core.types import Clip, Geometry, GroundTruth, InitResult, InitStatus


def gt_init_state(gt: GroundTruth) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """GT gravity g [3] and velocity v1 [3] in the first body frame B1 (R_WB1^T g_W, R_WB1^T v_WB1), and the GT
    gyro bias bg [3] (rad/s) or None where the GT has none (None or NaN in the track, e.g. Vicon-only bags)."""
    R_WB1 = np.asarray(gt.T_WB, dtype=np.float64)[0, :3, :3]
    g = R_WB1.T @ np.asarray(gt.g_W, dtype=np.float64)
    v1 = R_WB1.T @ np.asarray(gt.v_WB, dtype=np.float64)[0] if gt.v_WB is not None else np.full(3, np.nan)
    bg = None if gt.bg is None else np.asarray(gt.bg, dtype=np.float64).reshape(-1, 3)[0]
    return g, v1, bg if bg is not None and np.isfinite(bg).all() else None


def oracle_init(clip: Clip, geometry: Geometry, *, options: InitOptions | None = None) -> InitResult:
    """InitResult from the clip's ground truth; the scale is the least-squares fit of the backbone's
    positions to the IMU target's (``fit_positions`` with g and v1 known). Raises DataError without ground truth;
    bad IMU data still yields ``rejected``."""
    if clip.gt is None:
        raise DataError("oracle initialisation (--init gt) needs ground truth in the clip")
    options = options or InitOptions()
    reason = validate.check_stamps(clip.stamps) or validate.check_imu(clip.imu, clip.stamps, options)
    if reason:
        return InitResult(InitStatus.REJECTED, reason)
    g, v1, bg = gt_init_state(clip.gt)
    if bg is None:  # GT without biases (e.g. Vicon-only bags): the clip's own GT-free gyro-bias estimate
        bg = initialise_clip(clip, geometry, options=options).bg
    pre = preintegrate(clip.imu, clip.stamps, bg)
    target = pre.propagate(g, v1, clip.T_BC)
    s = fit_positions(geometry.T_wc, pre, clip.T_BC, g, v1).scale
    if not np.isfinite(s):
        return InitResult(InitStatus.UNOBSERVABLE, "backbone predicts no translation", bg=bg, g=g,
                          gravity_source="ground_truth")
    return InitResult(InitStatus.OK, "oracle (ground truth)", bg=bg, g=g, scale=s, v1=v1,
                      gravity_source="ground_truth", target=target)
