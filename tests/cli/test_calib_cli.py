"""``vi3 calib``: a generated flight whose calibration file has the camera mount turned by 3 deg and a 20 ms
timeshift is run through the node's pipeline with the embedded classical backbone; the YAML it prints is a Kalibr
camchain that loads, and it is closer to the truth than the file it was given, in the parts it says it corrected."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import yaml

from vi3_core import so3
from vi3_core.dataset.calib import load_calib, write_kalibr_camchain
from vi3_core.dataset.generate import cached_sequence
from vi3_ros import cli

pytestmark = pytest.mark.slow  # replays 10 s of a generated flight with the classical backbone


@pytest.fixture(scope="module")
def flight(cache_dir):
    return cached_sequence(cache_dir, seconds=10.0, seed=0, with_depth=False)  # as test_eval_inputs'


def _wrong(flight, path, *, rotation_deg=(0.0, 3.0, 0.0), timeshift=-0.020):
    """The flight's calibration with the mount turned back by ``rotation_deg`` about the body axes and a wrong
    ``timeshift_cam_imu`` (the truth is 0), written as Kalibr YAML to ``path``."""
    truth = load_calib(flight / "mav0" / "cam0" / "sensor.yaml")
    T = truth.T_BC.copy()
    T[:3, :3] = so3.exp(-np.radians(rotation_deg)) @ T[:3, :3]
    write_kalibr_camchain(dataclasses.replace(truth, T_BC=T, time_offset=timeshift), path,
                          rostopic="/camera/color/image_raw")
    doc = yaml.safe_load(path.read_text())  # fields a user's Kalibr file has that vi3 does not read
    doc["cam0"]["camera_model"], doc["cam0"]["cam_overlaps"] = "pinhole", [1]
    doc["cam1"] = {"rostopic": "/camera/infra1/image_rect_raw", "resolution": [848, 480]}
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return truth


def _angle_deg(a, b) -> float:
    return float(np.degrees(so3.angle(a[:3, :3].T @ b[:3, :3])))


def test_calib_prints_a_kalibr_file_closer_to_the_truth_than_the_one_given(flight, tmp_path, capsys):
    truth = _wrong(flight, tmp_path / "wrong.yaml")
    given = load_calib(tmp_path / "wrong.yaml")
    out = tmp_path / "fixed.yaml"
    assert cli.main(["calib", str(flight), "--calib", str(tmp_path / "wrong.yaml"), "-o", str(out),
                     "--no-progress"]) == 0
    text = out.read_text()
    comments = [line[2:] for line in text.splitlines() if line.startswith("# ")]
    fixed = load_calib(out)
    assert "cam0" in yaml.safe_load(text)
    assert "the configuration is off" in " ".join(comments), comments
    corrected_rotation = "T_cam_imu: rotation corrected" in comments
    corrected_offset = "s corrected" in " ".join(comments)
    assert corrected_rotation or corrected_offset, comments
    if corrected_rotation:
        assert _angle_deg(fixed.T_BC, truth.T_BC) < 0.5 < _angle_deg(given.T_BC, truth.T_BC), comments
    else:
        assert np.allclose(fixed.T_BC, given.T_BC, atol=1e-12)
    if corrected_offset:
        assert abs(fixed.time_offset - truth.time_offset) < 0.004, comments
    else:
        assert fixed.time_offset == given.time_offset
    assert np.array_equal(fixed.K, given.K) and np.allclose(fixed.T_BC[:3, 3], given.T_BC[:3, 3], atol=1e-12)
    assert capsys.readouterr().out == ""  # the YAML went to --output only
    # issue 39: every field it does not correct is kept (the topic was /cam0/image_raw whatever the file said)
    written, original = yaml.safe_load(text), yaml.safe_load((tmp_path / "wrong.yaml").read_text())
    for doc in (written, original):
        del doc["cam0"]["T_cam_imu"], doc["cam0"]["timeshift_cam_imu"]
    assert written == original


def test_calib_json_and_a_refused_output(flight, tmp_path, capsys):
    _wrong(flight, tmp_path / "wrong.yaml", rotation_deg=(0.0, 0.0, 0.0), timeshift=0.0)
    args = ["calib", str(flight), "--calib", str(tmp_path / "wrong.yaml")]
    assert cli.main([*args, "--json", "--no-progress"]) in (0, 1)
    obj = json.loads(capsys.readouterr().out)
    assert obj["off_by"] == "" and obj["clips"] > 0 and len(obj["corrected_T_cam_imu"]) == 4, obj
    assert abs(obj["corrected_timeshift_cam_imu_s"]) < 0.004, obj
    # an output onto the calibration it corrects is refused before anything runs
    assert cli.main([*args, "-o", str(tmp_path / "wrong.yaml"), "--force"]) == 2
    assert "would destroy the input" in capsys.readouterr().err
    # issue 39: an empty name was taken for no --output (the YAML went to standard output, exit 0)
    assert cli.main([*args, "-o", ""]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err == "vi3 calib: error: vi3 calib --output '': an empty name; name a YAML file (or leave " \
        "--output out for standard output)\n"


def test_eval_with_a_wrong_rig_reports_the_estimate_it_converged_to(euroc_v102, capsys):
    """``vi3 eval --calib-error``: the real V1_02 IMU with the mount turned by 3 deg about body y and the IMU 20 ms
    late; the chained JSON and every clip say what the self-calibration made of it."""
    assert cli.main(["eval", str(euroc_v102), "--backbone", "gt", "--gt-noise", "0.001,0.05", "--calib-error",
                     "0,3,0,20", "--json", "--no-progress"]) == 0
    obj = json.loads(capsys.readouterr().out)
    rig = obj["chained"]["calibration"]
    assert rig["rotation_applied"] and rig["offset_applied"], rig
    assert np.allclose(rig["rotation_deg"], [0.0, 3.0, 0.0], atol=0.3) and abs(rig["time_offset_ms"] - 20) < 3, rig
    assert 0 < rig["rotation_applied_after_s"] < 15 and 0 < rig["offset_applied_after_s"] < 15, rig
    assert obj["clips"][-1]["rig"]["clips"] == rig["clips"]
    claims = [c for c in obj["clips"] if c["status"] == "ok"]
    assert len(claims) >= 20 and all(abs(c["scale_fit"] - 1) < 0.1 for c in claims)
