"""``ImuNoiseModel``: what a metric fit assumes about the IMU (white noise, gyro scale error, bias priors and random
walks), and the covariances of IMU displacements and velocity changes it implies."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ImuNoiseModel:
    """What the fit assumes about the IMU, per axis.

    accel_noise_density: m/s^2/sqrt(Hz); gyro_noise_density: rad/s/sqrt(Hz). Defaults: EuRoC's ADIS16448 datasheet
    values (``imu0/sensor.yaml``) times 10 for the accelerometer and 5 for the gyro, as VIO systems inflate them for a
    real IMU (VINS-Mono uses 40x on EuRoC): with exact camera poses and its ground-truth state, the real EuRoC V1_02
    IMU misfits the positions of a 0.7 s clip by 3-19 mm RMS where the datasheet predicts under 1 mm.
    gyro_scale_error: relative error of the integrated rotation (scale factor, misalignment; 0.5 %: the real EuRoC IMU's
    attitude, integrated from bias-corrected gyro over 8.4 s windows of V1_02 and V2_03, errs by 0.16-0.25 % of the
    angle turned): gravity is tilted by this fraction of the angle turned within a clip, and the clips' attitudes walk
    apart by it between clips (``attitude_walk``). accel_bias_sigma: m/s^2, prior 1-sigma of the accelerometer bias
    (EuRoC's reach 0.1-0.2). gyro_bias_sigma: rad/s, floor of the gyro-bias prior's 1-sigma (a larger spread of its
    estimate is used when given). rel_floor: relative scale error the model does not see (the real IMU with exact poses:
    ~1 %). accel_bias_walk (m/s^2/sqrt(s)), gyro_bias_walk (rad/s/sqrt(s)): the biases' random walks (EuRoC's datasheet
    values): what a prior on the biases loses per second (``GaussianPrior.widened``). time_offset_sigma: s, prior
    1-sigma of the camera-IMU time offset left over after the configured one (software stamps, USB cameras: a few ms).
    """

    accel_noise_density: float = 2.0e-2
    gyro_noise_density: float = 8.5e-4
    gyro_scale_error: float = 0.005
    accel_bias_sigma: float = 0.2
    gyro_bias_sigma: float = 5.0e-4
    rel_floor: float = 0.01
    accel_bias_walk: float = 3.0e-3
    gyro_bias_walk: float = 1.9393e-05
    time_offset_sigma: float = 0.005

    def __post_init__(self) -> None:
        bad = [k for k, v in vars(self).items() if not (math.isfinite(v) and v >= 0.0)]
        bad += [k for k in ("accel_bias_sigma", "gyro_bias_sigma", "time_offset_sigma") if not getattr(self, k) > 0.0]
        if bad:
            raise ValueError(f"ImuNoiseModel: {', '.join(sorted(set(bad)))} must be finite and >= 0 (bias sigmas > 0)")

    def position_cov(self, dtau: np.ndarray, angle: np.ndarray, gravity_norm: float) -> np.ndarray:
        """[n,n] covariance (m^2, per axis) of the IMU displacements at dtau [n] s after the first stamp, where the body
        has turned ``angle`` [n] rad: the accelerometer's white noise integrated twice, plus the gyro scale error's
        tilt of gravity (G kappa angle_i dtau_i^2 / 6: a rotation error growing with the angle, integrated twice)."""
        ti, tj = dtau[:, None], dtau[None, :]
        m = np.minimum(ti, tj)
        cov = self.accel_noise_density**2 * (ti * tj * m - 0.5 * (ti + tj) * m**2 + m**3 / 3.0)
        f = gravity_norm * self.gyro_scale_error * angle * dtau**2 / 6.0
        return cov + np.outer(f, f)

    def attitude_walk(self, dt: np.ndarray, angle: np.ndarray) -> np.ndarray:
        """[k] rad: the 1-sigma (per axis) of the error the IMU's integrated attitude gains over intervals of dt [k] s
        in which the body turned ``angle`` [k] rad: the gyro's white noise and its ``gyro_scale_error`` of each radian
        turned."""
        return np.sqrt(self.gyro_noise_density**2 * dt + (self.gyro_scale_error * angle) ** 2)

    def velocity_sigma(self, dt: float, angle: float, gravity_norm: float) -> float:
        """1-sigma (m/s, per axis) of an IMU velocity change over dt s while turning ``angle`` rad."""
        return math.sqrt(self.accel_noise_density**2 * dt + (gravity_norm * self.gyro_noise_density)**2 * dt**3 / 3.0
                         + (0.5 * gravity_norm * self.gyro_scale_error * angle * dt)**2)


__all__ = ["ImuNoiseModel"]
