"""Smooth 6-DoF body trajectories with analytic derivatives.

World W is z-up with gravity g_W = [0, 0, -9.81]. The body (IMU) frame follows EuRoC's mounting: body x
points up, body z forward (along cam0's optical axis), so a level body has R_WB = R_vehicle @ R_MOUNT.
Position and the vehicle's yaw/pitch/roll are sums of sinusoids, so velocity, acceleration and angular
velocity are exact closed forms (no numerical differentiation anywhere).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vi3_core import so3

#: Columns are the body axes expressed in the vehicle's forward-left-up frame (EuRoC: x up, z forward).
R_MOUNT = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])

KINDS = ("drone", "hover", "pure_rotation", "stationary")


@dataclass(frozen=True)
class Sines:
    """f(t) = offset + rate * t + sum_k amp_k sin(2 pi freq_k t + phase_k), per output channel.

    amp, freq, phase: [C,K]; offset, rate: [C].
    """

    amp: np.ndarray
    freq: np.ndarray
    phase: np.ndarray
    offset: np.ndarray
    rate: np.ndarray

    def derivative(self, t: np.ndarray, order: int) -> np.ndarray:
        """d^order f / dt^order at t [N] -> [N,C]."""
        t = np.asarray(t, dtype=np.float64)[:, None, None]
        w = 2.0 * np.pi * self.freq
        arg = w * t + self.phase
        # d^k/dt^k sin(x) = w^k sin(x + k pi/2)
        out = (self.amp * w**order * np.sin(arg + order * np.pi / 2)).sum(-1)
        if order == 0:
            out = out + self.offset + self.rate * t[..., 0]
        elif order == 1:
            out = out + self.rate
        return out


@dataclass(frozen=True)
class Trajectory:
    """Analytic body trajectory in W: position sines [3 channels], attitude sines (yaw, pitch, roll)."""

    kind: str
    position: Sines
    attitude: Sines

    def _ypr(self, t, order):
        return self.attitude.derivative(t, order)

    def rotation(self, t: np.ndarray) -> np.ndarray:
        """R_WB [N,3,3] at t [N]."""
        y, p, r = self._ypr(t, 0).T
        R_veh = so3.exp(np.stack([np.zeros_like(y), np.zeros_like(y), y], -1)) @ \
            so3.exp(np.stack([np.zeros_like(p), p, np.zeros_like(p)], -1)) @ \
            so3.exp(np.stack([r, np.zeros_like(r), np.zeros_like(r)], -1))
        return R_veh @ R_MOUNT

    def position_W(self, t: np.ndarray) -> np.ndarray:
        """p_WB [N,3], m."""
        return self.position.derivative(t, 0)

    def velocity_W(self, t: np.ndarray) -> np.ndarray:
        """v_WB [N,3], m/s."""
        return self.position.derivative(t, 1)

    def acceleration_W(self, t: np.ndarray) -> np.ndarray:
        """a_WB [N,3], m/s^2 (kinematic, gravity not included)."""
        return self.position.derivative(t, 2)

    def angular_velocity_B(self, t: np.ndarray) -> np.ndarray:
        """omega [N,3] of B relative to W, expressed in B, rad/s (ZYX Euler kinematics, then the mount)."""
        y, p, r = self._ypr(t, 0).T
        dy, dp, dr = self._ypr(t, 1).T
        w_veh = np.stack([dr - dy * np.sin(p),
                          dp * np.cos(r) + dy * np.cos(p) * np.sin(r),
                          -dp * np.sin(r) + dy * np.cos(p) * np.cos(r)], -1)
        return w_veh @ R_MOUNT  # R_MOUNT^T w, row-wise

    def T_WB(self, t: np.ndarray) -> np.ndarray:
        """Body poses [N,4,4] in W."""
        return so3.make_T(self.rotation(t), self.position_W(t))


def _sines(rng, n_ch, amp_range, freq_range, k=2, offset=None, rate=None):
    amp = rng.uniform(*amp_range, size=(n_ch, k)) * rng.choice([-1.0, 1.0], size=(n_ch, k))
    return Sines(amp=amp, freq=rng.uniform(*freq_range, size=(n_ch, k)),
                 phase=rng.uniform(0, 2 * np.pi, size=(n_ch, k)),
                 offset=np.zeros(n_ch) if offset is None else np.asarray(offset, dtype=np.float64),
                 rate=np.zeros(n_ch) if rate is None else np.asarray(rate, dtype=np.float64))


def make_trajectory(kind: str = "drone", seed: int = 0, *, speed: tuple[float, float] = (0.3, 1.5),
                    center: tuple[float, float, float] = (0.0, 0.0, 1.5),
                    extent: tuple[float, float, float] = (1.8, 1.8, 0.4)) -> Trajectory:
    """A deterministic random trajectory of the given kind.

    drone: EuRoC-like flight, mean speed within ``speed`` m/s, within +-``extent`` m of ``center``;
    hover: millimetre jitter around ``center`` with slow yaw; pure_rotation: fixed position, body rotating;
    stationary: constant pose (only sensor noise moves).
    """
    if kind not in KINDS:
        raise ValueError(f"unknown trajectory kind {kind!r}; choose one of {KINDS}")
    rng = np.random.default_rng(seed)
    c = np.asarray(center, dtype=np.float64)
    yaw0 = rng.uniform(-np.pi, np.pi)
    if kind == "drone":
        ext = np.asarray(extent)
        pos = _sines(rng, 3, (0.4, 1.0), (0.06, 0.2), offset=c)
        pos = Sines(pos.amp * (ext / np.abs(pos.amp).sum(1))[:, None], pos.freq, pos.phase, pos.offset, pos.rate)
        ts = np.linspace(0.0, 60.0, 2001)
        mean_speed = np.linalg.norm(pos.derivative(ts, 1), axis=1).mean()
        target = rng.uniform(*speed)
        # Faster motion by raising frequencies keeps the flight inside the room.
        pos = Sines(pos.amp, pos.freq * target / mean_speed, pos.phase, pos.offset, pos.rate)
        # Small, quicker manoeuvres on top (EuRoC flights accelerate at ~0.5-2 m/s^2, not only drift).
        agile = _sines(rng, 3, (0.015, 0.04), (0.3, 0.8))
        pos = Sines(np.concatenate([pos.amp, agile.amp], 1), np.concatenate([pos.freq, agile.freq], 1),
                    np.concatenate([pos.phase, agile.phase], 1), pos.offset, pos.rate)
        att = _sines(rng, 3, (0.03, 0.08), (0.1, 0.4), offset=(yaw0, 0.0, 0.0))
        att = Sines(att.amp * np.array([[12.0], [1.0], [1.0]]), att.freq * np.array([[0.3], [1.0], [1.0]]),
                    att.phase, att.offset, att.rate)
    elif kind == "hover":
        pos = _sines(rng, 3, (0.001, 0.003), (0.2, 1.0), offset=c)
        att = _sines(rng, 3, (0.002, 0.005), (0.2, 1.0), offset=(yaw0, 0.0, 0.0))
    elif kind == "pure_rotation":
        pos = _sines(rng, 3, (0.0, 0.0), (0.1, 0.2), offset=c)
        att = _sines(rng, 3, (0.15, 0.35), (0.15, 0.5), offset=(yaw0, 0.0, 0.0))
    else:
        pos = _sines(rng, 3, (0.0, 0.0), (0.1, 0.2), offset=c)
        att = _sines(rng, 3, (0.0, 0.0), (0.1, 0.2), offset=(yaw0, 0.02, -0.01))
    return Trajectory(kind=kind, position=pos, attitude=att)
