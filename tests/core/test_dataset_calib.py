"""Calibration from EuRoC sensor.yaml and Kalibr camchain-imucam YAML; undistortion built once."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from vi3_core import so3
from vi3_core.dataset.calib import load_calib, write_euroc_sensor_yaml, write_kalibr_camchain
from vi3_core.dataset.generate import EUROC_CAM0
from vi3_core.errors import CalibrationError


def test_real_euroc_sensor_yaml(euroc_fixture):
    calib = load_calib(euroc_fixture / "cam0" / "sensor.yaml")
    assert calib.size == (752, 480) and calib.dist_model == "radtan" and calib.rate_hz == 20.0
    np.testing.assert_allclose(calib.K, EUROC_CAM0.K)
    np.testing.assert_allclose(calib.dist, EUROC_CAM0.dist)
    np.testing.assert_allclose(calib.T_BC, EUROC_CAM0.T_BC)
    cam1 = load_calib(euroc_fixture / "cam1" / "sensor.yaml")
    baseline = np.linalg.norm((so3.inv_T(calib.T_BC) @ cam1.T_BC)[:3, 3])
    assert 0.10 < baseline < 0.12  # EuRoC's stereo baseline is about 11 cm
    with pytest.raises(CalibrationError, match="not a camera"):
        load_calib(euroc_fixture / "imu0" / "sensor.yaml")


def test_kalibr_round_trip_inverts_T_cam_imu(tmp_path):
    path = tmp_path / "camchain-imucam.yaml"
    write_kalibr_camchain(EUROC_CAM0, path)
    text = path.read_text()
    assert "T_cam_imu" in text and "T_BS" not in text
    calib = load_calib(path)
    np.testing.assert_allclose(calib.T_BC, EUROC_CAM0.T_BC, atol=1e-12)
    np.testing.assert_allclose(calib.K, EUROC_CAM0.K)
    assert calib.dist_model == "radtan"
    euroc = tmp_path / "sensor.yaml"
    write_euroc_sensor_yaml(calib, euroc)
    np.testing.assert_allclose(load_calib(euroc).T_BC, EUROC_CAM0.T_BC, atol=1e-12)


def test_kalibr_equidistant(tmp_path):
    path = tmp_path / "camchain-imucam.yaml"
    path.write_text("""cam0:
  T_cam_imu:
  - [0.0, -1.0, 0.0, 0.01]
  - [0.0, 0.0, -1.0, 0.02]
  - [1.0, 0.0, 0.0, -0.03]
  - [0.0, 0.0, 0.0, 1.0]
  camera_model: pinhole
  distortion_coeffs: [0.01, -0.005, 0.001, -0.0002]
  distortion_model: equidistant
  intrinsics: [280.0, 281.0, 320.0, 240.0]
  resolution: [640, 480]
  rostopic: /cam0/image_raw
""")
    calib = load_calib(path)
    assert calib.dist_model == "equidistant"
    np.testing.assert_allclose(calib.T_BC[:3, 3], -calib.T_BC[:3, :3] @ [0.01, 0.02, -0.03])
    uv = np.array([[10.0, 15.0], [320.0, 240.0], [600.0, 400.0]])
    np.testing.assert_allclose(calib.distort(calib.undistort_points(uv)), uv, atol=1e-6)
    assert calib.undistorter().map_x.shape == (480, 640)


def test_undistortion_is_exact_and_built_once():
    calib = EUROC_CAM0
    u, v = np.meshgrid(np.arange(0, 752, 11.0), np.arange(0, 480, 11.0))
    uv = np.stack([u.ravel(), v.ravel()], 1)
    np.testing.assert_allclose(calib.distort(calib.undistort_points(uv)), uv, atol=1e-6)
    und = calib.undistorter()
    assert und is calib.undistorter()
    # The undistorted pixel (u, v) comes from raw pixel distort(K^-1 [u, v, 1]).
    xy = (uv - und.K[:2, 2]) / np.diag(und.K)[:2]
    raw = calib.distort(xy)
    maps = np.stack([und.map_x[v.ravel().astype(int), u.ravel().astype(int)],
                     und.map_y[v.ravel().astype(int), u.ravel().astype(int)]], 1)
    np.testing.assert_allclose(maps, raw, atol=1e-2)
    # With EuRoC's barrel distortion every undistorted pixel has a source inside the raw image.
    assert und.map_x.min() >= 0 and und.map_x.max() <= 751 and und.map_y.min() >= 0 and und.map_y.max() <= 479


@pytest.mark.parametrize("model, dist", [("radtan", np.zeros(4)), ("none", np.zeros(0))])
def test_a_camera_without_distortion_is_not_remapped_and_gives_the_remaps_bits(model, dist):
    """A rectified stream's frames are copied, not remapped: the same bits as a remap through the model's own maps
    (uint8 and float, linear and nearest), which the equidistant model, whose zero coefficients still map angles to
    radii, keeps."""
    calib = replace(EUROC_CAM0, dist_model=model, dist=dist)
    und = calib.undistorter()
    assert und.map_x is None and np.array_equal(und.K, calib.K)
    maps = cv2.initUndistortRectifyMap(calib.K, np.zeros(4), None, calib.K, calib.size, cv2.CV_32FC1)
    rng = np.random.default_rng(0)
    for image in (rng.integers(0, 256, (480, 752), dtype=np.uint8), rng.random((480, 752, 3), dtype=np.float32)):
        for interpolation in (cv2.INTER_LINEAR, cv2.INTER_NEAREST):
            out = und.apply(image, interpolation=interpolation)
            assert out is not image
            assert np.array_equal(out, cv2.remap(image, *maps, interpolation, borderMode=cv2.BORDER_CONSTANT))
    assert replace(EUROC_CAM0, dist_model="equidistant", dist=np.zeros(4)).undistorter().map_x is not None


@pytest.mark.parametrize("body, message", [
    ("sensor_type: camera\nT_BS: {cols: 4, rows: 4, data: [1, 0, 0]}\n", "T_BS is not a 4x4"),
    ("sensor_type: camera\nT_BS: {cols: 4, rows: 4, data: [2,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]}\n"
     "intrinsics: [1, 1, 1, 1]\nresolution: [4, 4]\n", "not a rigid transform"),
    ("sensor_type: camera\nT_BS: {cols: 4, rows: 4, data: [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]}\n"
     "intrinsics: [1, 1, 1, 1]\nresolution: [4, 4]\ndistortion_model: fov\n", "distortion_model 'fov'"),
    ("sensor_type: camera\nT_BS: {cols: 4, rows: 4, data: [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]}\n"
     "resolution: [4, 4]\n", "missing 'intrinsics'"),
    ("cam0: {intrinsics: [1, 1, 1, 1], resolution: [4, 4]}\n", "no T_cam_imu"),
    ("foo: 1\n", "neither an EuRoC sensor.yaml"),
    ("[1, 2\n", "not valid YAML"),
    # issue 26: a mirror T_BS (det -1) made every clip a "backbone failure"; a missing distortion model was reported
    # as "none distortion needs 0 coefficients, got 4"; a NaN or absurd timeshift was accepted
    ("sensor_type: camera\nT_BS: {cols: 4, rows: 4, data: [-1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]}\n"
     "intrinsics: [1, 1, 1, 1]\nresolution: [4, 4]\n", "T_BS is a mirror, not a rotation"),
    ("sensor_type: camera\nT_BS: {cols: 4, rows: 4, data: [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]}\n"
     "intrinsics: [1, 1, 1, 1]\nresolution: [4, 4]\ndistortion_coefficients: [0.1, 0.01, 0, 0]\n",
     "distortion_model is missing but distortion_coefficients has 4 coefficients"),
    ("cam0: {intrinsics: [1, 1, 1, 1], resolution: [4, 4], T_cam_imu: [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "
     "timeshift_cam_imu: .nan}\n", "timeshift_cam_imu = nan s"),
    ("cam0: {intrinsics: [1, 1, 1, 1], resolution: [4, 4], T_cam_imu: [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "
     "timeshift_cam_imu: 3.0}\n", r"timeshift_cam_imu = 3 s .* within \[-1, 1\] s"),
])
def test_bad_calibration_names_file_and_problem(tmp_path, body, message):
    path = tmp_path / "sensor.yaml"
    path.write_text(body)
    with pytest.raises(CalibrationError, match=message) as info:
        load_calib(path)
    assert str(path) in str(info.value)


def test_missing_calibration_file(tmp_path):
    with pytest.raises(CalibrationError, match="does not exist"):
        load_calib(tmp_path / "cam0" / "sensor.yaml")


def test_kalibr_timeshift_is_the_time_offset_and_round_trips(tmp_path):
    path = tmp_path / "camchain-imucam.yaml"
    write_kalibr_camchain(replace(EUROC_CAM0, time_offset=0.05), path)
    assert load_calib(path).time_offset == 0.05


def test_a_calibration_behind_a_symlink_loop_says_so(tmp_path):
    loop = tmp_path / "sensor.yaml"
    loop.symlink_to(loop)
    with pytest.raises(CalibrationError, match="sensor.yaml: calibration file is a symbolic link that points to "):
        load_calib(loop)
