"""Oracle initialisation from ground truth (GT gravity, v1 and gyro bias), as the paper's GT-vs-GT-free
tables use it. Only for evaluation: it needs ``clip.gt``."""

from __future__ import annotations

import numpy as np

from vi3_core.errors import DataError
from vi3_core.init import validate
from vi3_core.init.options import InitOptions
from vi3_core.init.position_fit import fit_positions
from vi3_core.preintegration import preintegrate
from vi3_core.types import Clip, Geometry, InitResult, InitStatus


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
    R1 = clip.gt.T_WB[0, :3, :3]
    g = R1.T @ clip.gt.g_W
    v1 = R1.T @ clip.gt.v_WB[0]
    bg = np.asarray(clip.gt.bg, dtype=np.float64).reshape(-1, 3)[0]
    pre = preintegrate(clip.imu, clip.stamps, bg)
    target = pre.propagate(g, v1, clip.T_BC)
    s = fit_positions(geometry.T_wc, pre, clip.T_BC, g, v1=v1).scale
    if not np.isfinite(s):
        return InitResult(InitStatus.UNOBSERVABLE, "backbone predicts no translation", bg=bg, g=g,
                          gravity_source="ground_truth")
    return InitResult(InitStatus.OK, "oracle (ground truth)", bg=bg, g=g, scale=s, v1=v1,
                      gravity_source="ground_truth", target=target)
