"""PX4's ``px4_msgs/msg/VehicleOdometry`` (the uXRCE-DDS topic ``/fmu/in/vehicle_visual_odometry``) <-> ``Px4Odometry``.

``DEFINITION`` is the message's field list written from PX4's message reference (docs.px4.io, "VehicleOdometry (UORB
message)", PX4 v1.14 to v1.18, the layout px4_msgs' branches of those releases generate): the fields' names, types and
order are the wire format (CDR) that PX4's uXRCE-DDS client reads; constants are not on the wire. It is registered with
a rosbags typestore (``register``) so that replay writes the message into an MCAP without px4_msgs installed; the node
uses px4_msgs' own class.

PX4's conventions (the same reference): ``timestamp`` and ``timestamp_sample`` in microseconds (set on the ROS side
with the clock the uXRCE-DDS agent synchronises with PX4's); ``position`` in metres in the frame ``pose_frame`` names;
``q`` (w, x, y, z) the rotation from the FRD body frame to that frame; ``velocity`` in ``velocity_frame``;
``angular_velocity`` in the FRD body frame; per-axis variances; NaN marks a field invalid.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters.errors import MalformedMessage
from msg_adapters.fields import float_array, uint_field
from msg_adapters.types import MessageTypes

NAME = "px4_msgs/msg/VehicleOdometry"
#: The frame enums, named POSE_FRAME_<key> and VELOCITY_FRAME_<key> in the message. NED: aligned with true north; FRD:
#: a constant, arbitrary heading offset from north, z down; BODY_FRD: the vehicle's forward-right-down body axes.
POSE_FRAMES = {"UNKNOWN": 0, "NED": 1, "FRD": 2}
VELOCITY_FRAMES = {"UNKNOWN": 0, "NED": 1, "FRD": 2, "BODY_FRD": 3}
POSE_FRAME_FRD, VELOCITY_FRAME_BODY_FRD = POSE_FRAMES["FRD"], VELOCITY_FRAMES["BODY_FRD"]


def _enum(name: str, values: dict[str, int]) -> list[str]:
    return [f"uint8 {name}_{key}={value}" for key, value in values.items()]


DEFINITION = "\n".join([
    "uint64 timestamp", "uint64 timestamp_sample",
    *_enum("POSE_FRAME", POSE_FRAMES), "uint8 pose_frame", "float32[3] position", "float32[4] q",
    *_enum("VELOCITY_FRAME", VELOCITY_FRAMES), "uint8 velocity_frame", "float32[3] velocity",
    "float32[3] angular_velocity", "float32[3] position_variance", "float32[3] orientation_variance",
    "float32[3] velocity_variance", "uint8 reset_counter", "int8 quality", ""])

_VECTORS = {"position": 3, "q": 4, "velocity": 3, "angular_velocity": 3, "position_variance": 3,
            "orientation_variance": 3, "velocity_variance": 3}


@dataclass(frozen=True)
class Px4Odometry:
    """The content of one VehicleOdometry, in PX4's frames and units: timestamps in microseconds (publication and
    measurement); ``pose_frame`` / ``velocity_frame`` (POSE_FRAMES, VELOCITY_FRAMES); position [3] m; q [4] (w, x, y,
    z), FRD body to ``pose_frame``; velocity [3] m/s in ``velocity_frame``; angular_velocity [3] rad/s, FRD body;
    position_variance [3] m^2, orientation_variance [3] rad^2, velocity_variance [3] m^2/s^2; reset_counter (0-255,
    wraps); quality (int8: 0 unknown, 1-100 worst to best)."""

    timestamp_us: int
    timestamp_sample_us: int
    pose_frame: int
    position: np.ndarray
    q: np.ndarray
    velocity_frame: int
    velocity: np.ndarray
    angular_velocity: np.ndarray
    position_variance: np.ndarray
    orientation_variance: np.ndarray
    velocity_variance: np.ndarray
    reset_counter: int
    quality: int


def register(typestore: Any) -> None:
    """Add VehicleOdometry to a rosbags ``typestore`` (nothing when it knows the type already)."""
    from rosbags.typesys import get_types_from_msg

    if NAME not in typestore.types:
        typestore.register(get_types_from_msg(DEFINITION, NAME))


def vehicle_odometry(odo: Px4Odometry, *, types: MessageTypes) -> Any:
    """``Px4Odometry`` -> ``px4_msgs/msg/VehicleOdometry``; MalformedMessage for a vector of the wrong size or an
    integer field out of its range."""
    vectors = {}
    for name, size in _VECTORS.items():
        v = np.asarray(getattr(odo, name), dtype=np.float32)
        if v.shape != (size,):
            raise MalformedMessage(f"VehicleOdometry {name} has shape {v.shape}, expected [{size}]")
        vectors[name] = v
    if not -128 <= int(odo.quality) <= 127:
        raise MalformedMessage(f"VehicleOdometry quality {odo.quality} is outside int8")
    return types.make(NAME, timestamp=uint_field(odo.timestamp_us, "timestamp", bits=64),
                      timestamp_sample=uint_field(odo.timestamp_sample_us, "timestamp_sample", bits=64),
                      pose_frame=uint_field(odo.pose_frame, "pose_frame", bits=8),
                      velocity_frame=uint_field(odo.velocity_frame, "velocity_frame", bits=8),
                      reset_counter=uint_field(odo.reset_counter, "reset_counter", bits=8),
                      quality=int(odo.quality), **vectors)


def vehicle_odometry_to_px4(msg: Any) -> Px4Odometry:
    """``px4_msgs/msg/VehicleOdometry`` (rclpy or rosbags) -> ``Px4Odometry`` (vectors as float64)."""
    return Px4Odometry(
        timestamp_us=uint_field(msg.timestamp, "timestamp", bits=64),
        timestamp_sample_us=uint_field(msg.timestamp_sample, "timestamp_sample", bits=64),
        pose_frame=uint_field(msg.pose_frame, "pose_frame", bits=8),
        velocity_frame=uint_field(msg.velocity_frame, "velocity_frame", bits=8),
        reset_counter=uint_field(msg.reset_counter, "reset_counter", bits=8), quality=int(msg.quality),
        **{name: float_array(getattr(msg, name), name, size=size) for name, size in _VECTORS.items()})


__all__ = ["DEFINITION", "NAME", "POSE_FRAMES", "POSE_FRAME_FRD", "VELOCITY_FRAMES", "VELOCITY_FRAME_BODY_FRD",
           "Px4Odometry", "register", "vehicle_odometry", "vehicle_odometry_to_px4"]
