"""``sensor_msgs/Imu`` <-> ``ImuSample`` / ``vi3_core.types.ImuSamples``.

Angular velocity (rad/s) and linear acceleration (m/s^2, specific force) are in the message's frame, the
IMU body frame B. Orientation (x, y, z, w) is reported only when ``orientation_covariance[0] != -1`` (the
ROS convention for "no orientation"). Values are not judged here (NaN passes through): the initialiser
turns bad data into a status. Stamps and field layouts are checked: violations raise ``MalformedMessage``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters.errors import MalformedMessage
from msg_adapters.fields import float_array, vector_field
from msg_adapters.stamps import NS_PER_S, make_header, sec_to_ns, stamp_to_ns
from msg_adapters.types import MessageTypes
from vi3_core.types import ImuSamples

_NO_ORIENTATION = -1.0


@dataclass(frozen=True)
class ImuSample:
    """One IMU message: stamp as t float64 s and t_ns int ns (exact), gyro [3] rad/s, accel [3] m/s^2, orientation
    [4] (x, y, z, w) or None."""

    t: float
    t_ns: int
    gyro: np.ndarray
    accel: np.ndarray
    orientation: np.ndarray | None


def imu_to_sample(msg: Any) -> ImuSample:
    """``sensor_msgs/Imu`` -> ``ImuSample`` (orientation None when ``orientation_covariance[0] == -1``)."""
    for name in ("angular_velocity_covariance", "linear_acceleration_covariance"):
        float_array(getattr(msg, name), name, size=9)
    has_orientation = float_array(msg.orientation_covariance, "orientation_covariance", size=9)[0] != _NO_ORIENTATION
    ns = stamp_to_ns(getattr(getattr(msg, "header", None), "stamp", None), name="header.stamp")
    return ImuSample(t=ns / NS_PER_S, t_ns=ns,
                     gyro=vector_field(msg.angular_velocity, "angular_velocity"),
                     accel=vector_field(msg.linear_acceleration, "linear_acceleration"),
                     orientation=vector_field(msg.orientation, "orientation", "xyzw") if has_orientation else None)


def imus_to_samples(msgs: Iterable[Any]) -> ImuSamples:
    """IMU messages -> ``ImuSamples`` in message order; orientation rows NaN where absent, None if absent in all."""
    samples = [imu_to_sample(m) for m in msgs]
    if not samples:
        return ImuSamples(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))
    orientation = None
    if any(s.orientation is not None for s in samples):
        orientation = np.stack([np.full(4, np.nan) if s.orientation is None else s.orientation for s in samples])
    return ImuSamples(np.array([s.t for s in samples]), np.stack([s.gyro for s in samples]),
                      np.stack([s.accel for s in samples]), orientation)


def samples_to_imus(samples: ImuSamples, *, frame_id: str, types: MessageTypes,
                    stamps_ns: Sequence[int] | None = None) -> list[Any]:
    """``ImuSamples`` -> ``sensor_msgs/Imu`` messages (for writing bags).

    Stamps are ``samples.t`` rounded to the nearest ns, or the exact integer ``stamps_ns`` [M] when given (float
    seconds resolve only ~240 ns at today's epoch). Rows without orientation (no orientation array, or a NaN row)
    get ``orientation_covariance[0] = -1`` and a zero quaternion; gyro/accel covariances are all zero ("unknown"
    in ``sensor_msgs/Imu``).
    """
    n = len(samples)
    stamps = [sec_to_ns(t) for t in samples.t.tolist()] if stamps_ns is None else list(stamps_ns)
    if len(stamps) != n:
        raise MalformedMessage(f"stamps_ns has {len(stamps)} stamps for {n} IMU samples")
    ori = np.full((n, 4), np.nan) if samples.orientation is None else samples.orientation
    has_ori = np.isfinite(ori).all(axis=1)
    ori = np.where(has_ori[:, None], ori, 0.0)
    cov_known, cov_absent = np.zeros(9), np.zeros(9)
    cov_absent[0] = _NO_ORIENTATION
    vec3 = lambda v: types.make("geometry_msgs/msg/Vector3", x=v[0], y=v[1], z=v[2])
    return [types.make("sensor_msgs/msg/Imu",
                       header=make_header(stamp_ns=ns, frame_id=frame_id, types=types),
                       orientation=types.make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]),
                       orientation_covariance=(cov_known if known else cov_absent).copy(),
                       angular_velocity=vec3(g), angular_velocity_covariance=np.zeros(9),
                       linear_acceleration=vec3(a), linear_acceleration_covariance=np.zeros(9))
            for ns, g, a, q, known in zip(stamps, samples.gyro.tolist(), samples.accel.tolist(), ori.tolist(),
                                          has_ori.tolist())]
