"""Odometry for a flight controller, beside ``~/odom`` and ``~/odom/imu``: ``px4_msgs/VehicleOdometry`` for PX4's EKF2
over uXRCE-DDS (``px4_odom``) and ``nav_msgs/Odometry`` for MAVROS's odometry plugin (``mavros_odom``), which sends it
to PX4 or ArduPilot as MAVLink ODOMETRY. How to set up the flight stack: docs/node.md, "Feeding PX4 / ArduPilot".

What is sent when. Nothing before the first chained clip (the first claimed scale, or the first window scale within
``odom_max_scale_sigma``: ``chain.OdomChain.places_unclaimed``). With ``flight_odom_source`` imu
(the default) one sample per ``~/odom/imu`` message: the same propagated state, at up to ``imu_odom_rate``, stopping
and resuming with it (``imu_odom_max_sigma``); with ``clip`` one per ``~/odom`` (the chained clip's last frame).

Frames (``vi3_ros.flight_frames``). PX4: position in the local frame (odom with the ENU -> NED axis swap; PX4's
``POSE_FRAME_FRD``: z down, a constant arbitrary heading, because odom's yaw is the first clip's, not north's), ``q``
the vehicle's FRD body frame (``frd_axes``) in it, velocity and angular rate in the FRD body frame
(``VELOCITY_FRAME_BODY_FRD``). MAVROS: ``odom_frame`` -> ``vehicle_frame`` (the vehicle's FLU axes, origin the IMU's),
twist in ``vehicle_frame``, as the plugin expects before it turns them into NED / FRD itself.

Variances, diagonal. ``clip``: ``~/odom``'s covariance diagonal (relative to the odom segment's first frame; yaw
``ODOM_YAW_SIGMA``). ``imu``: that of the chained clip the state was propagated from, plus what ``~/odom/imu``'s
covariance grew by since that clip's frame (``Anchor.propagated``), so the two streams agree at it and the variances
grow with the time since. PX4's position variance is that diagonal on the NED axes; its orientation and velocity
variances the diagonals of the attitude and velocity covariances expressed in the FRD body frame, as PX4 documents
them (an odom yaw variance of pi^2 lands on the body axis nearest the vertical).

Resets. A new odom segment (``odom_segment``: a bridge too uncertain to place a clip, a restarted window, time going
back) restarts the frame's origin. PX4's ``reset_counter`` is the segment's number (mod 256): it increments exactly at a
new segment, and EKF2 resets to the next sample instead of seeing a jump. MAVROS's odometry plugin has no reset counter
(it sends MAVLink's as 0), so the MAVROS stream pauses ``MAVROS_RESET_PAUSE_S`` of measurement time at a new segment,
longer than PX4's external-vision timeout (0.4 s), after which PX4 resets its position to the next sample.

``quality`` (PX4's EKF2_EV_QMIN compares it): ``scale_quality`` of the chained clip's relative scale sigma (1 for a
clip chained without a claim, its sigma being above ``max_scale_sigma``).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters.poses import odometry
from msg_adapters.px4 import POSE_FRAME_FRD, VELOCITY_FRAME_BODY_FRD, Px4Odometry, vehicle_odometry
from msg_adapters.types import MessageTypes
from vi3_core.errors import DataError
from vi3_core.online import ClipOutcome
from vi3_core.so3 import R_to_quat, make_T
from vi3_ros.flight_frames import FLU_FROM_FRD, NED_FROM_ENU, frd_rotation
from vi3_ros.settings import Settings

#: s of measurement time the MAVROS stream pauses at a new odom segment (PX4 drops external vision after 0.4 s
#: without samples and resets its position to the next one; MAVROS cannot forward a reset counter).
MAVROS_RESET_PAUSE_S = 1.0
_NED_AXES = [1, 0, 2]  # odom (x, y, z) variances on the NED axes


def scale_quality(rel_sigma: float, max_scale_sigma: float) -> int:
    """PX4's / MAVLink's quality (1 worst, 100 best) of a scale whose relative 1-sigma is ``rel_sigma``:
    100 (1 - rel_sigma / max_scale_sigma), rounded, at least 1 for a claimed scale (0 is PX4's "unknown"), 1 when the
    sigma is not finite."""
    q = 100.0 * (1.0 - rel_sigma / max_scale_sigma)
    return int(np.clip(np.rint(q), 1, 100)) if np.isfinite(q) else 1


@dataclass(frozen=True)
class Anchor:
    """What a chained clip fixes for the flight odometry until the next one: its odom ``segment`` (0: the first),
    ``quality`` (``scale_quality``), the diagonal variances of ``~/odom`` at its last frame (``pose_var`` [6]: x, y, z
    m^2 and rot x, y, z rad^2 about odom's axes; ``twist_var`` [6]: velocity m^2/s^2 and angular rate rad^2/s^2 on the
    body axes) and those of ``~/odom/imu``'s covariance at that frame (tau = 0: ``zero_pose_var``,
    ``zero_twist_var``), from which a propagation's growth is counted."""

    segment: int
    quality: int
    pose_var: np.ndarray
    twist_var: np.ndarray
    zero_pose_var: np.ndarray
    zero_twist_var: np.ndarray

    def propagated(self, pose_cov: np.ndarray, twist_cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(pose_var [6], twist_var [6]) of a state propagated from this anchor whose ``~/odom/imu`` covariances are
        ``pose_cov`` and ``twist_cov`` [6,6]: the anchor's, plus the growth since tau = 0."""
        return (self.pose_var + np.diag(pose_cov) - self.zero_pose_var,
                self.twist_var + np.diag(twist_cov) - self.zero_twist_var)


@dataclass(frozen=True)
class FlightSample:
    """One odometry sample for a flight controller, in the node's frames: ``stamp_ns`` the measurement time (IMU
    clock, ns); ``T_OB`` [4,4] the body (IMU) pose in odom, m; ``v_O`` [3] m/s in odom; ``omega_B`` [3] rad/s on the
    body axes; ``pose_var`` [6] and ``twist_var`` [6] as ``Anchor``'s; the anchor's ``segment`` and ``quality``."""

    stamp_ns: int
    T_OB: np.ndarray
    v_O: np.ndarray
    omega_B: np.ndarray
    pose_var: np.ndarray
    twist_var: np.ndarray
    segment: int
    quality: int


def px4_odometry(s: FlightSample, *, R_FRD_B: np.ndarray, timestamp_us: int) -> Px4Odometry:
    """``s`` in PX4's frames (module docstring) with the vehicle's FRD axes ``R_FRD_B`` [3,3] (body -> FRD); published
    at ``timestamp_us``."""
    R_FB_O = R_FRD_B @ s.T_OB[:3, :3].T  # odom -> FRD body
    q = R_to_quat(NED_FROM_ENU @ R_FB_O.T)  # FRD body -> the local frame, (x, y, z, w)
    return Px4Odometry(timestamp_us=int(timestamp_us), timestamp_sample_us=round(s.stamp_ns / 1000),
                       pose_frame=POSE_FRAME_FRD, position=NED_FROM_ENU @ s.T_OB[:3, 3], q=np.roll(q, 1),
                       velocity_frame=VELOCITY_FRAME_BODY_FRD, velocity=R_FB_O @ s.v_O,
                       angular_velocity=R_FRD_B @ s.omega_B, position_variance=s.pose_var[_NED_AXES],
                       orientation_variance=R_FB_O**2 @ s.pose_var[3:], velocity_variance=R_FRD_B**2 @ s.twist_var[:3],
                       reset_counter=s.segment % 256, quality=s.quality)


def mavros_odometry(s: FlightSample, *, R_FRD_B: np.ndarray, frame_id: str, child_frame_id: str,
                    types: MessageTypes) -> Any:
    """``s`` as the ``nav_msgs/Odometry`` MAVROS's odometry plugin takes: the pose of the vehicle's FLU frame
    ``child_frame_id`` (origin the IMU's) in ``frame_id`` (odom) with the pose covariance on odom's axes, the twist and
    its covariance in the FLU frame; stamped with the measurement time."""
    R_VB = FLU_FROM_FRD @ R_FRD_B  # body -> vehicle FLU (a signed permutation: variances map by its squares)
    R_OV = s.T_OB[:3, :3] @ R_VB.T
    twist_var = np.concatenate([R_VB**2 @ s.twist_var[:3], R_VB**2 @ s.twist_var[3:]])
    return odometry(make_T(R_OV, s.T_OB[:3, 3]), R_OV.T @ s.v_O, R_VB @ s.omega_B, stamp_ns=s.stamp_ns,
                    frame_id=frame_id, child_frame_id=child_frame_id, types=types, pose_cov=np.diag(s.pose_var),
                    twist_cov=np.diag(twist_var))


class FlightOdometry:
    """The flight controllers' odometry of one stream (``settings.flight``). ``anchor`` makes a chained clip's Anchor
    (worker thread); ``chained`` (worker thread) and ``propagated`` (the thread that feeds the IMU) each publish, when
    theirs is the ``flight_odom_source``, ``px4_odom`` and / or ``mavros_odom`` through ``publish(key, msg,
    stamp_ns)``; only the source's thread sends. ``clock``: ns of PX4's ``timestamp`` (the node's clock; None: the
    measurement time, as in replay). ``sent``: messages per key. A combination of settings it cannot run with raises
    DataError naming the parameters."""

    def __init__(self, settings: Settings, *, types: MessageTypes, publish: Callable[[str, Any, int], None],
                 clock: Callable[[], int] | None = None) -> None:
        fl = settings.flight
        self.R_FRD_B = frd_rotation(fl.frd_axes)
        if not settings.stream.online:
            raise DataError("parameters: px4_odom and mavros_odom need online (they send the chained odometry)")
        if fl.flight_odom_source == "imu" and settings.outputs.imu_odom_rate <= 0:
            raise DataError("parameters: flight_odom_source imu needs imu_odom_rate > 0 (or flight_odom_source clip)")
        if fl.mavros_odom and fl.vehicle_frame == settings.frames.base_frame \
                and not np.array_equal(self.R_FRD_B, FLU_FROM_FRD):
            raise DataError(f"parameters: vehicle_frame {fl.vehicle_frame!r} (FLU) is base_frame, whose axes frd_axes "
                            f"{fl.frd_axes!r} says are not FLU: name base_frame after the IMU (e.g. imu0)")
        self.source = fl.flight_odom_source
        self.keys = list(fl.outputs_on)
        self.frame_id, self.child_frame_id = settings.frames.odom_frame, fl.vehicle_frame
        self.max_scale_sigma = settings.init.max_scale_sigma
        self.types, self._publish, self._clock = types, publish, clock
        self._segment: int | None = None  # the segment of the last sample
        self._held_from: int | None = None  # ns: the first sample of a new segment while the MAVROS stream pauses
        self.sent: Counter[str] = Counter()

    def anchor(self, outcome: ClipOutcome, *, pose_cov: np.ndarray, twist_cov: np.ndarray,
               zero: tuple[np.ndarray, np.ndarray]) -> Anchor:
        """The Anchor of a chained clip's ``outcome`` whose ``~/odom`` covariances are ``pose_cov``, ``twist_cov``
        [6,6] and ``~/odom/imu``'s at its last frame ``zero`` (pose, twist [6,6])."""
        init = outcome.init
        rel = init.fit.scale_rel_sigma if init.fit is not None else init.scale_sigma / init.scale
        return Anchor(outcome.segment, scale_quality(rel, self.max_scale_sigma), np.diag(pose_cov).copy(),
                      np.diag(twist_cov).copy(), np.diag(zero[0]).copy(), np.diag(zero[1]).copy())

    def chained(self, anchor: Anchor, t: float, T_OB: np.ndarray, v_O: np.ndarray, omega_B: np.ndarray) -> None:
        """The chained state at its last frame (``t`` s, IMU clock; pose [4,4], velocity [3] in odom, rate [3] in the
        body frame) with ``anchor``'s variances: sent with ``flight_odom_source`` clip."""
        if self.source == "clip":
            self._send(FlightSample(round(t * 1e9), T_OB, v_O, omega_B, anchor.pose_var, anchor.twist_var,
                                    anchor.segment, anchor.quality))

    def propagated(self, anchor: Anchor, stamp_ns: int, T_OB: np.ndarray, v_O: np.ndarray, omega_B: np.ndarray,
                   pose_cov: np.ndarray, twist_cov: np.ndarray) -> None:
        """A state propagated from ``anchor``'s clip, as ``~/odom/imu`` publishes it (sample stamp, ns; pose, velocity
        in odom, rate in the body frame; its covariances [6,6]): sent with ``flight_odom_source`` imu."""
        if self.source == "imu":
            self._send(FlightSample(int(stamp_ns), T_OB, v_O, omega_B, *anchor.propagated(pose_cov, twist_cov),
                                    anchor.segment, anchor.quality))

    def _send(self, s: FlightSample) -> None:
        mavros_due = self._mavros_due(s)
        for key in self.keys:
            if key == "px4_odom":
                now = self._clock() if self._clock is not None else s.stamp_ns
                msg = vehicle_odometry(px4_odometry(s, R_FRD_B=self.R_FRD_B, timestamp_us=round(now / 1000)),
                                       types=self.types)
            elif mavros_due:
                msg = mavros_odometry(s, R_FRD_B=self.R_FRD_B, frame_id=self.frame_id,
                                      child_frame_id=self.child_frame_id, types=self.types)
            else:
                continue
            self._publish(key, msg, s.stamp_ns)
            self.sent[key] += 1

    def _mavros_due(self, s: FlightSample) -> bool:
        """False while the MAVROS stream pauses: from the first sample of a new segment for MAVROS_RESET_PAUSE_S of
        measurement time (the first segment starts at once)."""
        if self._segment is not None and s.segment != self._segment:
            self._held_from = s.stamp_ns
        self._segment = s.segment
        if self._held_from is not None and s.stamp_ns - self._held_from >= MAVROS_RESET_PAUSE_S * 1e9:
            self._held_from = None
        return self._held_from is None


__all__ = ["MAVROS_RESET_PAUSE_S", "Anchor", "FlightOdometry", "FlightSample", "mavros_odometry", "px4_odometry",
           "scale_quality"]
