"""Every builder's message survives CDR with the rosbags Jazzy typestore and decodes to the same arrays."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from msg_adapters import builders
from msg_adapters.camera_info import calib_to_camera_info, camera_info_to_calib
from msg_adapters.errors import UnknownMessageType
from msg_adapters.image import depth_to_image, image_to_numpy, numpy_to_image
from msg_adapters.imu import imu_to_sample, imus_to_samples, samples_to_imus
from msg_adapters.stamps import ns_to_stamp, stamp_to_ns
from msg_adapters.types import full_name, jazzy_types
from vi3_core.sim.imu import imu_stamps, simulate_imu
from vi3_core.sim.trajectory import make_trajectory
from vi3_core.so3 import make_T
from vi3_ros.io.ros1 import noetic_typestore, ros1_types

TYPES = jazzy_types()
STAMP = 1403636579758555392


def cdr(msg):
    """Serialise and deserialise with the Jazzy typestore (the bytes a bag or a DDS peer would carry)."""
    raw = TYPES.typestore.serialize_cdr(msg, msg.__msgtype__)
    return TYPES.typestore.deserialize_cdr(raw, msg.__msgtype__)


def random_T(rng, n):
    return make_T(Rotation.random(n, random_state=rng).as_matrix(), rng.normal(size=(n, 3)) * 10)


@pytest.mark.parametrize(("encoding", "dtype", "channels"), [
    ("mono8", np.uint8, 1), ("8UC1", np.uint8, 1), ("mono16", np.uint16, 1), ("16UC1", np.uint16, 1),
    ("32FC1", np.float32, 1), ("rgb8", np.uint8, 3), ("bgr8", np.uint8, 3), ("8UC3", np.uint8, 3),
    ("rgba8", np.uint8, 4), ("bgra8", np.uint8, 4),
])
def test_image_round_trip(encoding, dtype, channels):
    rng = np.random.default_rng(1)
    shape = (5, 7) if channels == 1 else (5, 7, channels)
    if dtype is np.float32:
        arr = rng.normal(size=shape).astype(dtype)
    else:
        arr = rng.integers(0, np.iinfo(dtype).max, size=shape, endpoint=True).astype(dtype)
    msg = cdr(numpy_to_image(arr, encoding=encoding, stamp_ns=STAMP, frame_id="cam0", types=TYPES))
    assert (msg.encoding, msg.height, msg.width, msg.header.frame_id) == (encoding, 5, 7, "cam0")
    assert stamp_to_ns(msg.header.stamp) == STAMP
    out = image_to_numpy(msg)
    assert out.dtype == dtype and out.shape == shape
    np.testing.assert_array_equal(out, arr)
    built = numpy_to_image(arr, encoding=encoding, stamp_ns=STAMP, frame_id="cam0", types=TYPES)
    assert not np.shares_memory(built.data, arr)  # the message owns its pixels
    if encoding.startswith("bgr"):  # the wire holds B first: compare with OpenCV's own conversion
        wire = np.frombuffer(msg.data, dtype=np.uint8).reshape(5, 7, channels)
        code = cv2.COLOR_RGB2BGR if channels == 3 else cv2.COLOR_RGBA2BGRA
        np.testing.assert_array_equal(wire, cv2.cvtColor(arr, code))


def test_depth_image_is_32fc1_metres_with_nan_for_invalid():
    depth = np.array([[1.5, 0.0, -2.0], [np.inf, np.nan, 1e-3]])
    out = image_to_numpy(cdr(depth_to_image(depth, stamp_ns=STAMP, frame_id="cam0", types=TYPES)))
    assert out.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(out), [[False, True, True], [True, True, False]])
    np.testing.assert_allclose(out[~np.isnan(out)], [1.5, 1e-3], rtol=1e-7)


def test_imu_round_trip_with_partial_orientation():
    traj = make_trajectory("drone", seed=3)
    sim = simulate_imu(traj, imu_stamps(1403636579.0, 1403636579.5), with_orientation=True, seed=3)
    ori = sim.samples.orientation.copy()
    ori[[2, 5]] = np.nan  # two messages without orientation
    samples = type(sim.samples)(sim.samples.t, sim.samples.gyro, sim.samples.accel, ori)
    msgs = [cdr(m) for m in samples_to_imus(samples, frame_id="imu0", types=TYPES)]
    assert [m.orientation_covariance[0] for m in msgs[:6]] == [0, 0, -1, 0, 0, -1]
    back = imus_to_samples(msgs)
    np.testing.assert_array_equal(back.t, samples.t)  # float s -> nearest ns -> float s is exact here
    np.testing.assert_array_equal(back.gyro, samples.gyro)
    np.testing.assert_array_equal(back.accel, samples.accel)
    np.testing.assert_array_equal(back.orientation, ori)


def test_imu_sample_keeps_the_exact_stamp():
    ns = [STAMP + 1, STAMP + 5_000_003]
    samples = type(imus_to_samples([]))(np.array(ns) * 1e-9, np.zeros((2, 3)), np.zeros((2, 3)))
    got = [imu_to_sample(cdr(m)) for m in samples_to_imus(samples, frame_id="imu0", types=TYPES, stamps_ns=ns)]
    assert [s.t_ns for s in got] == ns and [s.t for s in got] == [n / 1e9 for n in ns]


def test_imu_without_orientation_gives_none():
    sim = simulate_imu(make_trajectory("drone", seed=4), imu_stamps(10.0, 10.1), seed=4)
    back = imus_to_samples([cdr(m) for m in samples_to_imus(sim.samples, frame_id="imu0", types=TYPES)])
    assert back.orientation is None and len(back) == len(sim.samples)
    np.testing.assert_array_equal(back.gyro, sim.samples.gyro)
    assert len(imus_to_samples([])) == 0


@pytest.mark.parametrize(("model", "dist"), [
    ("plumb_bob", [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0]),
    ("rational_polynomial", [0.1, -0.2, 1e-3, -2e-3, 0.05, 0.01, -0.02, 0.003]),
    ("equidistant", [-0.01, 0.02, -0.003, 0.0004]),
])
def test_camera_info_round_trip(model, dist):
    K = np.array([[458.654, 0.0, 367.215], [0.0, 457.296, 248.375], [0.0, 0.0, 1.0]])
    msg = cdr(calib_to_camera_info(K, model, dist, (752, 480), stamp_ns=STAMP, frame_id="cam0", types=TYPES))
    K2, model2, dist2, size = camera_info_to_calib(msg)
    np.testing.assert_array_equal(K2, K)
    np.testing.assert_array_equal(dist2, dist)
    assert (model2, size, msg.height, msg.width) == (model, (752, 480), 480, 752)
    np.testing.assert_array_equal(np.asarray(msg.p).reshape(3, 4)[:, :3], K)


def test_pose_array_pose_stamped_and_path_round_trip():
    rng = np.random.default_rng(2)
    T = random_T(rng, 6)
    pa = cdr(builders.pose_array(T, stamp_ns=STAMP, frame_id="world", types=TYPES))
    np.testing.assert_allclose(builders.poses_to_T(pa.poses), T, atol=1e-12)
    ps = cdr(builders.pose_stamped(T[3], stamp_ns=STAMP, frame_id="world", types=TYPES))
    np.testing.assert_allclose(builders.pose_to_T(ps.pose), T[3], atol=1e-12)
    stamps = [STAMP + 50_000_000 * i for i in range(6)]
    p = cdr(builders.path(T, stamp_ns=STAMP, frame_id="world", types=TYPES, stamps_ns=stamps))
    np.testing.assert_allclose(builders.poses_to_T([q.pose for q in p.poses]), T, atol=1e-12)
    assert [stamp_to_ns(q.header.stamp) for q in p.poses] == stamps
    assert builders.poses_to_T(cdr(builders.pose_array(np.zeros((0, 4, 4)), stamp_ns=1, frame_id="w",
                                                       types=TYPES)).poses).shape == (0, 4, 4)


def test_odometry_round_trip_with_covariances():
    rng = np.random.default_rng(3)
    T, v, w = random_T(rng, 1)[0], rng.normal(size=3), rng.normal(size=3)
    A = rng.normal(size=(6, 6))
    pose_cov, twist_cov = A @ A.T, np.diag(np.arange(1.0, 7.0))
    msg = cdr(builders.odometry(T, v, w, stamp_ns=STAMP, frame_id="odom", child_frame_id="base_link", types=TYPES,
                                pose_cov=pose_cov, twist_cov=twist_cov.reshape(36)))
    T2, v2, w2, pc, tc = builders.odometry_to_numpy(msg)
    np.testing.assert_allclose(T2, T, atol=1e-12)
    np.testing.assert_array_equal(v2, v)
    np.testing.assert_array_equal(w2, w)
    np.testing.assert_array_equal(pc, pose_cov)
    np.testing.assert_array_equal(tc, twist_cov)
    assert (msg.header.frame_id, msg.child_frame_id) == ("odom", "base_link")


def test_tf_message_round_trip():
    rng = np.random.default_rng(4)
    T = random_T(rng, 2)
    items = [(T[0], "world", "imu0", STAMP), (T[1], "imu0", "cam0", STAMP + 1)]
    back = builders.tf_message_to_list(cdr(builders.tf_message(items, types=TYPES)))
    assert [(p, c, s) for _, p, c, s in back] == [(p, c, s) for _, p, c, s in items]
    np.testing.assert_allclose(np.stack([b[0] for b in back]), T, atol=1e-12)


def test_transform_stamped_in_ros2_and_ros1():
    """One TransformStamped builder for both: the Jazzy classes (CDR) and the Noetic ones (ROS 1 bags, seq 0)."""
    T = random_T(np.random.default_rng(5), 1)[0]
    msg = cdr(builders.transform_stamped(T, parent="world", child="body", stamp_ns=STAMP, types=TYPES))
    assert (msg.header.frame_id, msg.child_frame_id, stamp_to_ns(msg.header.stamp)) == ("world", "body", STAMP)
    np.testing.assert_allclose(builders.transform_to_T(msg.transform), T, atol=1e-12)
    ros1 = builders.transform_stamped(T, parent="world", child="body", stamp_ns=STAMP, types=ros1_types())
    store = noetic_typestore()
    back = store.deserialize_ros1(store.serialize_ros1(ros1, ros1.__msgtype__), ros1.__msgtype__)
    assert back.header.seq == 0 and stamp_to_ns(back.header.stamp) == STAMP
    np.testing.assert_array_equal(builders.transform_to_T(back.transform), builders.transform_to_T(msg.transform))


def test_camera_info_with_ros1_field_names():
    """ROS 1 CameraInfo (and bags converted from ROS 1) name the arrays D, K, R, P: they read the same."""
    store = noetic_typestore()
    K = np.array([[458.654, 0.0, 367.215], [0.0, 457.296, 248.375], [0.0, 0.0, 1.0]])
    d = np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0])
    header = store.types["std_msgs/msg/Header"](seq=0, stamp=ns_to_stamp(STAMP, types=TYPES), frame_id="cam0")
    roi = store.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    msg = store.types["sensor_msgs/msg/CameraInfo"](header=header, height=480, width=752, distortion_model="plumb_bob",
                                                     D=d, K=K.reshape(9), R=np.eye(3).reshape(9),
                                                     P=np.c_[K, np.zeros(3)].reshape(12), binning_x=0, binning_y=0,
                                                     roi=roi)
    back = store.deserialize_ros1(store.serialize_ros1(msg, msg.__msgtype__), msg.__msgtype__)
    K2, model, d2, size = camera_info_to_calib(back)
    np.testing.assert_array_equal(K2, K)
    np.testing.assert_array_equal(d2, d)
    assert (model, size) == ("plumb_bob", (752, 480))


def test_full_type_names():
    assert full_name("sensor_msgs/Image") == full_name("sensor_msgs/msg/Image") == "sensor_msgs/msg/Image"
    with pytest.raises(UnknownMessageType, match="'Image'"):
        full_name("Image")


def test_diagnostic_array_round_trip():
    statuses = [builders.DiagStatus(builders.Level.OK, "vi3/init", "scale ok", "cam0", {"scale": 1.25, "mode": "ttr"}),
                builders.DiagStatus(builders.Level.STALE, "vi3/imu", "no IMU for 2.0 s")]
    msg = cdr(builders.diagnostic_array(statuses, stamp_ns=STAMP, types=TYPES))
    assert [s.level for s in msg.status] == [0, 3]
    back = builders.diagnostic_array_to_statuses(msg)
    assert back[0] == builders.DiagStatus(builders.Level.OK, "vi3/init", "scale ok", "cam0",
                                          {"scale": "1.25", "mode": "ttr"})
    assert back[1] == statuses[1]


@pytest.mark.parametrize("organised", [False, True])
@pytest.mark.parametrize("extras", [(), ("intensity",), ("intensity", "confidence"), ("confidence",)])
def test_point_cloud2_round_trip(organised, extras):
    rng = np.random.default_rng(5)
    shape = (4, 6) if organised else (24,)
    pts = rng.normal(size=shape + (3,)).astype(np.float32)
    pts[1, 2] = np.nan
    values = {name: rng.uniform(0, 255, size=shape).astype(np.float32) for name in extras}
    msg = cdr(builders.point_cloud2(pts, stamp_ns=STAMP, frame_id="world", types=TYPES, **values))
    assert (msg.height, msg.width) == ((4, 6) if organised else (1, 24))
    assert msg.point_step == 4 * (3 + len(extras)) and msg.row_step == msg.point_step * msg.width
    assert not msg.is_dense
    cloud = builders.point_cloud2_to_numpy(msg)
    assert cloud.shape == shape and cloud.dtype.names == ("x", "y", "z", *extras)
    np.testing.assert_array_equal(np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=-1), pts)
    for name, v in values.items():
        np.testing.assert_array_equal(cloud[name], v)


def test_point_cloud2_intensity_from_uint8_image_and_dense_flag():
    rng = np.random.default_rng(6)
    pts = rng.normal(size=(3, 5, 3))
    grey = rng.integers(0, 256, size=(3, 5), dtype=np.uint8)
    msg = cdr(builders.point_cloud2(pts, intensity=grey, stamp_ns=STAMP, frame_id="cam0", types=TYPES))
    cloud = builders.point_cloud2_to_numpy(msg)
    assert msg.is_dense
    np.testing.assert_array_equal(cloud["intensity"], grey.astype(np.float32))
    np.testing.assert_array_equal(cloud["z"], pts[..., 2].astype(np.float32))
