"""The odometry for a flight controller without ROS (``vi3_ros.flight_odom``, ``vi3_ros.flight_frames``): the
ENU/FLU -> NED/FRD conversion with known signs, the variances mapped from the estimator's covariances, the growth
since the chained clip, reset counting, the MAVROS pause at a new segment, quality, and the settings refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msg_adapters.poses import odometry_to_numpy
from msg_adapters.px4 import POSE_FRAME_FRD, VELOCITY_FRAME_BODY_FRD, vehicle_odometry_to_px4
from msg_adapters.types import jazzy_types
from vi3_core import so3
from vi3_core.errors import DataError
from vi3_core.online import OdomState
from vi3_core.sim.trajectory import R_MOUNT
from vi3_ros.flight_frames import FLU_FROM_FRD, NED_FROM_ENU, frd_rotation
from vi3_ros.flight_odom import (
    MAVROS_RESET_PAUSE_S,
    Anchor,
    FlightOdometry,
    FlightSample,
    mavros_odometry,
    px4_odometry,
    scale_quality,
)
from vi3_ros.imu_odom import covariances, sigma_model, start_covariances
from vi3_ros.params import load_yaml, resolve

TYPES = jazzy_types()
EUROC = "+z,+y,-x"  # EuRoC's IMU: x up, y right, z forward
R_FLU_EUROC = R_MOUNT  # the simulator's mount: columns are the IMU's axes in the vehicle's FLU frame
FLU_MOUNT = np.eye(3)  # an IMU mounted FLU


def _yaw(deg: float) -> np.ndarray:
    """R_OV of a level vehicle (FLU) whose nose points ``deg`` counter-clockwise from odom's x (east)."""
    return so3.exp(np.array([0.0, 0.0, np.radians(deg)]))


def _sample(R_OV: np.ndarray, *, mount: np.ndarray = FLU_MOUNT, p=(0.0, 0.0, 0.0), v_O=(0.0, 0.0, 0.0),
            omega_V=(0.0, 0.0, 0.0), pose_var=(1.0, 2.0, 3.0, 4.0, 5.0, 6.0), twist_var=(7.0, 8.0, 9.0, 1.0, 2.0, 3.0),
            segment: int = 0, stamp_ns: int = 1_700_000_000_123_456_789) -> FlightSample:
    """A sample of a vehicle with attitude ``R_OV`` (FLU) carrying an IMU whose axes in FLU are ``mount``'s columns;
    ``omega_V`` rad/s on the FLU axes, the twist variances on the IMU's axes."""
    R_OB = R_OV @ mount
    return FlightSample(stamp_ns, so3.make_T(R_OB, np.asarray(p, float)), np.asarray(v_O, float),
                        mount.T @ np.asarray(omega_V, float), np.asarray(pose_var, float),
                        np.asarray(twist_var, float), segment, 42)


def test_frd_axes_name_the_vehicle_in_the_body_frame():
    np.testing.assert_array_equal(frd_rotation("+x,-y,-z"), FLU_FROM_FRD)  # an FLU IMU
    np.testing.assert_array_equal(frd_rotation(EUROC), FLU_FROM_FRD @ R_FLU_EUROC)  # the simulator's EuRoC mount
    np.testing.assert_array_equal(frd_rotation(" +X, +Y, +Z "), np.eye(3))
    for bad in ("+x,+y", "x,y,z", "+x,+x,+z", "+x,+y,-z", "+w,+y,+z"):
        with pytest.raises(ValueError, match="frd_axes"):
            frd_rotation(bad)
    with pytest.raises(DataError, match="frd_axes '\\+x,\\+y,-z'.*right-handed"):
        resolve({"frd_axes": "+x,+y,-z"})


@pytest.mark.parametrize("frd_axes, mount", [("+x,-y,-z", FLU_MOUNT), (EUROC, R_FLU_EUROC)], ids=["flu", "euroc"])
def test_a_flight_north_east_up_gives_px4_the_right_signs(frd_axes, mount):
    """odom as ENU (x east, y north): 1 m north, 2 m east, 3 m up -> NED (1, 2, -3); a level vehicle heading north is
    PX4's identity attitude, heading east a yaw of +90 deg (clockwise seen from above), pitched nose up a positive
    pitch; 1 m/s forward and a turn to the left are body FRD (1, 0, 0) and a negative yaw rate. The IMU's mount is
    undone (the EuRoC IMU gives the same message)."""
    R_FRD_B = frd_rotation(frd_axes)
    north = _yaw(90.0)
    odo = px4_odometry(_sample(north, mount=mount, p=(2.0, 1.0, 3.0), v_O=north @ [1.0, 0.0, 0.0],
                               omega_V=(0.0, 0.0, 0.3)), R_FRD_B=R_FRD_B, timestamp_us=5)
    np.testing.assert_allclose(odo.position, [1.0, 2.0, -3.0])
    np.testing.assert_allclose(odo.q, [1.0, 0.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(odo.velocity, [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(odo.angular_velocity, [0.0, 0.0, -0.3], atol=1e-12)
    assert (odo.pose_frame, odo.velocity_frame) == (POSE_FRAME_FRD, VELOCITY_FRAME_BODY_FRD)
    assert (odo.timestamp_us, odo.timestamp_sample_us) == (5, 1_700_000_000_123_457)  # microseconds, rounded
    east = px4_odometry(_sample(_yaw(0.0), mount=mount), R_FRD_B=R_FRD_B, timestamp_us=0)
    np.testing.assert_allclose(east.q, [np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)], atol=1e-12)
    nose_up = north @ so3.exp(np.array([0.0, -0.2, 0.0]))  # FLU: a negative turn about y lifts the nose
    pitched = px4_odometry(_sample(nose_up, mount=mount), R_FRD_B=R_FRD_B, timestamp_us=0)
    np.testing.assert_allclose(pitched.q, [np.cos(0.1), 0.0, np.sin(0.1), 0.0], atol=1e-12)


def test_px4_variances_are_the_covariance_diagonals_on_its_axes():
    """Position: odom's (x, y, z) variances on NED's axes (y, x, z). Attitude and velocity: the diagonal covariances
    expressed in the FRD body frame: for a vehicle heading north, FRD's (forward, right, down) are odom's (y, x, -z);
    heading north-east, tilt about the two level axes mixes evenly, yaw stays on the down axis."""
    odo = px4_odometry(_sample(_yaw(90.0), mount=R_FLU_EUROC), R_FRD_B=frd_rotation(EUROC), timestamp_us=0)
    np.testing.assert_allclose(odo.position_variance, [2.0, 1.0, 3.0])
    np.testing.assert_allclose(odo.orientation_variance, [5.0, 4.0, 6.0], atol=1e-12)
    np.testing.assert_allclose(odo.velocity_variance, [9.0, 8.0, 7.0])  # IMU (x up, y right, z forward)
    diagonal = px4_odometry(_sample(_yaw(45.0)), R_FRD_B=frd_rotation("+x,-y,-z"), timestamp_us=0)
    np.testing.assert_allclose(diagonal.orientation_variance, [4.5, 4.5, 6.0], atol=1e-12)
    np.testing.assert_allclose(diagonal.position_variance, [2.0, 1.0, 3.0])


def test_mavros_gets_the_vehicles_flu_frame_in_odom():
    """MAVROS's plugin takes odom (ENU) -> base_link (FLU) and converts to NED / FRD itself: the vehicle's FLU pose
    whatever the IMU's mount, the pose covariance on odom's axes, the twist and its covariance on the FLU axes."""
    north = _yaw(90.0)
    s = _sample(north, mount=R_FLU_EUROC, p=(2.0, 1.0, 3.0), v_O=north @ [1.0, 0.5, 0.0], omega_V=(0.1, 0.2, 0.3))
    msg = mavros_odometry(s, R_FRD_B=frd_rotation(EUROC), frame_id="odom", child_frame_id="base_link", types=TYPES)
    T, v, w, pose_cov, twist_cov = odometry_to_numpy(msg)
    assert (msg.header.frame_id, msg.child_frame_id) == ("odom", "base_link")
    np.testing.assert_allclose(T, so3.make_T(north, [2.0, 1.0, 3.0]), atol=1e-12)
    np.testing.assert_allclose(v, [1.0, 0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(w, [0.1, 0.2, 0.3], atol=1e-12)
    np.testing.assert_allclose(np.diag(pose_cov), [1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    np.testing.assert_allclose(np.diag(twist_cov), [9.0, 8.0, 7.0, 3.0, 2.0, 1.0])  # FLU = IMU (z, -y, x)


def test_the_growth_since_the_chained_clip_is_added_to_its_variances():
    """At tau = 0 the IMU-rate variances are ~/odom's; later, position grows by the propagation's, tilt and velocity
    by what they grew beyond their start, yaw stays pi^2 plus the gyro's."""
    options = resolve().init
    state = OdomState(np.array([0.0]), np.eye(4)[None], np.zeros((1, 3)), np.zeros(3), np.zeros(3), 0.02, 0.01)
    zero = start_covariances(state, options=options, sample_dt=0.005)
    chained = (np.diag([0.04, 0.05, 0.06, 1e-4, 1e-4, np.pi**2]), np.diag([4e-4] * 3 + [2e-4] * 3))
    anchor = Anchor(3, 80, np.diag(chained[0]), np.diag(chained[1]), np.diag(zero[0]), np.diag(zero[1]))

    def at(tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        pose, twist = (c[0] for c in covariances(sigma_model(state, options).at(np.array([tau])), options, 0.005))
        return (*anchor.propagated(pose, twist), np.diag(pose), np.diag(twist))

    pose0, twist0, _, _ = at(0.0)
    np.testing.assert_allclose(pose0, anchor.pose_var)
    np.testing.assert_allclose(twist0, anchor.twist_var)
    pose, twist, imu_pose, imu_twist = at(2.0)
    np.testing.assert_allclose(pose[:3], anchor.pose_var[:3] + imu_pose[:3])
    np.testing.assert_allclose(pose[3:5], imu_pose[3:5] - zero[0][3, 3] + 1e-4)
    np.testing.assert_allclose(pose[5], np.pi**2 + imu_pose[5])
    np.testing.assert_allclose(twist[:3], imu_twist[:3] - 0.02**2 + 4e-4)
    assert np.all(pose > pose0) and np.all(twist[:3] > twist0[:3])


def test_quality_follows_the_scale_sigma():
    assert [scale_quality(s, 0.04) for s in (0.0, 0.01, 0.02, 0.0399, 0.04, 0.2)] == [100, 75, 50, 1, 1, 1]
    assert scale_quality(float("nan"), 0.04) == 1


def _flight(**params) -> tuple[FlightOdometry, list]:
    sent: list = []
    settings = resolve({"px4_odom": True, "mavros_odom": True, "frd_axes": EUROC, "base_frame": "imu0", **params})
    return FlightOdometry(settings, types=TYPES, publish=lambda key, msg, stamp: sent.append((key, msg, stamp))), sent


def _anchor(segment: int) -> Anchor:
    return Anchor(segment, 60, np.full(6, 0.01), np.full(6, 0.001), np.zeros(6), np.zeros(6))


def test_reset_counter_counts_segments_and_mavros_pauses_at_a_new_one():
    """PX4 is told of a new odom segment by its reset_counter, from its first sample on; MAVROS cannot carry one, so
    its stream pauses MAVROS_RESET_PAUSE_S of measurement time from the new segment's first sample."""
    flight, sent = _flight()
    T, zero, cov = np.eye(4), np.zeros(3), np.eye(6) * 1e-3
    stamps = np.arange(0, 3_000_000_000, 100_000_000)  # 10 Hz for 3 s
    for t in stamps:
        segment = 0 if t < 1_000_000_000 else 1 if t < 2_500_000_000 else 2
        flight.propagated(_anchor(segment), int(t), T, zero, zero, cov, cov)
    px4 = [(stamp, vehicle_odometry_to_px4(m).reset_counter) for key, m, stamp in sent if key == "px4_odom"]
    mavros = [stamp for key, _, stamp in sent if key == "mavros_odom"]
    assert [s for s, _ in px4] == stamps.tolist()
    assert [c for s, c in px4] == [0] * 10 + [1] * 15 + [2] * 5
    pause = MAVROS_RESET_PAUSE_S * 1e9
    expected = [t for t in stamps if t < 1e9 or 1e9 + pause <= t < 2.5e9 or t >= 2.5e9 + pause]
    assert mavros == expected
    assert flight.sent == {"px4_odom": 30, "mavros_odom": len(expected)}
    flight.propagated(_anchor(256), int(stamps[-1]) + 1, T, zero, zero, cov, cov)
    assert vehicle_odometry_to_px4(sent[-1][1]).reset_counter == 0  # uint8: the 257th segment wraps


def test_each_source_sends_from_its_own_stream():
    """flight_odom_source imu: only the propagated states; clip: only the chained ones, stamped with the chained
    frame's IMU time, with ~/odom's variances."""
    T, zero, cov = np.eye(4), np.zeros(3), np.eye(6) * 1e-3
    imu, sent = _flight(mavros_odom=False)
    imu.chained(_anchor(0), 1.5, T, zero, zero)
    imu.propagated(_anchor(0), 1_600_000_000, T, zero, zero, cov, cov)
    assert [stamp for _, _, stamp in sent] == [1_600_000_000]
    clip, sent = _flight(mavros_odom=False, flight_odom_source="clip")
    clip.propagated(_anchor(0), 1_600_000_000, T, zero, zero, cov, cov)
    clip.chained(_anchor(2), 1.5, T, zero, zero)
    (_, msg, stamp), = sent
    odo = vehicle_odometry_to_px4(msg)
    assert stamp == 1_500_000_000 and odo.timestamp_sample_us == 1_500_000 and odo.reset_counter == 2
    np.testing.assert_allclose(odo.position_variance, 0.01, rtol=1e-6)
    assert odo.quality == 60


@pytest.mark.parametrize("params, message", [
    ({"online": False}, "need online"),
    ({"imu_odom_rate": 0.0}, "flight_odom_source imu needs imu_odom_rate > 0"),
    ({"base_frame": "base_link"}, "vehicle_frame 'base_link' \\(FLU\\) is base_frame"),
])
def test_settings_a_flight_odometry_cannot_run_with_are_named(params, message):
    with pytest.raises(DataError, match=message):
        _flight(**params)


@pytest.mark.parametrize("params, message", [
    ({"px4_odom_topic": ""}, "px4_odom_topic '' is not a ROS topic name"),
    ({"mavros_odom_topic": "/mavros/odometry out"}, "mavros_odom_topic '/mavros/odometry out' is not a ROS topic"),
    ({"px4_odom_topic": "/fmu//in"}, "px4_odom_topic '/fmu//in' is not a ROS topic name"),
    ({"vehicle_frame": "/"}, "vehicle_frame is empty"),
])
def test_topics_and_frames_that_cannot_be_used_are_named_at_once(params, message):
    with pytest.raises(DataError, match=message):
        resolve(params)


def test_base_link_may_be_the_imu_when_it_is_flu_or_mavros_is_off():
    _flight(base_frame="base_link", mavros_odom=False)
    _flight(base_frame="base_link", frd_axes="+x,-y,-z")


def test_the_local_frame_swap_is_its_own_inverse():
    np.testing.assert_array_equal(NED_FROM_ENU @ NED_FROM_ENU, np.eye(3))
    np.testing.assert_array_equal(FLU_FROM_FRD @ FLU_FROM_FRD, np.eye(3))


def test_the_euroc_configuration_feeds_flight_controllers():
    """config/euroc.yaml: EuRoC's IMU mount as frd_axes, and ~/odom's child frame named after the IMU, so that MAVROS's
    base_link can be the vehicle's FLU frame."""
    params = load_yaml(Path(__file__).resolve().parents[2] / "config" / "euroc.yaml")
    settings = resolve({**params, "px4_odom": True, "mavros_odom": True})
    np.testing.assert_array_equal(frd_rotation(settings.flight.frd_axes), FLU_FROM_FRD @ R_FLU_EUROC)
    flight = FlightOdometry(settings, types=TYPES, publish=lambda *a: None)
    assert (flight.frame_id, flight.child_frame_id, settings.frames.base_frame) == ("odom", "base_link", "imu0")
