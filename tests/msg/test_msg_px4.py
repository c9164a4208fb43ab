"""PX4's VehicleOdometry as ``msg_adapters.px4`` writes it: the CDR bytes PX4's uXRCE-DDS client reads (field order,
types, alignment, read back with ``struct`` independently of rosbags), the round trip, and the refused values."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from msg_adapters.errors import MalformedMessage
from msg_adapters.px4 import NAME, Px4Odometry, register, vehicle_odometry, vehicle_odometry_to_px4
from msg_adapters.types import jazzy_types

TYPES = jazzy_types()


def _odometry(**changes) -> Px4Odometry:
    fields = dict(timestamp_us=1_700_000_001_000_000, timestamp_sample_us=1_700_000_000_990_000, pose_frame=2,
                  position=np.array([1.5, -2.25, -3.0]), q=np.array([0.5, 0.5, -0.5, 0.5]), velocity_frame=3,
                  velocity=np.array([0.25, 0.5, -0.75]), angular_velocity=np.array([0.1, -0.2, 0.3]),
                  position_variance=np.array([0.01, 0.02, 0.03]), orientation_variance=np.array([1e-4, 2e-4, 9.87]),
                  velocity_variance=np.array([4e-4, 5e-4, 6e-4]), reset_counter=7, quality=-1)
    return Px4Odometry(**{**fields, **changes})


def test_cdr_bytes_are_px4s_layout():
    """Little-endian CDR after the 4-byte encapsulation header: two uint64, uint8 padded to 4, float32[3], float32[4],
    uint8 padded to 4, five float32[3], uint8, int8: 118 bytes."""
    odo = _odometry()
    raw = bytes(TYPES.typestore.serialize_cdr(vehicle_odometry(odo, types=TYPES), NAME))
    assert len(raw) == 118 and raw[:2] == b"\x00\x01"
    t, ts, pose_frame = struct.unpack_from("<QQB", raw, 4)
    floats = struct.unpack_from("<3f4f", raw, 24)
    velocity_frame = raw[52]
    rest = struct.unpack_from("<15f", raw, 56)
    reset, quality = struct.unpack_from("<Bb", raw, 116)
    assert (t, ts, pose_frame, velocity_frame, reset, quality) == (odo.timestamp_us, odo.timestamp_sample_us, 2, 3, 7,
                                                                   -1)
    np.testing.assert_allclose(floats, np.concatenate([odo.position, odo.q]), rtol=1e-7)
    np.testing.assert_allclose(rest, np.concatenate([odo.velocity, odo.angular_velocity, odo.position_variance,
                                                     odo.orientation_variance, odo.velocity_variance]), rtol=1e-6)


def test_round_trip_through_cdr():
    odo = _odometry()
    msg = vehicle_odometry(odo, types=TYPES)
    store = TYPES.typestore
    back = vehicle_odometry_to_px4(store.deserialize_cdr(store.serialize_cdr(msg, NAME), NAME))
    for name in ("timestamp_us", "timestamp_sample_us", "pose_frame", "velocity_frame", "reset_counter", "quality"):
        assert getattr(back, name) == getattr(odo, name), name
    for name in ("position", "q", "velocity", "angular_velocity", "position_variance", "orientation_variance",
                 "velocity_variance"):
        np.testing.assert_allclose(getattr(back, name), getattr(odo, name), rtol=1e-6, err_msg=name)


@pytest.mark.parametrize("changes, match", [
    ({"q": np.zeros(3)}, "q has shape \\(3,\\), expected \\[4\\]"),
    ({"reset_counter": 256}, "reset_counter = 256 is outside"),
    ({"quality": 128}, "quality 128 is outside int8"),
    ({"timestamp_us": -1}, "timestamp = -1 is outside"),
])
def test_values_px4_cannot_carry_are_refused(changes, match):
    with pytest.raises(MalformedMessage, match=match):
        vehicle_odometry(_odometry(**changes), types=TYPES)


def test_register_adds_the_definition_once_to_a_typestore():
    store = get_typestore(Stores.ROS2_JAZZY)
    assert NAME not in store.types
    register(store)
    register(store)
    assert store.generate_msgdef(NAME) == TYPES.typestore.generate_msgdef(NAME)
    assert "int8 quality" in store.generate_msgdef(NAME)[0]
