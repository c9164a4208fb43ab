"""Scale-free gravity seeds g^(0) for the fixed point, each in the first body frame B1, m/s^2.

- ``imu``: Eq. gimu, the clip's mean specific force. Assumes small accelerations over the clip: a drone
  accelerating steadily for 0.75 s tilts it by atan(a / 9.81) (about 6 deg at 1 m/s^2).
- ``orientation``: the attitude a flight controller reports in ``sensor_msgs/Imu.orientation`` (gravity-
  aligned world, z up). As good as the autopilot's estimator, typically about 1 deg.
- ``long_window``: beyond the paper, the mean specific force over seconds of IMU history around the clip,
  rotated into B1 with the bias-corrected gyro. Velocity is bounded, so the mean acceleration over T seconds is
  at most |dv| / T: 8 s or more are needed (2 s of EuRoC-like flight leave several degrees, worse than the
  clip's own inertial estimate). Gyro-bias error tilts it by about |dbg| T / 4 for a one-sided window and
  cancels to first order for a window centred on the clip.
- ``geocalib``: single-image gravity from GeoCalib (``pip install geocalib``; its weights must be in the local
  torch hub cache), when installed. Fails on texture-poor, out-of-distribution images (hence Eq. guard).
"""

from __future__ import annotations

import importlib.util

import numpy as np

from vi3_core import so3
from vi3_core.preintegration import Preintegration, preintegrate
from vi3_core.types import ImuSamples

_UP = np.array([0.0, 0.0, 1.0])


def imu_seed(pre: Preintegration, gravity_norm: float) -> np.ndarray:
    """Eq. gimu: -|g| * normalised sum of R_k a_k over the clip (pre integrated with ba = 0)."""
    f = pre.beta[-1]
    return -gravity_norm * f / np.linalg.norm(f)


def orientation_seed(imu: ImuSamples, t1: float, gravity_norm: float) -> np.ndarray | None:
    """Gravity in B1 from the reported attitude at the sample nearest t1, or None if none is reported."""
    if imu.orientation is None or len(imu) == 0:
        return None
    k = int(np.argmin(np.abs(imu.t - t1)))
    q = imu.orientation[k]
    if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 0.5:
        return None
    return -gravity_norm * so3.quat_to_R(q).T @ _UP


def long_window_seed(history: ImuSamples | None, t1: float, bg: np.ndarray, gravity_norm: float, *,
                     min_seconds: float = 8.0) -> np.ndarray | None:
    """Mean specific force over ``history`` expressed in B(t1), or None if the window is shorter than
    ``min_seconds``, does not contain t1, or has non-finite samples."""
    if history is None or len(history) < 3:
        return None
    t = history.t
    if t[-1] - t[0] < min_seconds or not (t[0] < t1 < t[-1]):
        return None
    if not (np.isfinite(history.gyro).all() and np.isfinite(history.accel).all() and np.all(np.diff(t) > 0)):
        return None
    pre = preintegrate(history, np.array([t[0], t1, t[-1]]), bg)
    mean_f = pre.R[1].T @ pre.beta[2]  # int R a dt over the window, from B(t0) axes into B(t1) axes
    return -gravity_norm * mean_f / np.linalg.norm(mean_f)


def geocalib_available() -> bool:
    return importlib.util.find_spec("geocalib") is not None


def geocalib_seed(image: np.ndarray, T_BC: np.ndarray, gravity_norm: float, *, device: str = "cpu") -> np.ndarray:
    """Gravity in B1 from GeoCalib on the first image (camera frame), rotated by R_BC.

    Raises ImportError when geocalib is not installed (callers check ``geocalib_available`` first).
    """
    import torch
    from geocalib import GeoCalib

    rgb = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=-1)
    tensor = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float().div(255.0).to(device)
    result = GeoCalib().to(device).calibrate(tensor)
    down_c = result["gravity"].vec3d.detach().cpu().numpy().reshape(3)  # unit "down" in the camera frame
    return gravity_norm * T_BC[:3, :3] @ (down_c / np.linalg.norm(down_c))
