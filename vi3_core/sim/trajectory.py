"""Smooth 6-DoF body trajectories with analytic derivatives.

World W is z-up with gravity g_W = [0, 0, -9.81]. The body (IMU) frame follows EuRoC's mounting: body x
points up, body z forward (along cam0's optical axis), so a level body has R_WB = R_vehicle @ R_MOUNT.
Position is a sum of sinusoids and the vehicle's yaw/pitch/roll are sums of sinusoids or follow the thrust,
so velocity, acceleration, jerk and angular velocity are exact closed forms (no numerical differentiation).

Drone motion comes in presets (``MOTIONS``). ``easy``, ``medium`` and ``difficult`` fly like EuRoC's Vicon-room
sequences: a smooth flight whose acceleration spectrum falls off above ~0.3 Hz like V1_02_medium's, with the
vehicle tilting its thrust axis along the acceleration as a multirotor does (plus a small attitude wobble), and
the speed, acceleration and angular-rate medians of the preset fitted per seed (``PRESETS``; docs/evaluation.md
lists the percentiles they give). ``handheld`` is a camera carried by hand around a room: the same spectrum of
gentler motion (the medians of a real handheld RealSense recording), the camera held roughly level and panned, its
attitude its own (slow yaw, a few degrees of pitch and roll), not the thrust's. ``agile`` is the earlier generator:
slow drift with fast small manoeuvres on top and an attitude independent of the acceleration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vi3_core import so3

#: Columns are the body axes expressed in the vehicle's forward-left-up frame (EuRoC: x up, z forward).
R_MOUNT = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
GRAVITY = 9.81

KINDS = ("drone", "hover", "pure_rotation", "stationary")
MOTIONS = ("easy", "medium", "difficult", "handheld", "agile")


@dataclass(frozen=True)
class MotionPreset:
    """Medians a realistic preset is fitted to, per seed: speed |v| (m/s), kinematic acceleration |a| (m/s^2,
    gravity excluded) and angular rate |omega| (rad/s); ``wobble_deg``: attitude wobble about the thrust-aligned
    attitude (1-3 Hz)."""

    speed: float
    accel: float
    angular_rate: float
    wobble_deg: float = 0.3


#: medium: EuRoC V1_02_medium (measured on its real ground truth and IMU, ../shared/data/euroc_v102_imu_gt);
#: easy and difficult: estimates from the EuRoC paper's per-sequence averages (docs/evaluation.md says which).
PRESETS: dict[str, MotionPreset] = {
    "easy": MotionPreset(speed=0.40, accel=0.35, angular_rate=0.19),
    "medium": MotionPreset(speed=0.92, accel=1.12, angular_rate=0.42),
    "difficult": MotionPreset(speed=0.78, accel=1.12, angular_rate=0.55),
    # a person walking a RealSense around a bedroom (github Zoltan3057/DM-VIO-dataset: |gyro| 0.11-0.18 rad/s, the
    # accelerometer norm's standard deviation 0.16-0.30 m/s^2 per 10 s; its speed from an offline reconstruction)
    "handheld": MotionPreset(speed=0.25, accel=0.25, angular_rate=0.13, wobble_deg=2.0),
}


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
class ThrustAttitude:
    """A multirotor's yaw, pitch and roll: the vehicle z axis (thrust) along a_W - g_W of ``position``, yaw from
    ``yaw`` [1 channel], plus ``wobble`` [2 channels: pitch, roll] added to the thrust-aligned pitch and roll."""

    position: Sines
    yaw: Sines
    wobble: Sines

    def derivative(self, t: np.ndarray, order: int) -> np.ndarray:
        """(yaw, pitch, roll) [N,3] (order 0, rad) or their rates (order 1, rad/s) at t [N]."""
        if order not in (0, 1):
            raise ValueError(f"ThrustAttitude has derivatives of order 0 and 1, not {order}")
        psi = self.yaw.derivative(t, 0)[:, 0]
        c, s = np.cos(psi), np.sin(psi)
        m = self.position.derivative(t, 2) + np.array([0.0, 0.0, GRAVITY])  # thrust direction in W, unnormalised
        # n: the thrust direction in the yawed frame Rz(psi)^T; R_veh e3 = Rz(psi) Ry(pitch) Rx(roll) e3 = n / |n|.
        n = np.stack([c * m[:, 0] + s * m[:, 1], -s * m[:, 0] + c * m[:, 1], m[:, 2]], -1)
        rho = np.hypot(n[:, 0], n[:, 2])
        wobble = self.wobble.derivative(t, order)
        if order == 0:
            pitch, roll = np.arctan2(n[:, 0], n[:, 2]), -np.arctan2(n[:, 1], rho)
            return np.stack([psi, pitch + wobble[:, 0], roll + wobble[:, 1]], -1)
        j = self.position.derivative(t, 3)
        dpsi = self.yaw.derivative(t, 1)[:, 0]
        dn = np.stack([c * j[:, 0] + s * j[:, 1] + dpsi * n[:, 1], -s * j[:, 0] + c * j[:, 1] - dpsi * n[:, 0],
                       j[:, 2]], -1)
        dpitch = (n[:, 2] * dn[:, 0] - n[:, 0] * dn[:, 2]) / rho**2
        drho = (n[:, 0] * dn[:, 0] + n[:, 2] * dn[:, 2]) / rho
        droll = -(rho * dn[:, 1] - n[:, 1] * drho) / (n[:, 1] ** 2 + rho**2)
        return np.stack([dpsi, dpitch + wobble[:, 0], droll + wobble[:, 1]], -1)


@dataclass(frozen=True)
class Trajectory:
    """Analytic body trajectory in W: position sines [3 channels], attitude (yaw, pitch, roll) sines or thrust."""

    kind: str
    position: Sines
    attitude: Sines | ThrustAttitude

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


def make_trajectory(kind: str = "drone", seed: int = 0, *, motion: str = "medium",
                    center: tuple[float, float, float] = (0.0, 0.0, 1.5),
                    extent: tuple[float, float, float] = (1.8, 1.8, 0.4)) -> Trajectory:
    """A deterministic random trajectory of the given kind.

    drone: a flight of the ``motion`` preset (``MOTIONS``) within +-``extent`` m of ``center``;
    hover: millimetre jitter around ``center`` with slow yaw; pure_rotation: fixed position, body rotating;
    stationary: constant pose (only sensor noise moves).
    """
    if kind not in KINDS:
        raise ValueError(f"unknown trajectory kind {kind!r}; choose one of {KINDS}")
    if motion not in MOTIONS:
        raise ValueError(f"unknown motion preset {motion!r}; choose one of {MOTIONS}")
    rng = np.random.default_rng(seed)
    c = np.asarray(center, dtype=np.float64)
    yaw0 = rng.uniform(-np.pi, np.pi)
    if kind == "drone" and motion != "agile":
        return _flight(rng, PRESETS[motion], c, np.asarray(extent, dtype=np.float64), yaw0,
                       handheld=motion == "handheld")
    if kind == "drone":
        pos, att = _agile(rng, c, np.asarray(extent, dtype=np.float64), yaw0)
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


def _agile(rng: np.random.Generator, c: np.ndarray, ext: np.ndarray, yaw0: float) -> tuple[Sines, Sines]:
    """The ``agile`` preset: slow sines filling the volume, mean speed 0.3-1.5 m/s, 1.5-4 cm manoeuvres at
    0.3-0.8 Hz on top, attitude independent of the acceleration."""
    pos = _sines(rng, 3, (0.4, 1.0), (0.06, 0.2), offset=c)
    pos = Sines(pos.amp * (ext / np.abs(pos.amp).sum(1))[:, None], pos.freq, pos.phase, pos.offset, pos.rate)
    ts = np.linspace(0.0, 60.0, 2001)
    mean_speed = np.linalg.norm(pos.derivative(ts, 1), axis=1).mean()
    target = rng.uniform(0.3, 1.5)
    # Faster motion by raising frequencies keeps the flight inside the room.
    pos = Sines(pos.amp, pos.freq * target / mean_speed, pos.phase, pos.offset, pos.rate)
    agile = _sines(rng, 3, (0.015, 0.04), (0.3, 0.8))
    pos = Sines(np.concatenate([pos.amp, agile.amp], 1), np.concatenate([pos.freq, agile.freq], 1),
                np.concatenate([pos.phase, agile.phase], 1), pos.offset, pos.rate)
    att = _sines(rng, 3, (0.03, 0.08), (0.1, 0.4), offset=(yaw0, 0.0, 0.0))
    att = Sines(att.amp * np.array([[12.0], [1.0], [1.0]]), att.freq * np.array([[0.3], [1.0], [1.0]]),
                att.phase, att.offset, att.rate)
    return pos, att


#: Position components per axis and their frequencies relative to the lowest (log-spaced), and the slope beta of
#: their acceleration amplitudes (proportional to freq**beta): with these V1_02_medium's acceleration falls off
#: above ~0.3 Hz as the generated one does (docs/evaluation.md).
_N_POS = 6
_REL_FREQ = np.geomspace(1.0, 10.0, _N_POS)
_BETA = -0.5
#: The stamps the per-seed fit evaluates the medians on (s): 800 random instants over 2 minutes (a regular grid
#: this sparse would alias the 1-3 Hz wobble).
_FIT_T = np.sort(np.random.default_rng(0).uniform(0.0, 120.0, 800))


def _flight(rng: np.random.Generator, preset: MotionPreset, c: np.ndarray, ext: np.ndarray,
            yaw0: float, *, handheld: bool = False) -> Trajectory:
    """A realistic flight: per axis ``_N_POS`` sinusoids at frequencies f0 * ``_REL_FREQ`` (jittered) with
    acceleration amplitudes ~ freq**``_BETA``, position amplitudes summing to ``fill`` * ``ext``; yaw a sum of
    slow sinusoids of rate gain ``gy``; thrust-aligned pitch and roll with a small wobble (``handheld``: pitch and roll
    their own slow sinusoids, the wobble's size, and the yaw's). f0 and fill (<= 1) are solved so that the medians of
    |v| and |a| over ``_FIT_T`` are the preset's, then gy for |omega| (0 if the tilt alone turns faster)."""
    rel = _REL_FREQ * rng.uniform(0.8, 1.25, size=(3, _N_POS))
    shape = rel ** (_BETA - 2.0) * rng.uniform(0.6, 1.4, size=(3, _N_POS))
    shape *= (ext / shape.sum(1))[:, None] * rng.choice([-1.0, 1.0], size=(3, _N_POS))
    phase = rng.uniform(0.0, 2.0 * np.pi, size=(3, _N_POS))
    yaw_rel = np.geomspace(0.5, 8.0, 3) * rng.uniform(0.8, 1.25, size=(1, 3))
    yaw_amp = rng.uniform(0.6, 1.4, size=(1, 3)) * rng.choice([-1.0, 1.0], size=(1, 3)) / (2.0 * np.pi * yaw_rel)
    yaw_phase = rng.uniform(0.0, 2.0 * np.pi, size=(1, 3))
    wobble = Sines(np.radians(preset.wobble_deg) * rng.uniform(0.5, 1.0, size=(2, 3)),
                   rng.uniform(1.0, 3.0, size=(2, 3)), rng.uniform(0.0, 2.0 * np.pi, size=(2, 3)),
                   np.zeros(2), np.zeros(2))
    tilt_phase = rng.uniform(0.0, 2.0 * np.pi, size=(2, 3))
    tilt = np.radians(preset.wobble_deg) * rng.uniform(0.5, 1.0, size=(2, 3)) * rng.choice([-1.0, 1.0], size=(2, 3))

    def build(f0: float, fill: float, gy: float) -> Trajectory:
        pos = Sines(fill * shape, f0 * rel, phase, c, np.zeros(3))
        # Yaw-rate amplitudes gy per component; yaw frequencies tied to the flight's.
        yaw = Sines(yaw_amp * gy / f0, f0 * yaw_rel, yaw_phase, np.array([yaw0]), np.zeros(1))
        if handheld:  # yaw, pitch and roll of their own (the hand's), tilt at the flight's frequencies
            att = Sines(np.concatenate([yaw.amp, tilt * max(gy, 1e-3) / max(preset.angular_rate, 1e-3)]),
                        np.concatenate([yaw.freq, f0 * np.tile(yaw_rel, (2, 1))]),
                        np.concatenate([yaw.phase, tilt_phase]), np.array([yaw0, 0.0, 0.0]), np.zeros(3))
            return Trajectory(kind="drone", position=pos, attitude=att)
        return Trajectory(kind="drone", position=pos, attitude=ThrustAttitude(pos, yaw, wobble))

    def median(f) -> float:
        return float(np.median(np.linalg.norm(f(_FIT_T), axis=1)))

    # |v| ~ fill * f0 and |a| ~ fill * f0**2 (up to the fit window): a few fixed-point steps solve both.
    f0, fill = 0.1, 1.0
    for _ in range(4):
        traj = build(f0, fill, 0.0)
        v, a = median(traj.velocity_W), median(traj.acceleration_W)
        f0 *= (preset.accel / a) / (preset.speed / v)
        fill = min(fill * (preset.speed / v) ** 2 / (preset.accel / a), 1.0)

    # Tilt and yaw rates add about in quadrature, median|omega|^2 ~ w0^2 + k gy^2: secant steps on gy^2.
    def excess(gy: float) -> float:
        return median(build(f0, fill, gy).angular_velocity_B) ** 2 - preset.angular_rate**2

    x0, e0 = 0.0, excess(0.0)
    if e0 >= 0.0:  # the tilt alone turns as fast as the preset: no yaw
        return build(f0, fill, 0.0)
    x1 = preset.angular_rate**2
    e1 = excess(np.sqrt(x1))
    for _ in range(8):
        if abs(e1) < 1e-3 * preset.angular_rate**2 or e1 == e0:
            break
        x0, e0, x1 = x1, e1, max(x1 - e1 * (x1 - x0) / (e1 - e0), 1e-8)
        e1 = excess(np.sqrt(x1))
    return build(f0, fill, float(np.sqrt(x1)))
