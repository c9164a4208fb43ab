"""Parameter declarations shared by the node and replay: checking, the ROS 2 parameter file, the docs table, and
the calibration assembly that CameraInfo / tf_static / calib_file feed."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from msg_adapters.camera_info import calib_to_camera_info, camera_info_to_calib
from msg_adapters.types import jazzy_types
from vi3_core.anchor import AnchorOptions
from vi3_core.dataset.calib import load_calib
from vi3_core.dataset.generate import EUROC_CAM0
from vi3_core.errors import CalibrationError, DataError
from vi3_core.init import InitOptions
from vi3_core.online import OnlineOptions
from vi3_ros import cli
from vi3_ros.calibration import Calibration, calib_from_camera_info
from vi3_ros.clip_buffer import ClipBufferOptions
from vi3_ros.commands.replay import register, settings_from_args
from vi3_ros.params import BY_NAME, PARAMS, load_yaml, markdown_table, parameter_values, parse_assignment, resolve
from vi3_ros.pipeline import buffer_options, make_pipeline
from vi3_ros.replay import DiscardSink
from vi3_ros.settings import Settings

REPO = Path(__file__).resolve().parents[2]


def test_every_parameter_is_valid_and_documented():
    assert len(BY_NAME) == len(PARAMS)
    for p in PARAMS:
        assert p.check(p.default) == p.default and p.description
        if p.range is not None:
            assert p.range[0] <= p.default <= p.range[1]
    assert (REPO / "docs" / "node.md").read_text().count(markdown_table()) == 1


def test_checks_name_the_parameter():
    with pytest.raises(DataError, match="clip_length: 1 is outside"):
        resolve({"clip_length": 1})
    with pytest.raises(DataError, match="mode: 'fast' is not one of"):
        resolve({"mode": "fast"})
    with pytest.raises(DataError, match="unknown parameter 'clip_len' \\(did you mean 'clip_length'\\?\\)"):
        resolve({"clip_len": 4})
    with pytest.raises(DataError, match="stride: expected int"):
        resolve({"stride": 2.5})
    # --param and parameter files only name the parameter; resolve checks and converts every value once
    assert resolve(dict([parse_assignment("publish_tf=true"), parse_assignment("time_offset=-0.01")])) \
        == resolve().replace(publish_tf=True, time_offset=-0.01)
    with pytest.raises(DataError, match=r"stride: expected int in \[1, 100\], got '2.5'"):
        resolve(dict([parse_assignment("stride=2.5")]))
    with pytest.raises(DataError, match="--param 'strid=2': unknown parameter 'strid' \\(did you mean 'stride'"):
        parse_assignment("strid=2")


def test_one_name_per_setting_from_parameter_to_options_field():
    """Every parameter is the field of the same name in its options dataclass, defaults to that field's default and
    sets it; the options classes refuse what their own checks refuse, naming the parameter."""
    settings = resolve()
    assert settings == Settings()
    for cls in (ClipBufferOptions, OnlineOptions, InitOptions, AnchorOptions):
        assert getattr(settings, {ClipBufferOptions: "buffer", OnlineOptions: "online", InitOptions: "init",
                                  AnchorOptions: "anchor"}[cls]) == cls(), cls.__name__
    assert parameter_values(settings)["hop"] == 0 and settings.buffer.hop is None  # 0 stands for None
    changed = resolve({"clip_length": 5, "hop": 3, "online_window": 4.0, "ttr_steps": 7, "max_imu_gap": 0.02,
                       "max_scale_sigma": 0.05, "mode": "ttr"})
    assert (changed.buffer.clip_length, changed.buffer.hop) == (5, 3)
    assert changed.online.online_window == 4.0 and changed.anchor.ttr_steps == 7
    assert changed.init.max_imu_gap == 0.02 and changed.init.max_scale_sigma == 0.05 and changed.stream.mode == "ttr"
    for p in PARAMS:
        assert changed.value(p.name) == p.field_value(parameter_values(changed)[p.name])
    assert buffer_options(settings).imu_history == settings.online.online_max_bridge  # online: history covers it
    assert buffer_options(resolve({"online": False})).imu_history == ClipBufferOptions().imu_history


def test_euroc_config_loads_and_maps_to_buffer_options():
    settings = resolve(load_yaml(REPO / "config" / "euroc.yaml"))
    assert settings.inputs.image_topic == "/cam0/image_raw" and settings.inputs.imu_topic == "/imu0"
    opts = buffer_options(settings)
    assert (opts.clip_length, opts.stride, opts.clip_hop) == (8, 2, 14)  # each clip shares a frame with the last
    calib = load_calib(REPO / "config" / "euroc_cam0_sensor.yaml")
    np.testing.assert_allclose(calib.K, EUROC_CAM0.K)
    np.testing.assert_allclose(calib.T_BC, EUROC_CAM0.T_BC)


def test_realsense_config_loads_and_learns_the_noise_levels():
    """config/realsense.yaml: a camera with a consumer IMU; its estimation settings reach the options (the noise
    levels learnt, no accelerometer matrix until one is given)."""
    settings = resolve(load_yaml(REPO / "config" / "realsense.yaml"))
    assert settings.init.noise_levels and settings.init.accel_A is None
    assert settings.inputs.imu_topic == "/camera/camera/imu" and not settings.inputs.use_tf_static
    assert resolve().init.noise_levels is False  # the default keeps the model's levels


def test_classical_keyframes_reach_the_backbone():
    """``classical_keyframes``: the pipeline's classical backbone holds its scale with keyframes, or (false) has no
    keyframe map; another backbone refuses false by name (it has no such option)."""
    for on in (True, False):
        pipeline = make_pipeline(resolve({"classical_keyframes": on}), sink=DiscardSink(), types=jazzy_types(),
                                 synchronous=True)
        assert (pipeline.stream.backbone.keyframes is not None) is on
    assert resolve({"backbone": "vggt"}).model.backbone_options() == {}
    with pytest.raises(DataError, match="classical_keyframes is false, but the backbone is vggt"):
        resolve({"classical_keyframes": False, "backbone": "vggt"})


def test_bad_parameter_file(tmp_path):
    bad = tmp_path / "p.yaml"
    bad.write_text("vi3_node:\n  ros__parameters:\n    strde: 3\n")
    with pytest.raises(DataError, match="unknown parameter 'strde' \\(did you mean 'stride'\\?\\)"):
        load_yaml(bad)
    bad.write_text("vi3_node:\n  ros__parameters:\n    stride: 0\n")
    with pytest.raises(DataError, match="stride: 0 is outside"):
        resolve(load_yaml(bad))
    bad.write_text("other_node:\n  ros__parameters: {}\n")
    with pytest.raises(DataError, match="no 'vi3_node: ros__parameters:'"):
        load_yaml(bad)


def test_a_parameter_file_that_is_not_yaml_is_one_line_naming_file_line_and_column(tmp_path, capsys):
    """Issue 31: a YAML syntax error ended the message with PyYAML's caret lines; now one line (``vi3 eval``)."""
    bad = tmp_path / "p.yaml"
    bad.write_text("vi3_node:\n  ros__parameters:\n    clip_length: [8\n    mode: init\n")
    assert cli.main(["eval", str(tmp_path), "--params-file", str(bad), "--json"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err == (f"vi3 eval: error: parameter file {bad}: not valid YAML: line 4, column 9: expected "
                                 "',' or ']', but got ':' (while parsing a flow sequence from line 3, column 18)\n")


def test_replay_cli_precedence(tmp_path):
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    f = tmp_path / "p.yaml"
    f.write_text("/**:\n  ros__parameters:\n    stride: 3\n    mode: ttr\n")
    args = parser.parse_args(["replay", "in", "-o", "out.mcap", "--params-file", str(f), "--param", "stride=4",
                              "--mode", "cond"])
    settings = settings_from_args(args)
    assert settings.buffer.stride == 4 and settings.stream.mode == "cond" and settings.buffer.clip_length == 8


def test_calibration_from_camera_info_and_tf():
    types = jazzy_types()
    c = EUROC_CAM0
    cal = Calibration()
    with pytest.raises(CalibrationError, match="no camera intrinsics"):
        cal.current()
    msg = calib_to_camera_info(c.K, "plumb_bob", np.r_[c.dist, 0.0], c.size, stamp_ns=1, frame_id="cam0", types=types)
    cal.set_intrinsics(*camera_info_to_calib(msg))
    with pytest.raises(CalibrationError, match="extrinsics"):
        cal.current()
    cal.set_extrinsics(c.T_BC)
    got = cal.current()
    assert got.dist_model == "radtan" and np.allclose(got.dist, c.dist) and got.size == c.size
    assert cal.current() is got  # cached until something changes
    cal.set_extrinsics(np.eye(4))
    assert np.allclose(cal.current().T_BC, np.eye(4))
    with pytest.raises(CalibrationError, match="beyond"):
        calib_from_camera_info(c.K, "plumb_bob", np.array([0.1, 0, 0, 0, 0.01]), c.size, c.T_BC)
    # zero coefficients: a rectified stream has no distortion, an ideal fisheye still maps angles to radii
    assert calib_from_camera_info(c.K, "plumb_bob", np.zeros(5), c.size, c.T_BC).dist_model == "none"
    for dist in (np.zeros(4), np.zeros(0)):
        fisheye = calib_from_camera_info(c.K, "equidistant", dist, c.size, c.T_BC)
        assert fisheye.dist_model == "equidistant" and fisheye.undistorter().map_x is not None
    file_cal = Calibration(c)
    assert file_cal.current() is c
