"""3DFM-like up-to-scale poses from ground truth, for initialisation tests and benchmarks.

The "visual" poses are the true camera poses (through T_BC), re-anchored at the first camera, with their
translation multiplied by an unknown scale and perturbed by independent per-frame noise: a rotation of a fixed
angle about a random axis, and a translation of a fixed fraction of the mean inter-frame baseline.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vi3_core import so3
from vi3_core.sim.euroc import CAMERA_RATE_HZ, IMU_RATE_HZ, T_BS_CAM0
from vi3_core.sim.imu import EUROC_NOISE, ImuNoise, default_vibration, draw_accel_bias, imu_stamps, simulate_imu
from vi3_core.sim.trajectory import make_trajectory
from vi3_core.types import Geometry, ImuSamples


@dataclass(frozen=True)
class InitCase:
    """A simulated clip for the initialiser: inputs and the truth they must recover (truth in B1)."""

    geometry: Geometry
    imu: ImuSamples
    stamps: np.ndarray
    T_BC: np.ndarray
    scale: float  # metric = scale * model translation
    bg: np.ndarray
    g: np.ndarray
    v1: np.ndarray
    T_B1Bi: np.ndarray


def noisy_poses(T_wc: np.ndarray, *, scale: float, rot_noise_deg: float, trans_noise_frac: float,
                rng: np.random.Generator, min_noise_m: float = 1e-3) -> np.ndarray:
    """T_wc [n,4,4] metric camera poses in C1 -> up-to-scale noisy poses (model units = metres / scale).

    Translation noise is ``trans_noise_frac`` of the mean metric inter-frame baseline (at least
    ``min_noise_m``), isotropic, applied before dividing by ``scale``; frame 0 stays the identity.
    """
    n = len(T_wc)
    axis = rng.standard_normal((n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    dR = so3.exp(axis * np.radians(rot_noise_deg))
    baseline = np.linalg.norm(np.diff(T_wc[:, :3, 3], axis=0), axis=1).mean()
    sigma = max(trans_noise_frac * baseline, min_noise_m if trans_noise_frac > 0 else 0.0) / np.sqrt(3)
    out = T_wc.copy()
    out[1:, :3, :3] = T_wc[1:, :3, :3] @ dR[1:]
    out[1:, :3, 3] = T_wc[1:, :3, 3] + rng.standard_normal((n - 1, 3)) * sigma
    out[:, :3, 3] /= scale
    return out


def make_init_case(seed: int, *, kind: str = "drone", motion: str = "medium", n: int = 8, stride: int = 2,
                   scale: float | None = None, rot_noise_deg: float = 0.0, trans_noise_frac: float = 0.0,
                   imu_noise: ImuNoise = EUROC_NOISE, accel_bias: bool = True, bg_sigma: float = 0.02,
                   depth_m: float = 3.0, with_orientation: bool = False) -> InitCase:
    """A clip of n frames at ``stride`` x 20 Hz with 200 Hz IMU, EuRoC extrinsics and noise.

    motion: the drone's motion preset (``vi3_core.sim.trajectory.MOTIONS``); scale: drawn log-uniformly in
    [0.1, 10] when None; gyro bias drawn N(0, bg_sigma) per axis; with ``accel_bias`` and a noisy IMU, an
    accelerometer bias of EuRoC's size (``draw_accel_bias``), else none (a noise-free IMU stays exact); the
    geometry's depth is a constant ``depth_m`` metres (in model units) so that parallax checks see a real scene depth.
    """
    rng = np.random.default_rng(seed)
    traj = make_trajectory(kind, seed=seed, motion=motion)
    if scale is None:
        scale = float(np.exp(rng.uniform(np.log(0.1), np.log(10.0))))
    t0 = rng.uniform(5.0, 50.0)
    stamps = t0 + np.arange(n) * stride / CAMERA_RATE_HZ + rng.uniform(0.0, 1.0 / IMU_RATE_HZ)
    bg = rng.normal(0.0, bg_sigma, 3)
    imu = simulate_imu(traj, imu_stamps(stamps[0] - 0.02, stamps[-1] + 0.02), noise=imu_noise, bg0=bg,
                       ba0=draw_accel_bias(rng) if accel_bias and imu_noise.accel_noise_density > 0 else None,
                       seed=seed + 1, with_orientation=with_orientation,
                       vibration=default_vibration(motion, imu_noise != ImuNoise.zero() and kind != "stationary"))
    T_WB = traj.T_WB(stamps)
    T_B1Bi = so3.inv_T(T_WB[0]) @ T_WB
    T_BC = T_BS_CAM0
    T_wc = so3.inv_T(T_BC) @ T_B1Bi @ T_BC
    poses = noisy_poses(T_wc, scale=scale, rot_noise_deg=rot_noise_deg, trans_noise_frac=trans_noise_frac, rng=rng)
    geometry = Geometry(T_wc=poses, K=np.tile(np.eye(3), (n, 1, 1)), depth=np.full((n, 4, 4), depth_m / scale),
                        conf=np.ones((n, 4, 4)), metric=False)
    R1 = T_WB[0, :3, :3]
    k1 = int(np.argmin(np.abs(imu.samples.t - stamps[0])))
    return InitCase(geometry=geometry, imu=imu.samples, stamps=stamps, T_BC=T_BC, scale=scale,
                    bg=imu.bg[k1], g=R1.T @ np.array([0.0, 0.0, -9.81]),
                    v1=R1.T @ traj.velocity_W(stamps[:1])[0], T_B1Bi=T_B1Bi)
