"""``~/odom/imu``: odometry at IMU rate between clips, shared by the node and replay (``vi3_ros.pipeline``), and the
covariances of both odometry topics (``covariances``; ``chained_covariances`` for ``~/odom``); each published state
also goes to the flight controllers' odometry (``vi3_ros.flight_odom``) when it is on.

After each chained clip the Pipeline calls ``restart`` with the new odom state and the IMU recorded since its last
frame (the worker thread; in the node the clip lands seconds after its frames, so the propagation catches up first);
every IMU sample then goes to ``add`` (the input thread), which advances ``vi3_core.online.propagator.ImuPropagator``
and publishes ``nav_msgs/Odometry`` at most ``imu_odom_rate`` times per second of IMU time (every sample when that is
the IMU's rate or more), stamped with the sample's own stamp. Pose covariance over (x, y, z, rot x, rot y, rot z) in
``odom_frame``: ``SigmaModel``'s since the last chained frame (zero at it; the chained pose's own uncertainty in
odom is not modelled); twist covariance in ``base_frame``: the velocity sigma and the gyro's white noise per sample.
Nothing is published before the first chained clip, nor once the propagation stopped (an IMU gap longer than
``max_imu_gap``, a non-finite sample, ``online_max_bridge`` s without a chained clip, or a horizontal position 1-sigma
above ``imu_odom_max_sigma``): ``status`` says why. Samples and states carry the clip buffer's epoch: when time went
back (a newer epoch) the propagation is forgotten, and a state chained from a clip of an older epoch is ignored.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from msg_adapters.poses import OdometryMessages
from msg_adapters.types import MessageTypes
from vi3_core.init.options import InitOptions
from vi3_core.online import OdomState, Trajectory
from vi3_core.online.propagator import ImuPropagator, ImuState, PropagationSigmas, SigmaModel
from vi3_core.types import ImuSamples
from vi3_ros.flight_odom import Anchor, FlightOdometry
from vi3_ros.settings import Settings

_DIAGONAL = np.arange(6) * 7  # the diagonal of a [6,6] covariance in its row-major [36]


def sigma_model(state: OdomState, options: InitOptions) -> SigmaModel:
    """The 1-sigmas of states propagated from ``state``'s last frame (``SigmaModel.at(tau)``), from ``state``'s sigmas
    and ``options``' IMU noise model."""
    return SigmaModel.of(v_sigma=state.v_sigma, g_sigma=state.g_sigma, noise=options.noise_model,
                         gravity_norm=options.gravity_norm)


def gyro_variance(options: InitOptions, sample_dt: float) -> float:
    """(rad/s)^2: the gyro's white noise over one sample interval ``sample_dt`` s."""
    return options.gyro_noise_density**2 / max(sample_dt, 1e-6)


def diagonals(s: PropagationSigmas, gyro_var) -> tuple[tuple, tuple]:
    """The diagonals (6 entries each, floats or arrays) of the pose covariance in odom over (x, y, z, rot x, rot y,
    rot z) and of the twist covariance in the body frame, of states with the 1-sigmas ``s`` (``SigmaModel.at``);
    ``gyro_var``: ``gyro_variance``."""
    h2, v2 = s.position_h**2, s.velocity**2
    return (h2, h2, s.position_v**2, s.tilt**2, s.tilt**2, s.yaw**2), (v2, v2, v2, gyro_var, gyro_var, gyro_var)


def covariances(s: PropagationSigmas, options: InitOptions, sample_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(pose covariance [m,6,6] in odom, twist covariance [m,6,6] in the body frame) of states with the 1-sigmas ``s``
    at m taus; ``sample_dt`` s: the IMU sample interval (gyro noise of ``options``)."""
    out = []
    for diag in diagonals(s, gyro_variance(options, sample_dt)):
        d = np.stack(np.broadcast_arrays(*diag), -1)
        cov = np.zeros(d.shape + (6,))
        cov[..., np.arange(6), np.arange(6)] = d
        out.append(cov)
    return out[0], out[1]


#: rad; the yaw 1-sigma of ``~/odom``: yaw in odom is unobservable (the first clip's is arbitrary), so it is not known.
ODOM_YAW_SIGMA = math.pi
#: the smallest 1-sigma (m, rad, m/s or rad/s) a diagonal entry of ``~/odom``'s covariances states: none is certain.
SIGMA_FLOOR = 1e-3


def start_covariances(state: OdomState, *, options: InitOptions, sample_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``covariances`` [6,6] (pose, twist) of ``~/odom/imu`` at the chained ``state``'s last frame (tau = 0): roll and
    pitch the gravity direction's sigma, velocity v_sigma, angular rate the gyro's white noise per ``sample_dt`` s,
    position and yaw zero."""
    pose, twist = covariances(sigma_model(state, options).at(np.zeros(1)), options, sample_dt)
    return pose[0], twist[0]


def chained_covariances(start: tuple[np.ndarray, np.ndarray],
                        trajectory: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """(pose covariance [6,6] in odom over x, y, z, rot x, rot y, rot z; twist covariance [6,6] in the body frame) of
    the chained state at its last frame (``~/odom``), relative to its segment's first frame (the segment's odom
    origin, exact by definition): ``start``, the state's ``start_covariances`` (not modified), plus per position axis
    what the segment's clips and bridges add up to (``trajectory.error_m``, ``trajectory.bridge_var``); yaw
    ODOM_YAW_SIGMA; every diagonal entry at least SIGMA_FLOOR^2."""
    pose, twist = start[0].copy(), start[1].copy()
    idx = np.arange(3)
    pose[idx, idx] += trajectory.error_m**2 + trajectory.bridge_var
    pose[5, 5] = ODOM_YAW_SIGMA**2
    for cov in (pose, twist):
        np.fill_diagonal(cov, np.maximum(np.diag(cov), SIGMA_FLOOR**2))
    return pose, twist


class ImuOdometry:
    """The IMU-rate odometry of one stream; thread-safe (``restart`` on the worker thread, ``add`` on the input
    thread). ``publish(key, msg, stamp_ns)`` is the Pipeline's; ``settings`` its settings. Lock order: ``restart``
    calls ``imu_since`` (which takes the Pipeline's lock) under this object's lock, so the Pipeline must not call
    into this object while it holds its own. A sample costs about 15 us of CPU with rosbags' message
    classes and 30 us with rclpy's, its message included (``vi3 bench pipeline``: ``imu_odom_us_per_sample``)."""

    def __init__(self, settings: Settings, *, types: MessageTypes, publish: Callable[[str, Any, int], None],
                 flight: FlightOdometry | None = None) -> None:
        self.period_ns = round(1e9 / settings.outputs.imu_odom_rate)
        self.max_sigma = float(settings.outputs.imu_odom_max_sigma)
        self.messages = OdometryMessages(frame_id=settings.frames.odom_frame,
                                         child_frame_id=settings.frames.base_frame, types=types)
        # dead reckoning is trusted for as long as the window bridges a gap between clips
        self.options, self.max_tau_s = settings.init, settings.online.online_max_bridge
        self.accel_A = settings.init.accel_A  # the accelerometer's calibration (None: none)

        self._publish, self.flight = publish, flight
        self._lock = threading.Lock()
        self._prop: ImuPropagator | None = None
        self._caught_up: list[ImuState] = []  # the states ``restart`` caught up through
        self._sigmas: SigmaModel | None = None  # of the state propagated
        self._anchor: Anchor | None = None  # the flight odometry's anchor of the state
        self._next_ns: int | None = None  # the next publication is due at the first sample at or after this stamp
        self._last_ns: int | None = None  # the previous sample's stamp
        self._epoch = 0  # the clip buffer's epoch of the samples and states taken
        self.published = 0

    @property
    def status(self) -> str:
        """``waiting`` (no chained clip yet), ``running`` or ``stopped: <why>``."""
        with self._lock:
            if self._prop is None:
                return "waiting"
            return f"stopped: {self._prop.stopped}" if self._prop.stopped else "running"

    def restart(self, state: OdomState, imu_since: Callable[[float], ImuSamples | None], epoch: int = 0,
                anchor: Anchor | None = None) -> None:
        """Start over from a newly chained ``state`` of a clip of buffer ``epoch``, catching up through
        ``imu_since(t)`` (the samples recorded from at or before t s to the newest; None: none), read while no sample
        can slip in between; nothing when time went back since that clip. ``anchor``: the clip's for ``flight``,
        taken together with the state, so that no sample pairs one clip's state with another's."""
        prop = ImuPropagator(state, gravity_norm=self.options.gravity_norm, max_gap_s=self.options.max_imu_gap,
                             max_tau_s=self.max_tau_s)
        sigmas = sigma_model(state, self.options)
        with self._lock:
            if not self._take_epoch(epoch):
                return
            imu = imu_since(prop.t_c)
            if imu is not None and self.accel_A is not None:
                imu = imu.read_through(self.accel_A)
            self._caught_up = prop.advance_states(imu) if imu is not None else []
            self._prop, self._sigmas, self._anchor = prop, sigmas, anchor

    def add(self, stamp_ns: int, gyro, accel, epoch: int = 0) -> None:
        """One IMU sample (stamp in IMU time, ns; gyro [3] rad/s; accel [3] m/s^2) of buffer ``epoch``: propagate,
        and publish when due."""
        stamp_ns = int(stamp_ns)
        with self._lock:
            self._take_epoch(epoch)
            last = self._last_ns
            if last is not None and stamp_ns <= last:
                return
            self._last_ns = stamp_ns
            prop, anchor = self._prop, self._anchor
            if prop is None or prop.stopped:
                return
            if self.accel_A is not None:
                accel = self.accel_A @ np.asarray(accel, np.float64)
            # ``restart`` may have caught up through this sample already (it came in between)
            s = prop.step(stamp_ns * 1e-9, gyro, accel) or _state_at(self._caught_up, stamp_ns)
            if s is None:
                return
            sig = self._sigmas.at(s.tau)
            if self._too_uncertain(prop, sig.position_h, s.tau) or not self._due(stamp_ns, last):
                return
        dt = (stamp_ns - last) * 1e-9 if last is not None else 1e-9 * self.period_ns
        pose_cov, twist_cov = np.zeros(36), np.zeros(36)
        pose_diag, twist_diag = diagonals(sig, gyro_variance(self.options, dt))
        pose_cov[_DIAGONAL], twist_cov[_DIAGONAL] = pose_diag, twist_diag
        self._publish("odom_imu", self.messages.make(stamp_ns, s.p, s.q, s.v_body, s.omega, pose_cov, twist_cov),
                      stamp_ns)
        self.published += 1
        if self.flight is not None and anchor is not None:
            self.flight.propagated(anchor, stamp_ns, s.T_OB, np.array(s.v), np.array(s.omega),
                                   pose_cov.reshape(6, 6), twist_cov.reshape(6, 6))

    def _take_epoch(self, epoch: int) -> bool:
        """Move to ``epoch`` when it is newer (time went back: everything is forgotten); False when it is older."""
        if epoch > self._epoch:
            self._epoch, self._prop, self._next_ns, self._last_ns = epoch, None, None, None
        return epoch == self._epoch

    def _too_uncertain(self, prop: ImuPropagator, sigma: float, tau: float) -> bool:
        """Whether the newest state's horizontal position 1-sigma (``sigma`` m, ``tau`` s after the chained frame)
        exceeds ``imu_odom_max_sigma``; then the propagation stops, saying so."""
        if self.max_sigma <= 0 or sigma <= self.max_sigma:
            return False
        prop.stopped = (f"position 1-sigma {sigma:.2f} m > imu_odom_max_sigma {self.max_sigma:g} m, {tau:.1f} s after "
                        "the last chained frame")
        return True

    def _due(self, stamp_ns: int, last_ns: int | None) -> bool:
        """Whether the sample at ``stamp_ns`` is published: the first sample within half a sample interval of the
        due stamp (stamps jitter), the due stamps ``period_ns`` apart (re-anchored after a pause)."""
        half = (stamp_ns - last_ns) // 2 if last_ns is not None else 0
        if self._next_ns is not None and stamp_ns < self._next_ns - half:
            return False
        nxt = (self._next_ns or stamp_ns) + self.period_ns
        self._next_ns = nxt if nxt > stamp_ns else stamp_ns + self.period_ns
        return True


def _state_at(states: list[ImuState], stamp_ns: int) -> ImuState | None:
    """The state of ``states`` (in time order) at the sample stamped ``stamp_ns`` (ns; within a microsecond), or
    None."""
    t = stamp_ns * 1e-9
    k = bisect.bisect_left(states, t - 1e-6, key=lambda s: s.t)
    return states[k] if k < len(states) and abs(states[k].t - t) <= 1e-6 else None
