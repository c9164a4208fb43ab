"""EuRoC MAV cam0 and IMU calibration (``mav0/cam0/sensor.yaml``), the defaults of every simulated sequence."""

from __future__ import annotations

import numpy as np

#: cam0 pose in the body (IMU) frame, EuRoC ``T_BS``.
T_BS_CAM0 = np.array([
    [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
    [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
    [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
    [0.0, 0.0, 0.0, 1.0],
])
#: fu, fv, cu, cv of cam0 (pinhole, distorted image).
INTRINSICS_CAM0 = (458.654, 457.296, 367.215, 248.375)
#: radial-tangential k1, k2, p1, p2 of cam0.
DISTORTION_CAM0 = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
RESOLUTION_CAM0 = (752, 480)  # width, height
CAMERA_RATE_HZ = 20.0
IMU_RATE_HZ = 200.0


def K_cam0() -> np.ndarray:
    fu, fv, cu, cv = INTRINSICS_CAM0
    return np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
