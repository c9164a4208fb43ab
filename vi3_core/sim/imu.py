"""IMU synthesis along an analytic trajectory, with EuRoC's noise model (``imu0/sensor.yaml``), an accelerometer
bias of EuRoC's size and, optionally, the airframe vibration a real multirotor's IMU records."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, sosfilt

from vi3_core import so3
from vi3_core.sim.trajectory import GRAVITY, Trajectory
from vi3_core.types import ImuSamples


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
class Vibration:
    """Airframe vibration (propellers) seen by the IMU: zero-mean noise above ``cutoff_hz`` (and below ``max_hz``,
    when set) with per-axis RMS ``accel_rms`` (m/s^2) and ``gyro_rms`` (rad/s) in the body frame. Defaults: EuRoC
    V1_02_medium's real IMU in flight, 15-95 Hz band (../shared/data/euroc_v102_imu_gt). Its displacement is
    micrometres, so it is in the IMU only, not in the ground-truth motion; EuRoC's ``sensor.yaml`` noise densities do
    not include it either."""

    accel_rms: tuple[float, float, float] = (0.85, 0.47, 0.62)
    gyro_rms: tuple[float, float, float] = (0.018, 0.036, 0.024)
    cutoff_hz: float = 15.0
    max_hz: float | None = None


#: The vibration of EuRoC's AscTec Firefly in flight, on by default in the realistic motion presets.
EUROC_VIBRATION = Vibration()
#: A hand's tremor and steps as a handheld RealSense's IMU shows them (github Zoltan3057/DM-VIO-dataset): 4-16 Hz.
HANDHELD_TREMOR = Vibration(accel_rms=(0.22, 0.12, 0.17), gyro_rms=(0.034, 0.029, 0.047), cutoff_hz=4.0, max_hz=16.0)
#: That RealSense's IMU: its white-noise floor (60-95 Hz of the recording), the random walks of its Kalibr file.
REALSENSE_NOISE = ImuNoise(gyro_noise_density=1.6e-4, gyro_random_walk=2.6e-6, accel_noise_density=7.5e-4,
                           accel_random_walk=3.0e-3)

def default_vibration(motion: str, noisy: bool) -> Vibration | None:
    """``HANDHELD_TREMOR`` for a noisy IMU carried by hand, ``EUROC_VIBRATION`` on the other realistic motion
    presets; None for ``agile`` (the earlier generator) or a noise-free IMU."""
    if not noisy or motion == "agile":
        return None
    return HANDHELD_TREMOR if motion == "handheld" else EUROC_VIBRATION


#: Accelerometer bias magnitude of a sequence, m/s^2 (EuRoC's ground truth: 0.05-0.2; V1_02: 0.14).
ACCEL_BIAS_RANGE = (0.05, 0.2)


def draw_accel_bias(rng: np.random.Generator) -> np.ndarray:
    """An initial accelerometer bias [3] m/s^2: uniform magnitude in ``ACCEL_BIAS_RANGE``, uniform direction."""
    direction = rng.standard_normal(3)
    return direction / np.linalg.norm(direction) * rng.uniform(*ACCEL_BIAS_RANGE)


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


class ImuSimulator:
    """Gyro and accelerometer readings along ``traj`` on a uniform grid of period ``dt``, produced over consecutive
    chunks of stamps: biases walk on, the noise streams continue and the vibration filter keeps its state, so any
    split of the grid gives the same samples as one call over all of it (up to rounding).

    gyro = omega_B + bg + n_g (+ vibration); accel = R_WB^T (a_W - g_W) + ba + n_a (+ vibration), with
    g_W = [0, 0, -9.81]. White noise sigma = density / sqrt(dt); biases follow random walks of sigma = rw * sqrt(dt)
    per step, starting at bg0/ba0. ``with_orientation`` adds the exact attitude quaternion as a flight controller
    would. Each noise source draws from its own stream of ``seed``.
    """

    def __init__(self, traj: Trajectory, *, dt: float, noise: ImuNoise = EUROC_NOISE, bg0: np.ndarray | None = None,
                 ba0: np.ndarray | None = None, seed: int = 0, vibration: Vibration | None = None,
                 with_orientation: bool = False) -> None:
        self.traj, self.dt, self.noise, self.with_orientation = traj, float(dt), noise, with_orientation
        self._bg = np.zeros(3) if bg0 is None else np.asarray(bg0, dtype=np.float64)
        self._ba = np.zeros(3) if ba0 is None else np.asarray(ba0, dtype=np.float64)
        self._rng = [np.random.default_rng([seed, k]) for k in range(5)]
        self._started = False
        self._vibration = vibration
        if vibration is not None:
            nyquist = 0.5 / self.dt
            band = (vibration.cutoff_hz / nyquist if vibration.max_hz is None else
                    [vibration.cutoff_hz / nyquist, min(vibration.max_hz / nyquist, 0.99)])
            self._sos = butter(4, band, btype="highpass" if vibration.max_hz is None else "bandpass", output="sos")
            impulse = np.zeros(4096)
            impulse[0] = 1.0
            gain = np.sqrt(np.sum(sosfilt(self._sos, impulse) ** 2))  # RMS of filtered unit white noise
            self._vib_scale = np.concatenate([vibration.gyro_rms, vibration.accel_rms]) / gain
            self._zi = np.zeros((len(self._sos), 2, 6))  # filter state [sections, 2, channels], at rest

    def __call__(self, t: np.ndarray) -> SimulatedImu:
        """The samples at the next stamps t [M] (continuing the previous call's grid)."""
        t = np.asarray(t, dtype=np.float64)
        M = len(t)
        R = self.traj.rotation(t)
        a_W = self.traj.acceleration_W(t) - np.array([0.0, 0.0, -GRAVITY])
        f_B = np.einsum("nji,nj->ni", R, a_W)
        w_B = self.traj.angular_velocity_B(t)
        n = self.noise

        def walk(b0, rw, rng):
            steps = rng.standard_normal((M, 3)) * rw * np.sqrt(self.dt)
            if not self._started and M:
                steps[0] = 0.0  # the first sample of the grid has bias b0 exactly
            return b0 + np.cumsum(steps, axis=0)

        bg, ba = walk(self._bg, n.gyro_random_walk, self._rng[0]), walk(self._ba, n.accel_random_walk, self._rng[1])
        gyro = w_B + bg + self._rng[2].standard_normal((M, 3)) * n.gyro_noise_density / np.sqrt(self.dt)
        accel = f_B + ba + self._rng[3].standard_normal((M, 3)) * n.accel_noise_density / np.sqrt(self.dt)
        if self._vibration is not None:
            vib, self._zi = sosfilt(self._sos, self._rng[4].standard_normal((M, 6)), axis=0, zi=self._zi)
            vib *= self._vib_scale
            gyro, accel = gyro + vib[:, :3], accel + vib[:, 3:]
        if M:
            self._bg, self._ba, self._started = bg[-1], ba[-1], True
        ori = so3.R_to_quat(R) if self.with_orientation else None
        return SimulatedImu(ImuSamples(t, gyro, accel, ori), bg, ba)


def simulate_imu(traj: Trajectory, t: np.ndarray, *, noise: ImuNoise = EUROC_NOISE,
                 bg0: np.ndarray | None = None, ba0: np.ndarray | None = None, seed: int = 0,
                 vibration: Vibration | None = None, with_orientation: bool = False) -> SimulatedImu:
    """``ImuSimulator`` over the stamps t [M] (uniform rate) in one call."""
    t = np.asarray(t, dtype=np.float64)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.005
    return ImuSimulator(traj, dt=dt, noise=noise, bg0=bg0, ba0=ba0, seed=seed, vibration=vibration,
                        with_orientation=with_orientation)(t)
