"""IMU-rate odometry between clips (beyond the paper): the last chained clip's state propagated with every IMU sample
that arrives after its last frame, as a VIO node propagates between camera updates.

The state at the last chained frame t_c (``OdomState``: pose T_OB, velocity v_O, biases bg and ba; gravity
[0, 0, -G] in odom) is advanced sample by sample with the integration scheme of the clips' IMU targets
(``vi3_core.preintegration``; the tests hold the two to 1e-9): over each interval the rotation turns by the midpoint
rate ((w_k + w_k+1) / 2 - bg) dt, the specific force rotated into odom is linear in time, so the velocity gains its
trapezoid and the position the exact double integral. One step works on plain floats (the attitude a unit
quaternion): numpy's per-call cost on 3-vectors made a sample cost 150 us of CPU, the node's whole budget three times
over. The next chained clip replaces the state (the correction); a new ``ImuPropagator`` starts from it and catches
up through the IMU recorded since its last frame.

Uncertainty (``SigmaModel``) is that of the propagation relative to the chained pose at t_c, which the
correction replaces: it grows with tau = t - t_c from the state's velocity and gravity-direction 1-sigmas and the IMU
noise model. (A bridge between two clips, ``OdomChain.placement``, knows the velocity at both ends and grows
more slowly.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vi3_core import so3
from vi3_core.fit.noise import ImuNoiseModel
from vi3_core.online.chain import OdomState
from vi3_core.types import ImuSamples

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


@dataclass(frozen=True)
class PropagationSigmas:
    """1-sigmas of a propagation at times tau [m] (or one tau, then floats) s after the last chained frame: position_h
    (per horizontal axis of odom, m; a gravity-direction error tilts the integrated acceleration sideways), position_v
    (vertical, m), velocity (per axis, m/s), tilt (roll and pitch about the odom x and y axes, rad), yaw (about odom z,
    rad)."""

    position_h: np.ndarray | float
    position_v: np.ndarray | float
    velocity: np.ndarray | float
    tilt: np.ndarray | float
    yaw: np.ndarray | float


@dataclass(frozen=True)
class SigmaModel:
    """The 1-sigmas of a propagation from a state whose velocity 1-sigma is v_sigma m/s and gravity direction 1-sigma
    g_sigma rad, under the accelerometer and gyro white noise of an ``ImuNoiseModel`` (``of``). Position: v_sigma tau,
    0.5 G g_sigma tau^2 (horizontal only) and the integrated accelerometer noise q_a tau^1.5 / sqrt(3), added in
    quadrature; velocity: v_sigma, G g_sigma tau, q_a sqrt(tau); attitude: the gravity direction's sigma (tilt) and
    the gyro noise q_g sqrt(tau). Bias errors are inside v_sigma / g_sigma at t_c and not propagated further.

    Each 1-sigma squared is a sum of powers of tau, kept as its coefficients (SI units): a state's sigmas at one tau
    cost a few float operations (the node evaluates them per IMU sample) and at many taus one vectorised pass."""

    v2: float  # v_sigma^2
    a2: float  # accelerometer white noise density^2
    tilt2: float  # (0.5 G g_sigma)^2: horizontal position from a tilted gravity
    gv2: float  # (G g_sigma)^2
    g2: float  # g_sigma^2
    w2: float  # gyro white noise density^2

    @classmethod
    def of(cls, *, v_sigma: float, g_sigma: float, noise: ImuNoiseModel, gravity_norm: float) -> SigmaModel:
        qa, qg, G = noise.accel_noise_density, noise.gyro_noise_density, gravity_norm
        return cls(v_sigma**2, qa**2, (0.5 * G * g_sigma) ** 2, (G * g_sigma) ** 2, g_sigma**2, qg**2)

    def at(self, tau):
        """``PropagationSigmas`` at tau s >= 0 (a float, or an array: arrays out)."""
        t2 = tau * tau
        pos_v2 = self.v2 * t2 + self.a2 * t2 * tau / 3.0
        return PropagationSigmas(position_h=(pos_v2 + self.tilt2 * t2 * t2) ** 0.5, position_v=pos_v2**0.5,
                                 velocity=(self.v2 + self.gv2 * t2 + self.a2 * tau) ** 0.5,
                                 tilt=(self.g2 + self.w2 * tau) ** 0.5, yaw=(self.w2 * tau) ** 0.5)


@dataclass(frozen=True, slots=True)
class ImuState:
    """One propagated state, in plain floats: t s; p m and v m/s in odom; q (x, y, z, w) the body's attitude in odom;
    R its matrix, row-major (9); omega rad/s the body rate (gyro - bg); tau s since the last chained frame."""

    t: float
    p: Vec3
    v: Vec3
    q: Quat
    R: tuple[float, ...]
    omega: Vec3
    tau: float

    @property
    def T_OB(self) -> np.ndarray:
        """[4,4] the body pose in odom."""
        return so3.make_T(np.reshape(self.R, (3, 3)), self.p)

    @property
    def v_body(self) -> Vec3:
        """The velocity in the body frame, R^T v, m/s."""
        R, (x, y, z) = self.R, self.v
        return (R[0] * x + R[3] * y + R[6] * z, R[1] * x + R[4] * y + R[7] * z, R[2] * x + R[5] * y + R[8] * z)


def _quat_R(q: Quat) -> tuple[float, ...]:
    """The rotation matrix (row-major, 9 floats) of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    xx, yy, zz, xy, xz, yz, wx, wy, wz = x * x, y * y, z * z, x * y, x * z, y * z, w * x, w * y, w * z
    return (1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy),
            2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx),
            2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy))


def _turn(q: Quat, rx: float, ry: float, rz: float) -> Quat:
    """q Exp(r): the attitude turned by the rotation vector r (rad) in the body frame, renormalised."""
    th = math.sqrt(rx * rx + ry * ry + rz * rz)
    s = 0.5 - th * th / 48.0 if th < 1e-4 else math.sin(0.5 * th) / th  # sin(th/2)/th, Taylor near 0
    bx, by, bz, bw = rx * s, ry * s, rz * s, math.cos(0.5 * th)
    x, y, z, w = q
    out = (w * bx + x * bw + y * bz - z * by, w * by - x * bz + y * bw + z * bx,
           w * bz + x * by - y * bx + z * bw, w * bw - x * bx - y * by - z * bz)
    n = math.sqrt(sum(c * c for c in out))
    return (out[0] / n, out[1] / n, out[2] / n, out[3] / n)


class ImuPropagator:
    """Propagates one chained state (``OdomState``, its last frame) with the IMU samples that follow it.

    ``step(t, gyro, accel)`` integrates one sample and returns the state at it (None when it is not after the current
    time, precedes the state, or the propagation has stopped); ``advance(imu)`` does so for every sample of ``imu``.
    The IMU is interpolated at the state's last frame, so nothing is returned until a sample at or before it and one
    after it have come. Propagation stops for good (``stopped`` names why; a new chained state starts a new
    propagator) at the first gap between samples longer than ``max_gap_s``, a non-finite sample, or ``max_tau_s``
    after the state: beyond those the IMU no longer supports the state. Not thread-safe."""

    def __init__(self, state: OdomState, *, gravity_norm: float, max_gap_s: float, max_tau_s: float) -> None:
        self.t_c = float(state.stamps[-1])
        self.bg = tuple(float(b) for b in state.bg)
        self.ba = tuple(float(b) for b in state.ba)
        self.gravity = float(gravity_norm)
        self.max_gap_s, self.max_tau_s = max_gap_s, max_tau_s
        T = np.asarray(state.T_OB[-1], np.float64)
        q = so3.R_to_quat(T[:3, :3])
        self._q: Quat = tuple(float(c) for c in q)
        self._R = _quat_R(self._q)
        self._p: Vec3 = tuple(float(c) for c in T[:3, 3])
        self._v: Vec3 = tuple(float(c) for c in np.asarray(state.v_O[-1], np.float64))
        self.t = self.t_c  # the time of the current state
        self._imu: tuple[Vec3, Vec3] | None = None  # (gyro, accel) at self.t; None until a sample after t_c came
        self._before: tuple[float, np.ndarray, np.ndarray] | None = None  # until then, the last sample <= t_c
        self.stopped = ""

    def advance_states(self, imu: ImuSamples) -> list[ImuState]:
        """The states at the samples of ``imu`` after the current time (none once ``stopped``)."""
        out = []
        for t, gyro, accel in zip(imu.t.tolist(), imu.gyro, imu.accel):
            s = self.step(t, gyro, accel)
            if s is not None:
                out.append(s)
            elif self.stopped:
                break
        return out

    def step(self, t: float, gyro, accel) -> ImuState | None:
        """The state at one sample (t s; gyro [3] rad/s; accel [3] m/s^2, body frame), or None (see the class)."""
        if self.stopped:
            return None
        if self._imu is None:
            if not self._start(t, gyro, accel):
                return None
        elif t <= self.t:
            return None
        (gx, gy, gz), (ax, ay, az) = (float(c) for c in gyro), (float(c) for c in accel)
        if not all(map(math.isfinite, (gx, gy, gz, ax, ay, az))):
            self.stopped = f"non-finite IMU sample at {t:.6f} s"
            return None
        if t - self.t > self.max_gap_s:
            self.stopped = f"IMU gap of {t - self.t:.3f} s > {self.max_gap_s} s at {self.t:.6f} s"
            return None
        if t - self.t_c > self.max_tau_s:
            self.stopped = f"{self.max_tau_s} s since the last chained clip (its frame at {self.t_c:.6f} s)"
            return None
        (w0x, w0y, w0z), (a0x, a0y, a0z) = self._imu
        bgx, bgy, bgz = self.bg
        bax, bay, baz = self.ba
        dt = t - self.t
        R0 = self._R
        q1 = _turn(self._q, (0.5 * (w0x + gx) - bgx) * dt, (0.5 * (w0y + gy) - bgy) * dt, (0.5 * (w0z + gz) - bgz) * dt)
        R1 = _quat_R(q1)
        # the specific force in odom at both ends (Eq. preintegrationVelocity's integrand), linear in between
        f0 = _mul(R0, a0x - bax, a0y - bay, a0z - baz)
        f1 = _mul(R1, ax - bax, ay - bay, az - baz)
        gz_dt = -self.gravity * dt
        c1, c2 = 0.5 * dt, dt * dt / 6.0
        v0 = self._v
        v1 = (v0[0] + c1 * (f0[0] + f1[0]), v0[1] + c1 * (f0[1] + f1[1]), v0[2] + gz_dt + c1 * (f0[2] + f1[2]))
        p0 = self._p
        p1 = (p0[0] + v0[0] * dt + c2 * (2.0 * f0[0] + f1[0]), p0[1] + v0[1] * dt + c2 * (2.0 * f0[1] + f1[1]),
              p0[2] + v0[2] * dt + 0.5 * gz_dt * dt + c2 * (2.0 * f0[2] + f1[2]))
        self.t, self._q, self._R, self._p, self._v, self._imu = t, q1, R1, p1, v1, ((gx, gy, gz), (ax, ay, az))
        return ImuState(t, p1, v1, q1, R1, (gx - bgx, gy - bgy, gz - bgz), t - self.t_c)

    def _start(self, t: float, gyro, accel) -> bool:
        """The IMU at the state's last frame, interpolated between the last sample at or before it and the first
        after it (``t``); False while no sample after it has come (a sample at or before it is kept), and stopped
        when the IMU starts after it or is not finite there."""
        if t <= self.t_c:
            self._before = (t, np.asarray(gyro, np.float64), np.asarray(accel, np.float64))
            return False
        if self._before is None:
            self.stopped = f"IMU starts at {t:.6f} s, after the chained frame at {self.t_c:.6f} s"
            return False
        t0, g0, a0 = self._before
        u = (self.t_c - t0) / (t - t0)
        g = (1.0 - u) * g0 + u * np.asarray(gyro, np.float64)
        a = (1.0 - u) * a0 + u * np.asarray(accel, np.float64)
        if not (np.isfinite(g).all() and np.isfinite(a).all()):
            self.stopped = f"non-finite IMU at the chained frame {self.t_c:.6f} s"
            return False
        self._imu = (tuple(g.tolist()), tuple(a.tolist()))
        return True


def _mul(R: tuple[float, ...], x: float, y: float, z: float) -> Vec3:
    """R (row-major, 9) times (x, y, z)."""
    return (R[0] * x + R[1] * y + R[2] * z, R[3] * x + R[4] * y + R[5] * z, R[6] * x + R[7] * y + R[8] * z)


__all__ = ["ImuPropagator", "ImuState", "PropagationSigmas", "SigmaModel"]
