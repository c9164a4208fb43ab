"""ASL -> ROS 1 bag (rosbags) -> rosbag2 MCAP (rosbags' converter) -> one reader: nothing changes on the way."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer

from msg_adapters.imu import samples_to_imus
from vi3_core.dataset.asl import find_mav0, read_asl
from vi3_core.dataset.generate import EUROC_CAM0, cached_sequence
from vi3_core.errors import DataError
from vi3_ros import cli
from vi3_ros.io.convert import convert_to_rosbag2
from vi3_ros.io.reader import BAG_DAMAGE, DropEvent, ImageEvent, ImuEvent, iter_events, merge_by_time, open_sequence
from vi3_ros.io.ros1 import noetic_typestore, ros1_types, write_ros1_bag

pytestmark = pytest.mark.slow  # every test here runs replays, evaluations or generated sequences


def _assert_same(seq, ref, *, gt_velocity_atol: float):
    assert np.array_equal(seq.stamps_ns, ref.stamps_ns)
    assert np.array_equal(seq.imu_ns, ref.imu_ns)
    assert np.array_equal(seq.imu.gyro, ref.imu.gyro) and np.array_equal(seq.imu.accel, ref.imu.accel)
    for i in range(len(ref)):
        assert np.array_equal(seq.image(i), ref.image(i)), i
    assert np.array_equal(seq.gt.t_ns, ref.gt.t_ns)
    np.testing.assert_allclose(seq.gt.T_WB, ref.gt.T_WB, atol=1e-12)
    np.testing.assert_allclose(seq.gt.v_WB, ref.gt.v_WB, atol=gt_velocity_atol)
    assert seq.gt.bg is None and seq.gt_depth(0) is None


def _round_trip(asl, tmp_path, *, gt_velocity_atol):
    ref = read_asl(asl)
    bag = write_ros1_bag(asl, tmp_path / "ros1.bag")
    mcap = convert_to_rosbag2(bag, tmp_path / "mcap")
    sqlite = convert_to_rosbag2(bag, tmp_path / "sqlite", storage="sqlite3")
    assert (mcap / "metadata.yaml").is_file() and "storage_identifier: mcap" in (mcap / "metadata.yaml").read_text()
    bare = next(mcap.glob("*.mcap"))
    for path in (bag, mcap, sqlite, bare):
        seq = open_sequence(path, calib=EUROC_CAM0)
        _assert_same(seq, ref, gt_velocity_atol=gt_velocity_atol)
    return ref, mcap


def test_generated_round_trip(cache_dir, tmp_path):
    ref, mcap = _round_trip(cached_sequence(cache_dir, seconds=2.0, seed=0), tmp_path, gt_velocity_atol=5e-3)
    events = list(iter_events(mcap))
    assert [type(e) for e in events].count(ImageEvent) == len(ref)
    assert [type(e) for e in events].count(ImuEvent) == len(ref.imu)
    stamps = [e.t_ns for e in events]
    assert stamps == sorted(stamps)
    asl_events = list(iter_events(cache_dir / "room_seed0_2s"))
    assert [(type(e), e.t_ns) for e in asl_events] == [(type(e), e.t_ns) for e in events]


def test_real_euroc_fixture_round_trip(euroc_fixture, tmp_path):
    ref, mcap = _round_trip(euroc_fixture.parent, tmp_path, gt_velocity_atol=0.02)
    assert ref.stamps_ns[0] == 1403636579763555584
    seq = open_sequence(mcap, calib=euroc_fixture / "cam0" / "sensor.yaml")
    np.testing.assert_allclose(seq.calib.K, ref.calib.K)


def test_bad_bags_name_the_file_and_the_problem(cache_dir, tmp_path):
    bag = write_ros1_bag(cached_sequence(cache_dir, seconds=2.0, seed=0), tmp_path / "ros1.bag")
    truncated = tmp_path / "truncated.bag"
    truncated.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    with pytest.raises(DataError, match="truncated.bag: cannot read the bag") as info:
        open_sequence(truncated)
    assert "index" in str(info.value).lower() or "truncated" in str(info.value)
    with pytest.raises(DataError, match="does not exist"):
        open_sequence(tmp_path / "missing.bag")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="not an EuRoC ASL folder .*nor a rosbag2 directory"):
        open_sequence(tmp_path / "empty")

    imu_only = tmp_path / "imu_only.bag"
    seq = read_asl(cache_dir / "room_seed0_2s")
    with Writer(imu_only) as writer:
        conn = writer.add_connection("/imu0", "sensor_msgs/msg/Imu", typestore=noetic_typestore())
        for msg, ns in zip(samples_to_imus(seq.imu.select(slice(0, 5)), frame_id="imu4", types=ros1_types()),
                           seq.imu_ns[:5].tolist()):
            writer.write(conn, ns, noetic_typestore().serialize_ros1(msg, conn.msgtype))
    with pytest.raises(DataError, match=r"imu_only.bag: no image topic \(sensor_msgs/msg/Image or "
                       r"sensor_msgs/msg/CompressedImage\); topics: \{'/imu0'"):
        open_sequence(imu_only)
    with pytest.raises(DataError, match=r"topic '/cam1/image_raw' is not in it; image topics \(sensor_msgs/msg/"
                       r"Image or sensor_msgs/msg/CompressedImage\): /cam0/image_raw \(sensor_msgs/msg/Image\)"):
        open_sequence(bag, image_topic="/cam1/image_raw")


def test_an_mcap_recording_cut_short_is_read_as_far_as_its_records_go(cache_dir, tmp_path, capsys):
    """A recording cut short (power lost in flight: no summary, and ros2 bag writes metadata.yaml only when it
    closes) is read record by record, every chunk that ended before the cut, as a bare .mcap, as a rosbag2 folder and
    as a folder without metadata.yaml, also when the file system left its end zeroed; a damaged chunk is skipped and
    the rest read. A last DropEvent (``bag_truncated``, ``bag_damaged``) says what was lost, replay tells it on stderr
    and counts it, and evaluation, which takes whole recordings, refuses it naming the cause."""
    from mcap.reader import make_reader

    asl = cached_sequence(cache_dir, seconds=2.0, seed=0)
    mcap = convert_to_rosbag2(write_ros1_bag(asl, tmp_path / "ros1.bag"), tmp_path / "mcap")
    data = next(mcap.glob("*.mcap"))
    whole = list(iter_events(data))
    with data.open("rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    raw = data.read_bytes()
    at = len(raw) // 2
    complete = [c for c in chunks if c.chunk_start_offset + c.chunk_length <= at]
    assert 2 <= len(complete) < len(chunks)

    def read_all_of(kept, events) -> None:
        """``events`` are ``whole``'s in order, those of the chunks ``kept`` and no others (the converter logs each
        message at its stamp; a stamp shared by two chunks' messages may come from either)."""
        inside = [any(c.message_start_time <= e.t_ns <= c.message_end_time for c in kept) for e in whole]
        sure = [any(c.message_start_time < e.t_ns < c.message_end_time for c in kept) for e in whole]
        assert all(any((type(g), g.t_ns) == (type(w), w.t_ns) for w, i in zip(whole, inside) if i) for g in events)
        assert sum(sure) <= len(events) <= sum(inside)
        by_stamp = {(type(w), w.t_ns): w for w in whole}
        assert all(np.array_equal(g.image, by_stamp[type(g), g.t_ns].image) for g in events
                   if isinstance(g, ImageEvent))

    bare, zeroed, crashed = tmp_path / "cut.mcap", tmp_path / "zeroed.mcap", tmp_path / "crashed"
    bare.write_bytes(raw[:at])
    zeroed.write_bytes(raw[:at] + bytes(1 << 20))  # past the cut, a file system's zeroed blocks
    crashed.mkdir()
    (crashed / data.name).write_bytes(raw[:at])
    data.write_bytes(raw[:at])  # the rosbag2 folder with the metadata.yaml of the whole recording
    for path in (bare, zeroed, crashed, mcap):
        *events, last = list(iter_events(path))
        assert isinstance(last, DropEvent) and last.reason == "bag_truncated", last
        assert "has no summary and its records end early" in last.detail and "messages read" in last.detail
        read_all_of(complete, events)
        assert [(type(e), e.t_ns) for e in events] == [(type(e), e.t_ns) for e in whole[:len(events)]], path
    hole = bytearray(raw)  # chunk 1 damaged, its framing intact: its CRC (after opcode, length, times, size) is wrong
    c = chunks[1]
    hole[c.chunk_start_offset + 33: c.chunk_start_offset + 37] = (1).to_bytes(4, "little")
    holed = tmp_path / "holed.mcap"
    holed.write_bytes(bytes(hole[:at]))
    *events, last = list(iter_events(holed))
    assert last.reason == "bag_truncated" and "1 damaged chunk(s) skipped" in last.detail, last
    read_all_of([k for k in complete if k is not c], events)
    with pytest.raises(DataError, match="cut.mcap has no summary .*evaluation takes whole recordings"):
        open_sequence(bare)
    closed = bytearray(raw)  # the recording closed, but its summary (between DataEnd and the footer) zeroed
    footer = len(raw) - 8 - 29  # the footer record: opcode, length, two offsets and a CRC, before the end magic
    closed[footer - 200: footer] = bytes(200)
    data.write_bytes(bytes(closed))  # rosbags raised MemoryError reading it
    *events, last = list(iter_events(mcap))
    assert [(type(e), e.t_ns) for e in events] == [(type(e), e.t_ns) for e in whole] and last.reason in BAG_DAMAGE
    data.write_bytes(raw[:at])
    header = tmp_path / "header.mcap"
    header.write_bytes(raw[:30])
    with pytest.raises(DataError, match=r"no image topic .*header.mcap has no summary and its records end early"):
        list(iter_events(header))
    (crashed / "second.mcap").write_bytes(raw[:at])  # a split recording cut short: which file is which is not known
    with pytest.raises(DataError, match=r"no metadata.yaml\) and holds 2 .mcap files: give them one at a time"):
        open_sequence(crashed)
    (crashed / "second.mcap").unlink()
    poses = tmp_path / "poses.tum"
    poses.write_text("".join(f"{e.t_ns * 1e-9:.9f} 0 0 {i * 0.01} 0 0 0 1\n"
                             for i, e in enumerate(w for w in whole if isinstance(w, ImageEvent))))
    capsys.readouterr()
    calib = find_mav0(asl) / "cam0" / "sensor.yaml"
    assert cli.main(["reference", str(bare), "--poses", str(poses), "--calib", str(calib),
                     "-o", str(tmp_path / "ref.tum")]) == 2
    assert "cut.mcap has no summary" in capsys.readouterr().err and not (tmp_path / "ref.tum").exists()
    rc = cli.main(["replay", str(crashed), "--output", str(tmp_path / "out.mcap"), "--calib", str(calib),
                   "--no-progress"])
    out, err = capsys.readouterr()
    assert rc != 2 and "'bag_truncated': 1" in out, (rc, out, err)  # the input was taken (1: no clip had a result)
    assert f"vi3 replay: the MCAP file {crashed / data.name} has no summary" in err and "Traceback" not in err


def test_make_bag_is_deterministic_and_opens(tmp_path):
    outs = [tmp_path / "a", tmp_path / "b"]
    for out in outs:
        assert cli.main(["make-bag", str(out), "--seconds", "0.3", "--seed", "2", "--no-depth"]) == 0
    a, b = outs
    for out in outs:
        assert (out / "asl" / "mav0" / "cam0" / "sensor.yaml").is_file() and (out / "ros1.bag").is_file()
        assert (out / "mcap" / "metadata.yaml").is_file() and (out / "camchain-imucam.yaml").is_file()
    pngs = sorted((a / "asl" / "mav0" / "cam0" / "data").glob("*.png"))
    assert len(pngs) == 7
    for png in pngs:
        assert png.read_bytes() == (b / png.relative_to(a)).read_bytes()
    imu = "asl/mav0/imu0/data.csv"
    assert (a / imu).read_text() == (b / imu).read_text()
    seq = open_sequence(a)  # a make-bag folder opens as its MCAP, with the camchain beside it
    np.testing.assert_allclose(seq.calib.T_BC, EUROC_CAM0.T_BC, atol=1e-12)
    assert np.array_equal(seq.image(6), read_asl(a / "asl").image(6))
    assert cli.main(["make-bag", str(a), "--seconds", "0.3", "--seed", "3", "--no-depth"]) == 2
    assert cli.main(["make-bag", str(a), "--seconds", "0.3", "--seed", "3", "--no-depth", "--overwrite"]) == 0
    assert (a / pngs[0].relative_to(a)).read_bytes() != (b / pngs[0].relative_to(a)).read_bytes()


#: How far data generated on another CPU may be from this one's (the bundled bag was made on one machine and is
#: regenerated on any): NumPy's SIMD dispatch and the BLAS kernels give other last bits on a CPU without AVX-512 (seen:
#: gyro up to 4.4e-16 rad/s, accelerometer 3.6e-15 m/s^2, GT poses 5.6e-16), so floats get 1e-12 absolute on values of
#: order 1-10; an image may differ by one grey level where the rendering lands on a rounding boundary, in at most one
#: pixel in 10^4 (none seen). Stamps (integer ns) stay exact.
CROSS_CPU_ATOL = 1e-12
CROSS_CPU_PIXELS = 1e-4


def test_bundled_bag_is_the_make_bag_sequence(cache_dir):
    """bags/vi3_demo is the MCAP of ``vi3 make-bag --seconds 1.8 --seed 0``: regenerating it on any CPU gives the same
    data, within CROSS_CPU_ATOL and CROSS_CPU_PIXELS."""
    path = Path(__file__).resolve().parents[2] / "bags" / "vi3_demo"
    seq = open_sequence(path)
    assert sum(f.stat().st_size for f in path.parent.rglob("*") if f.is_file()) <= 15e6
    assert len(seq) == 37 and seq.calib is not None and seq.gt is not None
    fresh = read_asl(cached_sequence(cache_dir, seconds=1.8, seed=0, with_depth=False))
    assert np.array_equal(seq.stamps_ns, fresh.stamps_ns) and np.array_equal(seq.imu_ns, fresh.imu_ns)
    np.testing.assert_allclose(seq.imu.gyro, fresh.imu.gyro, rtol=0, atol=CROSS_CPU_ATOL)
    np.testing.assert_allclose(seq.imu.accel, fresh.imu.accel, rtol=0, atol=CROSS_CPU_ATOL)
    np.testing.assert_allclose(seq.gt.T_WB, fresh.gt.T_WB, rtol=0, atol=CROSS_CPU_ATOL)
    for i in (0, 18, 36):
        diff = np.abs(seq.image(i).astype(np.int16) - fresh.image(i))
        assert diff.max() <= 1 and np.count_nonzero(diff) <= CROSS_CPU_PIXELS * diff.size, i


def test_merge_by_time_is_the_record_order():
    """ASL streams (frames, IMU, ground truth) merge by stamp, ties by stream then index, as bags record them."""
    rng = np.random.default_rng(0)
    streams = [np.sort(rng.integers(0, 50, size=n)) for n in (7, 30, 12)]
    expected = sorted((int(ns), k, i) for k, s in enumerate(streams) for i, ns in enumerate(s))
    assert list(merge_by_time(*streams)) == expected
    one = [(int(ns), 1, i) for i, ns in enumerate(streams[0])]
    assert list(merge_by_time(np.zeros(0, np.int64), streams[0])) == one
