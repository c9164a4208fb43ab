"""3DFM-like up-to-scale poses from ground truth, for initialisation tests, benchmarks and the evaluation's ``gt``
pose-noise instrument.

The "visual" poses are the true camera poses (through T_BC) perturbed per frame (``PoseNoise``), re-anchored at the
first camera as a 3DFM re-anchors every clip (so the first frame's error moves all the others), with their
translation divided by an unknown scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vi3_core import so3
from vi3_core.sim.euroc import CAMERA_RATE_HZ, IMU_RATE_HZ, T_BS_CAM0
from vi3_core.sim.imu import EUROC_NOISE, ImuNoise, default_vibration, draw_accel_bias, imu_stamps, simulate_imu
from vi3_core.sim.trajectory import make_trajectory
from vi3_core.types import CLIP_LENGTH, CLIP_STRIDE, Geometry, ImuSamples


def parse_floats(text: str, counts: tuple[int, int], what: str, form: str, example: str, *,
                 minimum: float = -math.inf) -> list[float]:
    """The comma-separated numbers of a command-line value, between counts[0] and counts[1] of them, finite and >=
    ``minimum``; ValueError "<what> '<text>': expected <form> (e.g. <example>)" otherwise."""
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        values = []
    if not (counts[0] <= len(values) <= counts[1] and all(math.isfinite(v) and v >= minimum for v in values)):
        raise ValueError(f"{what} {text!r}: expected {form} (e.g. {example})")
    return values


@dataclass(frozen=True)
class PoseNoise:
    """Errors of a 3DFM's camera poses, in metric units before the scale is applied.

    pos_m: m, i.i.d. per frame and axis; rot_deg: deg, per frame, about a random axis; drift_m: m, a random walk whose
    per-axis 1-sigma reaches drift_m at the last frame (temporally correlated errors, which a clip's own residuals
    under-report)."""

    pos_m: float = 0.0
    rot_deg: float = 0.0
    drift_m: float = 0.0

    def __post_init__(self) -> None:
        if not all(np.isfinite(v) and v >= 0 for v in (self.pos_m, self.rot_deg, self.drift_m)):
            raise ValueError(f"PoseNoise: every value must be finite and >= 0, got {self}")

    @staticmethod
    def parse(text: str) -> PoseNoise:
        """"POS_M,ROT_DEG[,DRIFT_M]" (the evaluation's ``--gt-noise``) -> PoseNoise; ValueError naming the text."""
        return PoseNoise(*parse_floats(text, (2, 3), "pose noise", "POS_M,ROT_DEG[,DRIFT_M], finite and >= 0",
                                       "0.003,0.1", minimum=0.0))


@dataclass(frozen=True)
class DepthNoise:
    """Errors of a 3DFM's depth maps, relative (multiplicative, as log-depth errors): rel, i.i.d. per pixel; smooth, a
    low-frequency field per frame (``smooth_field``: a few cycles across the image, unit variance, times smooth) that
    no average over neighbouring pixels removes."""

    rel: float = 0.0
    smooth: float = 0.0

    def __post_init__(self) -> None:
        if not all(np.isfinite(v) and v >= 0 for v in (self.rel, self.smooth)):
            raise ValueError(f"DepthNoise: every value must be finite and >= 0, got {self}")

    @staticmethod
    def parse(text: str) -> DepthNoise:
        """"REL[,SMOOTH]" (the evaluation's ``--gt-depth-noise``) -> DepthNoise; ValueError naming the text."""
        return DepthNoise(*parse_floats(text, (1, 2), "depth noise", "REL[,SMOOTH], finite and >= 0", "0.05,0.02",
                                        minimum=0.0))

    def apply(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """``depth`` [n,h,w] times exp(rel N(0, 1) per pixel + smooth ``smooth_field`` per frame)."""
        n, h, w = depth.shape
        if self.rel == 0 and self.smooth == 0:
            return depth
        log_err = self.rel * rng.standard_normal(depth.shape) if self.rel > 0 else np.zeros(depth.shape)
        if self.smooth > 0:
            log_err += self.smooth * np.stack([smooth_field(h, w, rng) for _ in range(n)])
        return (depth * np.exp(log_err)).astype(depth.dtype)


def smooth_field(h: int, w: int, rng: np.random.Generator, *, modes: int = 8) -> np.ndarray:
    """[h,w] unit-variance random field of ``modes`` plane waves of 1 to 3 cycles across the image in random
    directions and phases: an error that varies slowly over the image."""
    angle = rng.uniform(0.0, 2.0 * np.pi, modes)
    cycles = rng.uniform(1.0, 3.0, modes)
    phase = rng.uniform(0.0, 2.0 * np.pi, modes)
    y, x = np.mgrid[0:h, 0:w]
    arg = (np.cos(angle)[:, None, None] * x[None] / w + np.sin(angle)[:, None, None] * y[None] / h)
    waves = np.cos(2.0 * np.pi * cycles[:, None, None] * arg + phase[:, None, None])
    return waves.sum(0) * np.sqrt(2.0 / modes)


def noisy_poses(T_wc: np.ndarray, *, scale: float, noise: PoseNoise, rng: np.random.Generator) -> np.ndarray:
    """T_wc [n,4,4] metric camera poses in C1 -> up-to-scale poses with ``noise`` (model units = metres / scale),
    re-anchored so that the first is the identity."""
    n = len(T_wc)
    axis = rng.standard_normal((n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    out = T_wc.copy()
    out[:, :3, :3] = T_wc[:, :3, :3] @ so3.exp(axis * np.radians(noise.rot_deg))
    out[:, :3, 3] += rng.standard_normal((n, 3)) * noise.pos_m
    if noise.drift_m > 0 and n > 1:
        out[:, :3, 3] += np.cumsum(rng.standard_normal((n, 3)), axis=0) * (noise.drift_m / np.sqrt(n))
    out = so3.relative_to_first(out)
    out[:, :3, 3] /= scale
    return out


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


def make_init_case(seed: int, *, kind: str = "drone", motion: str = "medium", n: int = CLIP_LENGTH,
                   stride: int = CLIP_STRIDE, scale: float | None = None, pose_noise: PoseNoise | None = None,
                   imu_noise: ImuNoise = EUROC_NOISE,
                   accel_bias: bool = True, bg_sigma: float = 0.02, depth_m: float = 3.0,
                   with_orientation: bool = False) -> InitCase:
    """A clip of n frames at ``stride`` x 20 Hz with 200 Hz IMU, EuRoC extrinsics and noise.

    motion: the drone's motion preset (``vi3_core.sim.trajectory.MOTIONS``); scale: drawn log-uniformly in
    [0.1, 10] when None; pose_noise: the 3DFM-like errors of the poses (none by default); gyro bias drawn
    N(0, bg_sigma) per axis; with ``accel_bias`` and a noisy IMU, an accelerometer bias of EuRoC's size
    (``draw_accel_bias``), else none (a noise-free IMU stays exact); the
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
    poses = noisy_poses(T_wc, scale=scale, noise=pose_noise or PoseNoise(), rng=rng)
    geometry = Geometry(T_wc=poses, K=np.tile(np.eye(3), (n, 1, 1)), depth=np.full((n, 4, 4), depth_m / scale),
                        conf=np.ones((n, 4, 4)), metric=False)
    R1 = T_WB[0, :3, :3]
    k1 = int(np.argmin(np.abs(imu.samples.t - stamps[0])))
    return InitCase(geometry=geometry, imu=imu.samples, stamps=stamps, T_BC=T_BC, scale=scale,
                    bg=imu.bg[k1], g=R1.T @ np.array([0.0, 0.0, -9.81]),
                    v1=R1.T @ traj.velocity_W(stamps[:1])[0], T_B1Bi=T_B1Bi)
