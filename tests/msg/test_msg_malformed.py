"""Malformed messages and inputs raise ``MalformedMessage`` (a ``ValueError``) naming the field; nothing else
escapes. Property-based: valid messages are generated, then broken one field at a time, or fuzzed with junk."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from msg_adapters import builders
from msg_adapters.camera_info import camera_info_to_calib
from msg_adapters.errors import MalformedMessage
from msg_adapters.image import ENCODINGS, compressed_to_numpy, depth_to_image, image_to_numpy, numpy_to_image
from msg_adapters.imu import imu_to_sample, samples_to_imus
from msg_adapters.stamps import ns_to_stamp
from msg_adapters.types import jazzy_types
from vi3_core.errors import CalibrationError
from vi3_core.types import ImuSamples

TYPES = jazzy_types()
SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

JUNK = st.one_of(st.none(), st.booleans(), st.integers(-2**40, 2**40), st.floats(), st.text(max_size=6),
                 st.binary(max_size=24), st.lists(st.integers(-5, 300), max_size=24),
                 st.lists(st.floats(), max_size=12))


def header(ns=1_000_000_123):
    return TYPES.make("std_msgs/msg/Header", stamp=ns_to_stamp(ns, types=TYPES), frame_id="f")


@st.composite
def images(draw):
    """A valid sensor_msgs/Image with random encoding, size and row padding."""
    encoding = draw(st.sampled_from(sorted(ENCODINGS)))
    layout = ENCODINGS[encoding]
    h, w, pad = draw(st.integers(0, 5)), draw(st.integers(0, 5)), draw(st.integers(0, 5))
    step = w * layout.channels * layout.dtype.itemsize + pad
    data = np.frombuffer(draw(st.binary(min_size=step * h, max_size=step * h)), dtype=np.uint8)
    return TYPES.make("sensor_msgs/msg/Image", header=header(), height=h, width=w, encoding=encoding,
                      is_bigendian=draw(st.sampled_from([0, 1])), step=step, data=data)


def expect_malformed(fn, msg, field: str, error: type[ValueError] = MalformedMessage):
    with pytest.raises(error, match=field) as info:
        fn(msg)
    assert isinstance(info.value, ValueError)


def only_malformed_escapes(fn, msg):
    try:
        fn(msg)
    except MalformedMessage as exc:
        assert str(exc)


@SETTINGS
@given(images())
def test_valid_images_decode_to_the_declared_shape(msg):
    layout = ENCODINGS[msg.encoding]
    out = image_to_numpy(msg)
    assert out.shape[:2] == (msg.height, msg.width) and out.dtype == layout.dtype
    assert out.ndim == (2 if layout.channels == 1 else 3)


@SETTINGS
@given(images(), st.data())
def test_broken_images_name_the_field(msg, data):
    layout = ENCODINGS[msg.encoding]
    kind = data.draw(st.sampled_from(["step", "short", "long", "encoding", "height", "width", "data", "endian"]))
    if kind == "step":
        msg.width = max(msg.width, 1)
        msg.step = data.draw(st.integers(0, msg.width * layout.channels * layout.dtype.itemsize - 1))
        field = "step"
    elif kind == "short":
        msg.height = max(msg.height, 1)
        msg.step = max(msg.step, 1)
        msg.data = msg.data[:data.draw(st.integers(0, msg.step * msg.height - 1))]
        field = "data has"
    elif kind == "long":
        msg.data = np.concatenate([msg.data, np.zeros(data.draw(st.integers(1, 9)), dtype=np.uint8)])
        field = "data has"
    elif kind == "encoding":
        msg.encoding = data.draw(st.text(max_size=8).filter(lambda e: e not in ENCODINGS))
        field = "encoding"
    elif kind in ("height", "width"):
        setattr(msg, kind, data.draw(st.one_of(st.integers(max_value=-1), st.floats(), st.just(math.nan),
                                               st.none(), st.text(max_size=3))))
        field = kind
    elif kind == "data":
        msg.data = data.draw(st.one_of(st.text(min_size=1, max_size=4), st.floats(), st.none(),
                                       st.lists(st.integers(256, 10**4), min_size=1, max_size=3),
                                       st.just(np.zeros(3, dtype=np.float32))))
        field = "data"
    else:
        msg.is_bigendian = data.draw(st.one_of(st.integers(max_value=-1), st.integers(min_value=256),
                                               st.just(math.nan)))
        field = "is_bigendian"
    expect_malformed(image_to_numpy, msg, field)


@SETTINGS
@given(images(), st.lists(st.tuples(st.sampled_from(["height", "width", "encoding", "is_bigendian", "step",
                                                      "data"]), JUNK), min_size=1, max_size=3))
def test_image_fuzz_raises_only_malformed_message(msg, junk):
    for name, value in junk:
        setattr(msg, name, value)
    only_malformed_escapes(image_to_numpy, msg)


def imu_msg():
    samples = ImuSamples(np.array([12.5]), np.array([[0.1, -0.2, 0.3]]), np.array([[0.0, 0.1, 9.81]]),
                         np.array([[0.0, 0.0, 0.0, 1.0]]))
    return samples_to_imus(samples, frame_id="imu0", types=TYPES)[0]


@SETTINGS
@given(st.sampled_from(["sec", "nanosec", "cov", "vector"]), st.data())
def test_broken_imu_messages_name_the_field(kind, data):
    msg = imu_msg()
    if kind == "sec":
        msg.header.stamp.sec = data.draw(st.one_of(st.just(math.nan), st.floats(), st.integers(max_value=-1),
                                                   st.integers(min_value=2**31)))
        field = "header.stamp.sec"
    elif kind == "nanosec":
        msg.header.stamp.nanosec = data.draw(st.one_of(st.integers(min_value=10**9), st.integers(max_value=-1),
                                                       st.just(math.nan)))
        field = "header.stamp.nanosec"
    elif kind == "cov":
        field = data.draw(st.sampled_from(["orientation_covariance", "angular_velocity_covariance",
                                           "linear_acceleration_covariance"]))
        n = data.draw(st.integers(0, 20).filter(lambda k: k != 9))
        setattr(msg, field, np.zeros(n))
    else:
        field = data.draw(st.sampled_from(["angular_velocity", "linear_acceleration"]))
        setattr(getattr(msg, field), data.draw(st.sampled_from("xyz")), data.draw(st.one_of(st.none(),
                                                                                            st.text(max_size=3))))
    expect_malformed(imu_to_sample, msg, field)


@SETTINGS
@given(st.lists(st.tuples(st.sampled_from(["header", "orientation", "orientation_covariance", "angular_velocity",
                                           "angular_velocity_covariance", "linear_acceleration",
                                           "linear_acceleration_covariance"]), JUNK), min_size=1, max_size=3))
def test_imu_fuzz_raises_only_malformed_message(junk):
    msg = imu_msg()
    for name, value in junk:
        setattr(msg, name, value)
    only_malformed_escapes(imu_to_sample, msg)


def camera_info_msg():
    K = np.array([400.0, 0, 320, 0, 410, 240, 0, 0, 1])
    return TYPES.make("sensor_msgs/msg/CameraInfo", header=header(), height=480, width=640,
                      distortion_model="plumb_bob", d=np.zeros(5), k=K, r=np.eye(3).reshape(9),
                      p=np.zeros(12), binning_x=0, binning_y=0,
                      roi=TYPES.make("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                                     do_rectify=False))


@SETTINGS
@given(st.sampled_from(["d", "model", "k_zero", "k_nan", "k_size", "width"]), st.data())
def test_broken_camera_info_names_the_problem(kind, data):
    msg = camera_info_msg()
    if kind == "d":
        msg.distortion_model = data.draw(st.sampled_from(["plumb_bob", "rational_polynomial", "equidistant"]))
        msg.d = np.zeros(data.draw(st.sampled_from([0, 1, 3, 6, 7, 9, 13, 15])))
        field = "coefficients"
    elif kind == "model":
        msg.distortion_model = data.draw(st.text(max_size=10).filter(
            lambda m: m not in ("plumb_bob", "rational_polynomial", "equidistant")))
        field = "distortion_model"
    elif kind == "k_zero":
        msg.k = np.zeros(9)
        field = "uncalibrated"
    elif kind == "k_nan":
        msg.k = msg.k.copy()
        msg.k[data.draw(st.integers(0, 8))] = data.draw(st.sampled_from([math.nan, math.inf]))
        field = "not finite"
    elif kind == "k_size":
        msg.k = np.eye(3).reshape(9)[:data.draw(st.integers(0, 8))]
        field = "k has"
    else:
        msg.width = data.draw(st.sampled_from([0, -1, 2**32, 1.5]))
        field = "width"
    # the message's layout is a MalformedMessage, its calibration content a CalibrationError: both DataError
    expect_malformed(camera_info_to_calib, msg, field, MalformedMessage if kind in ("k_size", "width") else
                     CalibrationError)


@SETTINGS
@given(st.lists(st.tuples(st.sampled_from(["height", "width", "distortion_model", "d", "k"]), JUNK), min_size=1,
                max_size=3))
def test_camera_info_fuzz_raises_only_data_errors(junk):
    msg = camera_info_msg()
    for name, value in junk:
        setattr(msg, name, value)
    try:
        camera_info_to_calib(msg)
    except (MalformedMessage, CalibrationError) as exc:
        assert str(exc)


@st.composite
def clouds(draw):
    n = draw(st.integers(1, 6))
    pts = np.asarray(draw(st.lists(st.floats(-1e3, 1e3, width=32), min_size=3 * n, max_size=3 * n)),
                     dtype=np.float32).reshape(n, 3)
    return builders.point_cloud2(pts, intensity=np.ones(n), stamp_ns=1, frame_id="w", types=TYPES)


@SETTINGS
@given(clouds(), st.sampled_from(["short", "row_step", "offset", "datatype", "count", "duplicate", "empty"]),
       st.data())
def test_broken_point_clouds_name_the_field(msg, kind, data):
    f = msg.fields[data.draw(st.integers(0, len(msg.fields) - 1))]
    if kind == "short":
        msg.data = msg.data[:data.draw(st.integers(0, len(msg.data) - 1))]
        field = "data has"
    elif kind == "row_step":
        msg.row_step = data.draw(st.integers(0, msg.width * msg.point_step - 1))
        field = "row_step"
    elif kind == "offset":
        f.offset = data.draw(st.integers(msg.point_step - 3, 2**32 - 1))
        field = "point_step"
    elif kind == "datatype":
        f.datatype = data.draw(st.one_of(st.just(0), st.integers(9, 255)))
        field = "datatype"
    elif kind == "count":
        f.count = 0
        field = "point_step"
    elif kind == "duplicate":
        msg.fields[-1].name = msg.fields[0].name
        field = "repeated"
    else:
        msg.fields = []
        field = "fields"
    expect_malformed(builders.point_cloud2_to_numpy, msg, field)


@SETTINGS
@given(clouds(), st.lists(st.tuples(st.sampled_from(["height", "width", "fields", "is_bigendian", "point_step",
                                                      "row_step", "data"]), JUNK), min_size=1, max_size=3))
def test_point_cloud_fuzz_raises_only_malformed_message(msg, junk):
    for name, value in junk:
        setattr(msg, name, value)
    only_malformed_escapes(builders.point_cloud2_to_numpy, msg)


@SETTINGS
@given(st.one_of(st.binary(max_size=64), st.just(b"")), st.sampled_from(["jpeg", "png", "rgb8; jpeg compressed bgr8",
                                                                        "tiff", "16UC1; compressedDepth png", ""]))
def test_compressed_garbage_is_malformed(data, fmt):
    msg = TYPES.make("sensor_msgs/msg/CompressedImage", header=header(), format=fmt,
                     data=np.frombuffer(data, dtype=np.uint8))
    expect_malformed(compressed_to_numpy, msg, "format|data")


@pytest.mark.parametrize(("call", "field"), [
    (lambda: numpy_to_image(np.zeros((2, 3), np.float64), encoding="32FC1", stamp_ns=1, frame_id="c", types=TYPES),
     "dtype"),
    (lambda: numpy_to_image(np.zeros((2, 3, 3), np.uint8), encoding="mono8", stamp_ns=1, frame_id="c", types=TYPES),
     "shape"),
    (lambda: numpy_to_image(np.zeros((2, 3), np.uint8), encoding="yuv422", stamp_ns=1, frame_id="c", types=TYPES),
     "encoding"),
    (lambda: depth_to_image(np.zeros((2, 3), np.float32), stamp_ns=math.nan, frame_id="c", types=TYPES), "stamp"),
    (lambda: depth_to_image(np.zeros(3), stamp_ns=1, frame_id="c", types=TYPES), "shape"),
    (lambda: builders.odometry(np.eye(4), np.zeros(3), np.zeros(3), stamp_ns=1, frame_id="o", child_frame_id="b",
                               types=TYPES, pose_cov=np.zeros(35)), "pose_cov"),
    (lambda: builders.odometry(np.eye(4), np.zeros(2), np.zeros(3), stamp_ns=1, frame_id="o", child_frame_id="b",
                               types=TYPES), "v_linear"),
    (lambda: builders.pose_array(np.tile(np.diag([2.0, 1, 1, 1]), (2, 1, 1)), stamp_ns=1, frame_id="w", types=TYPES),
     "rotation"),
    (lambda: builders.pose_stamped(np.full((4, 4), np.nan), stamp_ns=1, frame_id="w", types=TYPES), "non-finite"),
    (lambda: builders.pose_stamped(np.ones((4, 4)), stamp_ns=1, frame_id="w", types=TYPES), "bottom row"),
    (lambda: builders.path(np.tile(np.eye(4), (3, 1, 1)), stamp_ns=1, frame_id="w", types=TYPES, stamps_ns=[1, 2]),
     "stamps"),
    (lambda: builders.point_cloud2(np.zeros((4, 3)), intensity=np.zeros(5), stamp_ns=1, frame_id="w", types=TYPES),
     "intensity"),
    (lambda: builders.point_cloud2(np.zeros((4, 2)), stamp_ns=1, frame_id="w", types=TYPES), "points"),
    (lambda: builders.tf_message([(np.eye(4), "a", "b", -5)], types=TYPES), "stamp"),
    (lambda: builders.diagnostic_array([builders.DiagStatus(7, "n", "m")], stamp_ns=1, types=TYPES), "level"),
    (lambda: samples_to_imus(ImuSamples([math.nan], [[0, 0, 0]], [[0, 0, 0]]), frame_id="i", types=TYPES), "stamp"),
    (lambda: samples_to_imus(ImuSamples([1.0], [[0, 0, 0]], [[0, 0, 0]]), frame_id="i", types=TYPES,
                             stamps_ns=[1, 2]), "stamps_ns"),
])
def test_bad_builder_inputs_raise_value_errors_naming_the_input(call, field):
    with pytest.raises(MalformedMessage, match=field):
        call()


def test_diagnostic_level_out_of_range_on_read():
    status = TYPES.make("diagnostic_msgs/msg/DiagnosticStatus", level=9, name="n", message="m", hardware_id="",
                        values=[])
    msg = TYPES.make("diagnostic_msgs/msg/DiagnosticArray", header=header(), status=[status])
    with pytest.raises(MalformedMessage, match="level"):
        builders.diagnostic_array_to_statuses(msg)
