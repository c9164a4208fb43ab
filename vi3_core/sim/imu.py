"""IMU synthesis along an analytic trajectory, with EuRoC's noise model (``imu0/sensor.yaml``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vi3_core.sim.trajectory import Trajectory
from vi3_core.types import ImuSamples

GRAVITY = 9.81


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time noise densities and bias random walks (EuRoC ADIS16448 values by default)."""

    gyro_noise_density: float = 1.6968e-04  # rad/s/sqrt(Hz)
    gyro_random_walk: float = 1.9393e-05  # rad/s^2/sqrt(Hz)
    accel_noise_density: float = 2.0e-3  # m/s^2/sqrt(Hz)
    accel_random_walk: float = 3.0e-3  # m/s^3/sqrt(Hz)

    @staticmethod
    def zero() -> ImuNoise:
        return ImuNoise(0.0, 0.0, 0.0, 0.0)


#: EuRoC's ADIS16448 noise, the default of every simulation.
EUROC_NOISE = ImuNoise()


@dataclass(frozen=True)
class SimulatedImu:
    """Measurements plus the exact biases at every sample: samples.t [M], bg [M,3], ba [M,3]."""

    samples: ImuSamples
    bg: np.ndarray
    ba: np.ndarray


def imu_stamps(t0: float, t1: float, rate: float = 200.0) -> np.ndarray:
    """Stamps k / rate covering [t0, t1] (inclusive of the grid points), float64 s."""
    k0, k1 = int(np.floor(t0 * rate + 1e-9)), int(np.ceil(t1 * rate - 1e-9))
    return np.arange(k0, k1 + 1) / rate


def simulate_imu(traj: Trajectory, t: np.ndarray, *, noise: ImuNoise = EUROC_NOISE,
                 bg0: np.ndarray | None = None, ba0: np.ndarray | None = None,
                 seed: int = 0, with_orientation: bool = False) -> SimulatedImu:
    """Gyro and accelerometer readings at stamps t [M] (uniform rate).

    gyro = omega_B + bg + n_g;  accel = R_WB^T (a_W - g_W) + ba + n_a, with g_W = [0, 0, -9.81].
    White noise sigma = density * sqrt(rate); biases follow random walks of sigma = rw * sqrt(dt) per step,
    starting at bg0/ba0. ``with_orientation`` adds the exact attitude quaternion as a flight controller would.
    """
    t = np.asarray(t, dtype=np.float64)
    rng = np.random.default_rng(seed)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.005
    M = len(t)
    R = traj.rotation(t)
    a_W = traj.acceleration_W(t) - np.array([0.0, 0.0, -GRAVITY])
    f_B = np.einsum("nji,nj->ni", R, a_W)
    w_B = traj.angular_velocity_B(t)

    def walk(b0, rw):
        b0 = np.zeros(3) if b0 is None else np.asarray(b0, dtype=np.float64)
        steps = rng.standard_normal((M, 3)) * rw * np.sqrt(dt)
        steps[0] = 0.0
        return b0 + np.cumsum(steps, axis=0)

    bg, ba = walk(bg0, noise.gyro_random_walk), walk(ba0, noise.accel_random_walk)
    gyro = w_B + bg + rng.standard_normal((M, 3)) * noise.gyro_noise_density / np.sqrt(dt)
    accel = f_B + ba + rng.standard_normal((M, 3)) * noise.accel_noise_density / np.sqrt(dt)
    ori = None
    if with_orientation:
        from vi3_core import so3

        ori = so3.R_to_quat(R)
    return SimulatedImu(ImuSamples(t, gyro, accel, ori), bg, ba)
