"""IMU-rate odometry between clips (beyond the paper): the last chained clip's state propagated with every IMU sample
that arrives after its last frame, as a VIO node propagates between camera updates.

The state at the last chained frame t_c (``OdomState``: pose T_OB, velocity v_O, biases bg and ba; gravity
[0, 0, -G] in odom) is propagated with ``vi3_core.preintegration``, the integration scheme of the clips' IMU targets:
each batch of samples is preintegrated in the body frame of the current state and turned into odom poses and
velocities with ``Preintegration.propagate``. The next chained clip replaces the state (the correction); a new
``ImuPropagator`` starts from it and catches up through the IMU recorded since its last frame.

Uncertainty (``propagation_sigmas``) is that of the propagation relative to the chained pose at t_c, which the
correction replaces: it grows with tau = t - t_c from the state's velocity and gravity-direction 1-sigmas and the IMU
noise model. The position term is the one the estimator uses to decide whether a bridge still joins two clips.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vi3_core import so3
from vi3_core.fit.noise import ImuNoiseModel
from vi3_core.online.estimator import OdomState
from vi3_core.preintegration import Grid, preintegrate
from vi3_core.types import ImuSamples


@dataclass(frozen=True)
class PropagationSigmas:
    """1-sigmas of a propagation at times tau [m] s after the last chained frame, each [m]: position_h (per
    horizontal axis of odom, m; a gravity-direction error tilts the integrated acceleration sideways), position_v
    (vertical, m), velocity (per axis, m/s), tilt (roll and pitch about the odom x and y axes, rad), yaw (about odom z,
    rad)."""

    position_h: np.ndarray
    position_v: np.ndarray
    velocity: np.ndarray
    tilt: np.ndarray
    yaw: np.ndarray


def propagation_sigmas(tau, *, v_sigma: float, g_sigma: float, noise: ImuNoiseModel,
                       gravity_norm: float) -> PropagationSigmas:
    """The 1-sigmas ``tau`` [m] (or scalar) s after a state whose velocity 1-sigma is ``v_sigma`` m/s and gravity
    direction 1-sigma ``g_sigma`` rad, under the accelerometer and gyro white noise of ``noise``.

    Position: v_sigma tau, 0.5 G g_sigma tau^2 (horizontal only) and the integrated accelerometer noise
    q_a tau^1.5 / sqrt(3), added in quadrature; velocity: v_sigma, G g_sigma tau, q_a sqrt(tau); attitude: the
    gravity direction's sigma (tilt) and the gyro noise q_g sqrt(tau). Bias errors are inside v_sigma / g_sigma at
    t_c and not propagated further."""
    tau = np.maximum(np.asarray(tau, dtype=np.float64), 0.0)
    qa, qg, G = noise.accel_noise_density, noise.gyro_noise_density, gravity_norm
    from_v, from_a = v_sigma * tau, qa * tau**1.5 / math.sqrt(3.0)
    return PropagationSigmas(position_h=np.sqrt(from_v**2 + (0.5 * G * g_sigma * tau**2) ** 2 + from_a**2),
                             position_v=np.hypot(from_v, from_a),
                             velocity=np.sqrt(v_sigma**2 + (G * g_sigma * tau) ** 2 + qa**2 * tau),
                             tilt=np.sqrt(g_sigma**2 + qg**2 * tau), yaw=qg * np.sqrt(tau))


@dataclass(frozen=True)
class PropagatedStates:
    """States at m IMU sample stamps: t [m] s; T_OB [m,4,4] body poses in odom; v_O [m,3] m/s in odom; omega [m,3]
    rad/s body rate (gyro - bg, body frame); tau [m] s since the last chained frame."""

    t: np.ndarray
    T_OB: np.ndarray
    v_O: np.ndarray
    omega: np.ndarray
    tau: np.ndarray

    def __len__(self) -> int:
        return len(self.t)


class ImuPropagator:
    """Propagates one chained state (``OdomState``, its last frame) with the IMU samples that follow it.

    ``advance(imu)`` integrates the samples of ``imu`` after the current time (earlier ones were integrated already,
    or precede the state) and returns the states at them. The IMU is interpolated at the state's last frame, so
    nothing is returned until calls have brought a sample at or before it and one after it. Propagation stops for
    good (``stopped`` names why; a new chained state starts a new propagator) at the first gap between samples longer
    than ``max_gap_s``, a non-finite sample, or ``max_tau_s`` after the state: beyond those the IMU no longer supports
    the state. Not thread-safe."""

    def __init__(self, state: OdomState, *, gravity_norm: float, max_gap_s: float, max_tau_s: float) -> None:
        self.t_c = float(state.stamps[-1])
        self.bg, self.ba = np.asarray(state.bg, np.float64), np.asarray(state.ba, np.float64)
        self.g_O = np.array([0.0, 0.0, -gravity_norm])
        self.max_gap_s, self.max_tau_s = max_gap_s, max_tau_s
        self.T_OB = np.asarray(state.T_OB[-1], np.float64)  # the current state, at time self.t
        self.v_O = np.asarray(state.v_O[-1], np.float64)
        self.t = self.t_c
        self._gyro: np.ndarray | None = None  # the IMU at self.t (None until a sample after t_c arrived)
        self._accel: np.ndarray | None = None
        self._before: ImuSamples | None = None  # until then, the last sample at or before t_c
        self.stopped = ""

    def advance(self, imu: ImuSamples) -> PropagatedStates:
        """States at the samples of ``imu`` after the current time (none once ``stopped``)."""
        if self.stopped:
            return _empty()
        if self._gyro is None and not self._start(imu):
            return _empty()
        new = imu.t > self.t
        t = np.concatenate([[self.t], imu.t[new]])
        gyro = np.concatenate([self._gyro[None], imu.gyro[new]])
        accel = np.concatenate([self._accel[None], imu.accel[new]])
        m = self._usable(t, gyro, accel)
        if m == 0:
            return _empty()
        t, gyro, accel = t[: m + 1], gyro[: m + 1], accel[: m + 1]
        grid = Grid(t, gyro, accel, np.arange(m + 1))  # the samples are the integration grid, nothing to interpolate
        pre = preintegrate(ImuSamples(t, gyro, accel), t, self.bg, self.ba, grid=grid)
        R0, p0 = self.T_OB[:3, :3], self.T_OB[:3, 3]
        rel = pre.propagate(R0.T @ self.g_O, R0.T @ self.v_O)  # in the body frame at self.t
        T_OB = so3.make_T(R0 @ rel.R[1:], p0 + rel.p[1:] @ R0.T)
        v_O = rel.v[1:] @ R0.T
        self.T_OB, self.v_O, self.t, self._gyro, self._accel = T_OB[-1], v_O[-1], float(t[-1]), gyro[-1], accel[-1]
        return PropagatedStates(t[1:], T_OB, v_O, gyro[1:] - self.bg, t[1:] - self.t_c)

    def _start(self, imu: ImuSamples) -> bool:
        """The IMU at the state's last frame, interpolated between the samples around it; False (stopped when the IMU
        starts after it) while there is no sample after it yet (the last one before it is kept for the next call)."""
        if self._before is not None:
            imu = ImuSamples.concatenate([self._before, imu.select(imu.t > self._before.t[0])])
        if len(imu) and imu.t[0] > self.t_c:
            self.stopped = f"IMU starts at {imu.t[0]:.6f} s, after the chained frame at {self.t_c:.6f} s"
        if self.stopped or not len(imu):
            return False
        if imu.t[-1] <= self.t_c:
            self._before = imu.select(slice(len(imu) - 1, None))
            return False
        self._gyro = np.array([np.interp(self.t_c, imu.t, imu.gyro[:, a]) for a in range(3)])
        self._accel = np.array([np.interp(self.t_c, imu.t, imu.accel[:, a]) for a in range(3)])
        if not (np.isfinite(self._gyro).all() and np.isfinite(self._accel).all()):
            self.stopped = f"non-finite IMU at the chained frame {self.t_c:.6f} s"
            return False
        return True

    def _usable(self, t: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> int:
        """How many of the new samples t[1:] can be integrated; sets ``stopped`` at the first that cannot."""
        bad = ~(np.isfinite(gyro[1:]).all(1) & np.isfinite(accel[1:]).all(1))
        gap = np.diff(t) > self.max_gap_s
        late = t[1:] - self.t_c > self.max_tau_s
        stop = bad | gap | late
        if not stop.any():
            return len(t) - 1
        k = int(np.argmax(stop))
        if bad[k]:
            self.stopped = f"non-finite IMU sample at {t[k + 1]:.6f} s"
        elif gap[k]:
            self.stopped = f"IMU gap of {t[k + 1] - t[k]:.3f} s > {self.max_gap_s} s at {t[k]:.6f} s"
        else:
            self.stopped = f"{self.max_tau_s} s since the last chained clip (its frame at {self.t_c:.6f} s)"
        return k


def _empty() -> PropagatedStates:
    return PropagatedStates(np.zeros(0), np.zeros((0, 4, 4)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))


__all__ = ["ImuPropagator", "PropagatedStates", "PropagationSigmas", "propagation_sigmas"]
