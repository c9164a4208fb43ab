"""Issue 26, what is said: faults of the input named as such, not blamed on the backbone or reported as something
else. Kalibr's timeshift_cam_imu is the time offset; a run whose clips mostly fail the gyro check points at the time
offset or T_BS; unsorted or empty IMU files, symbolic-link loops, topics that do not apply or have the wrong type, an
empty --output, an input taken for --ray's address, a make-bag that cannot fit on the disk: each a message naming
the cause. An ASL folder is read as a stream (memory does not grow with its length)."""

from __future__ import annotations

import json
import os
import shutil
import tracemalloc
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from test_replay import OPEN_GATE, _calib_file, _converted_bag, _edited
from test_replay_faults import _replay, _vi3

from msg_adapters.stamps import ns_to_stamp, stamp_to_ns
from msg_adapters.types import jazzy_types
from vi3_core.dataset.calib import write_euroc_sensor_yaml, write_kalibr_camchain
from vi3_core.dataset.generate import EUROC_CAM0
from vi3_ros.io.reader import ImageEvent, ImuEvent, iter_events

SHIFT_NS = 50_000_000  # the IMU's clock 50 ms ahead of the camera's: t_imu = t_cam + 0.05 s
GATE = [a for k, v in OPEN_GATE.items() for a in ("--param", f"{k}={v}")]


@pytest.fixture(scope="module")
def bag3(cache_dir):
    return _converted_bag(cache_dir, seconds=2.5, seed=1)


@pytest.fixture(scope="module")
def shifted(bag3, tmp_path_factory) -> Path:
    """bag3 (3 clips) with every IMU stamp 50 ms late."""
    types = jazzy_types()

    def edit(topic, t, msg):
        if topic != "/imu0":
            return [(t, msg)]
        msg.header.stamp = ns_to_stamp(stamp_to_ns(msg.header.stamp) + SHIFT_NS, types=types)
        return [(t + SHIFT_NS, msg)]

    return _edited(bag3[1], tmp_path_factory.mktemp("shifted") / "bag", edit, until_ns=2**62)


def _asl(bag3, dst: Path) -> Path:
    return Path(shutil.copytree(bag3[0], dst)) / "mav0"


# ------------------------------------------------------------------------------------------- 5, 6: time offset
def test_kalibr_timeshift_is_the_time_offset_and_a_gyro_failing_run_names_the_likelier_cause(shifted, tmp_path,
                                                                                               capsys):
    # with the calibration as configured (self-calibration would find the offset from the first clip)
    rc, out, err = _replay(capsys, shifted, tmp_path / "a.mcap", "--json", *GATE, "--param", "self_calibration=false")
    summary = json.loads(out)
    assert summary["outcomes"].get("none", 0) >= 2, summary  # rejected by the gyro check: "backbone failure"
    assert "most clips failed the gyro check" in summary["hint"] and "time offset" in summary["hint"]
    assert "T_BS" in summary["hint"]
    camchain = tmp_path / "camchain-imucam.yaml"
    write_kalibr_camchain(replace(EUROC_CAM0, time_offset=SHIFT_NS * 1e-9), camchain)
    rc, out, err = _replay(capsys, shifted, tmp_path / "b.mcap", "--json", *GATE, calib=camchain)
    assert rc == 0 and json.loads(out)["outcomes"] == {"init": 3} and "hint" not in json.loads(out), err
    assert "overrides" not in err
    rc, out, err = _replay(capsys, shifted, tmp_path / "c.mcap", "--param", "time_offset=0.02", *GATE,
                           calib=camchain)
    assert "parameter time_offset = 0.02 s overrides the calibration's timeshift_cam_imu = 0.05 s" in err
    assert str(camchain) in err
    rc, out, err = _vi3(capsys, "eval", shifted, "--calib", _calib_file(tmp_path), "--independent", "--no-progress",
                        "--param", "self_calibration=false")
    assert "most clips failed the gyro check" in out, out


def test_a_mirror_t_bs_is_refused_on_load(bag3, tmp_path, capsys):
    mirror = tmp_path / "mirror.yaml"  # the camera's x axis flipped: orthonormal, determinant -1
    write_euroc_sensor_yaml(replace(EUROC_CAM0, T_BC=EUROC_CAM0.T_BC @ np.diag([-1.0, 1.0, 1.0, 1.0])), mirror)
    rc, _, err = _replay(capsys, bag3[1], tmp_path / "out.mcap", calib=mirror)
    assert rc == 2 and "T_BS is a mirror, not a rotation" in err and "Traceback" not in err


# ------------------------------------------------------------------------------------------- 10: named causes
def test_an_unsorted_or_empty_imu_file_is_named(bag3, tmp_path, capsys):
    mav0 = _asl(bag3, tmp_path / "shuffled")
    path = mav0 / "imu0" / "data.csv"
    header, *rows = path.read_text().splitlines()
    rows = [rows[i] for i in np.random.default_rng(0).permutation(len(rows))]
    path.write_text("\n".join([header, *rows]) + "\n")
    for cmd in (["replay", mav0.parent, "--output", tmp_path / "a.mcap"], ["eval", mav0.parent]):
        rc, _, err = _vi3(capsys, *cmd, "--no-progress")
        assert rc == 2 and "imu0/data.csv: its stamps are not increasing (unsorted" in err, err
    path.write_text(header + "\n")
    for cmd in (["replay", mav0.parent, "--output", tmp_path / "b.mcap"], ["eval", mav0.parent]):
        rc, _, err = _vi3(capsys, *cmd, "--no-progress")
        assert rc == 2 and "imu0/data.csv: no samples (a header and no rows)" in err, err


def test_symbolic_link_loops_are_named(bag3, tmp_path, capsys):
    loop = tmp_path / "loop.mcap"
    loop.symlink_to(loop)
    rc, _, err = _replay(capsys, loop, tmp_path / "a.mcap")
    assert rc == 2 and f"{loop}: is a symbolic link that points to itself (a loop)" in err
    mav0 = _asl(bag3, tmp_path / "asl")
    csv = mav0 / "cam0" / "data.csv"
    csv.unlink()
    csv.symlink_to(csv)
    for cmd in (["replay", mav0.parent, "--output", tmp_path / "b.mcap"], ["eval", mav0.parent]):
        rc, _, err = _vi3(capsys, *cmd, "--no-progress")
        assert rc == 2 and f"{csv}: is a symbolic link that points to itself" in err, err


def test_options_that_do_not_apply_or_name_nothing_are_refused(bag3, tmp_path, capsys):
    asl, src = bag3
    rc, _, err = _replay(capsys, asl, tmp_path / "a.mcap", "--image-topic", "/cam1/image_raw")
    assert rc == 2 and "--image-topic /cam1/image_raw" in err and "is an ASL folder, which has no topics" in err
    rc, _, err = _vi3(capsys, "eval", asl, "--imu-topic", "/imu1", "--no-progress")
    assert rc == 2 and "--imu-topic /imu1" in err and "no topics" in err
    rc, _, err = _vi3(capsys, "replay", src, "--output", "", "--calib", _calib_file(tmp_path))
    assert rc == 2 and "replay output is empty" in err
    rc, _, err = _vi3(capsys, "eval", "--ray", "in/x")
    assert rc == 2 and "'in/x' is not a Ray address" in err and "put --ray after the inputs" in err
    assert "the following arguments are required" not in err


def test_an_imu_topic_of_the_wrong_type_is_not_replaced_silently(bag3, tmp_path, capsys):
    """/imu0 (the parameter's topic) carries geometry_msgs/Vector3Stamped; the IMU is on /imu1."""
    store = jazzy_types().typestore
    Vector3Stamped = store.types["geometry_msgs/msg/Vector3Stamped"]
    dst = tmp_path / "bag"
    with Reader(bag3[1]) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {c.topic: writer.add_connection(c.topic, c.msgtype, typestore=store) for c in reader.connections}
        imu1 = writer.add_connection("/imu1", "sensor_msgs/msg/Imu", typestore=store)
        conns["/imu0"] = writer.add_connection("/imu0", "geometry_msgs/msg/Vector3Stamped", typestore=store)
        for c, t, raw in reader.messages():
            if c.topic == "/imu0":
                imu = store.deserialize_cdr(raw, c.msgtype)
                writer.write(imu1, t, raw)
                raw = store.serialize_cdr(Vector3Stamped(imu.header, imu.angular_velocity),
                                          "geometry_msgs/msg/Vector3Stamped")
            writer.write(conns[c.topic], t, raw)
    rc, _, err = _replay(capsys, dst, tmp_path / "a.mcap")
    assert rc == 2 and "topic '/imu0' has type geometry_msgs/msg/Vector3Stamped, not sensor_msgs/msg/Imu" in err
    assert "/imu1 (sensor_msgs/msg/Imu)" in err and "--imu-topic" in err
    rc, _, err = _replay(capsys, dst, tmp_path / "b.mcap", "--imu-topic", "/imu1")
    assert rc == 0, err


def test_make_bag_that_cannot_fit_on_the_disk_is_refused_before_it_starts(tmp_path, capsys):
    rc, out, err = _vi3(capsys, "make-bag", tmp_path / "huge", "--seconds", "1e9")
    assert rc == 2 and "1e+09 s of sequence need about" in err and "GB free" in err
    assert not (tmp_path / "huge").exists()


# ------------------------------------------------------------------------------------------- 9: streaming
def test_an_asl_folder_is_read_as_a_stream(bag3, tmp_path):
    """600 s of 200 Hz IMU and ground truth rows beside bag3's 51 frames: reading every event holds no more than a
    few frames' worth of memory (the csv files alone are 13 and 42 MB; read whole, their cells took ~10x that)."""
    mav0 = tmp_path / "long" / "mav0"
    mav0.mkdir(parents=True)
    os.symlink(bag3[0] / "mav0" / "cam0", mav0 / "cam0")
    first = int((bag3[0] / "mav0" / "imu0" / "data.csv").read_text().splitlines()[1].split(",")[0])
    ns = first + np.arange(600 * 200, dtype=np.int64) * 5_000_000
    rng = np.random.default_rng(0)
    for folder, columns in (("imu0", 6), ("state_groundtruth_estimate0", 16)):
        (mav0 / folder).mkdir()
        rows = np.column_stack([ns.astype(np.float64), rng.normal(size=(len(ns), columns))])
        np.savetxt(mav0 / folder / "data.csv", rows, delimiter=",", fmt=["%d"] + ["%.17g"] * columns,
                   header=",".join(["#timestamp"] + [f"c{i}" for i in range(columns)]), comments="")
    tracemalloc.start()
    try:
        counts = {ImageEvent: 0, ImuEvent: 0}
        for event in iter_events(mav0.parent):
            counts[type(event)] += 1
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert counts == {ImageEvent: 51, ImuEvent: len(ns)}
    assert peak < 8e6, f"{peak / 1e6:.1f} MB"
