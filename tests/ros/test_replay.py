"""`vi3 replay` end to end on generated sequences converted the way users convert bags (ASL -> ROS 1 bag ->
rosbags-convert -> rosbag2 MCAP), and every fault of issue 7 made by editing such a bag through rosbags.

Each fault bag is a real bag with one edit; replaying it must skip or flag the affected clip with a named reason on
~/status and /diagnostics while the following clips still produce metric output.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Reader as Ros1Reader
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from msg_adapters.camera_info import calib_to_camera_info
from msg_adapters.diagnostics import diagnostic_array_to_statuses
from msg_adapters.image import image_to_numpy
from msg_adapters.pointcloud import point_cloud2_to_numpy
from msg_adapters.poses import poses_to_T, tf_message, transform_stamped
from msg_adapters.stamps import ns_to_stamp, stamp_to_ns
from msg_adapters.types import jazzy_types
from vi3_core.backbones import make_backbone
from vi3_core.backbones.recorded import RecordedBackbone, Recording, RecordingBackbone
from vi3_core.dataset.asl import read_asl
from vi3_core.dataset.calib import write_euroc_sensor_yaml
from vi3_core.dataset.generate import EUROC_CAM0, cached_sequence, generation_tag
from vi3_core.eval.metrics import scale_traj
from vi3_ros.cli import main as vi3_main
from vi3_ros.io.convert import convert_to_rosbag2
from vi3_ros.io.ros1 import ros1_types, write_ros1_bag
from vi3_ros.params import resolve
from vi3_ros.replay import replay
from vi3_ros.replay_bench import bench_pipeline, bench_replay

pytestmark = pytest.mark.slow  # every test here runs replays, evaluations or generated sequences

CLIP_HOP = 14  # input frames between clip starts: clip_length 8 x stride 2, each sharing its first frame with the last
CLIP_FRAMES = np.arange(0, 16, 2)  # a clip's frames from its start


def _publish_atomically(dst: Path, build: Callable[[Path], None]) -> Path:
    """Build into a temporary sibling and rename (safe when two test processes race)."""
    if dst.exists():
        return dst
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.", dir=dst.parent))
    try:
        build(tmp / dst.name)
        try:
            os.rename(tmp / dst.name, dst)
        except OSError:
            if not dst.exists():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dst


def _converted_bag(cache_dir: Path, *, seconds: float, seed: int) -> tuple[Path, Path]:
    """(ASL folder, rosbag2 MCAP directory) of a generated sequence, cached."""
    asl = cached_sequence(cache_dir, seconds=seconds, seed=seed, with_depth=False)
    folder = cache_dir / f"replay_{asl.name}_{generation_tag(asl)}"
    folder.mkdir(exist_ok=True)
    bag = _publish_atomically(folder / "seq.bag", lambda p: write_ros1_bag(asl, p))
    return asl, _publish_atomically(folder / "mcap", lambda p: convert_to_rosbag2(bag, p))


def _edited(src: Path, dst: Path, edit: Callable[[str, int, object], list[tuple[int, object]]], *,
            until_ns: int, extra: dict[str, str] | None = None, extra_msgs: list[tuple[str, int, object]] = ()) -> Path:
    """Copy the rosbag2 ``src`` up to log time ``until_ns`` to ``dst`` (MCAP) through rosbags, passing every message
    through ``edit(topic, t_ns, msg) -> [(t_ns, msg), ...]``; ``extra`` adds topics (name -> type) whose
    ``extra_msgs`` are merged by time."""
    store = jazzy_types().typestore
    with Reader(src) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {c.topic: writer.add_connection(c.topic, c.msgtype, typestore=store) for c in reader.connections}
        conns.update({t: writer.add_connection(t, ty, typestore=store) for t, ty in (extra or {}).items()})
        out = [(t, topic, msg) for topic, t, msg in extra_msgs]
        for c, t, raw in reader.messages(stop=until_ns + 1):
            out += [(t2, c.topic, m) for t2, m in edit(c.topic, t, store.deserialize_cdr(raw, c.msgtype))]
        for t, topic, msg in sorted((e for e in out if e[0] <= until_ns), key=lambda e: e[0]):
            writer.write(conns[topic], t, store.serialize_cdr(msg, conns[topic].msgtype))
    return dst


def _read(path: Path) -> dict[str, list]:
    """Topic -> deserialised messages (rosbags)."""
    out: dict[str, list] = {}
    with AnyReader([path], default_typestore=jazzy_types().typestore) as reader:
        for c, _, raw in reader.messages():
            out.setdefault(c.topic, []).append(reader.deserialize(raw, c.msgtype))
    return out


def _statuses(msgs: dict[str, list], topic: str = "/vi3_node/status"):
    return [s for m in msgs.get(topic, []) for s in diagnostic_array_to_statuses(m)]


#: The fault and plumbing tests below check what replay does with a clip, not which clips may claim a scale (the
#: error model's gate, tests/core/test_init.py and tests/core/test_online.py): on 2.5 s bags of two clips the gate
#: stays open.
OPEN_GATE = {"max_scale_sigma": 10.0}


def _run(inp: Path, out: Path, **params) -> tuple[object, dict[str, list]]:
    settings = resolve({"calib_file": str(params.pop("calib", _calib_file(out.parent))), **OPEN_GATE, **params})
    summary = replay(inp, out, settings=settings, progress=False)
    return summary, _read(summary.output)  # OUT, or OUT.partial.mcap when no clip produced a result


def _calib_file(folder: Path) -> Path:
    path = folder / "cam0_sensor.yaml"
    if not path.exists():
        write_euroc_sensor_yaml(EUROC_CAM0, path)
    return path


@pytest.fixture(scope="module")
def bag4(cache_dir):
    return _converted_bag(cache_dir, seconds=4.0, seed=0)


@pytest.fixture(scope="module")
def bag3(cache_dir):
    return _converted_bag(cache_dir, seconds=2.5, seed=1)


@pytest.fixture(scope="module")
def e2e(bag4, tmp_path_factory):
    asl, mcap = bag4
    tmp = tmp_path_factory.mktemp("e2e")
    rc = vi3_main(["replay", str(mcap), "--output", str(tmp / "out.mcap"), "--calib", str(_calib_file(tmp)),
                   "--backbone", "classical", "--mode", "init", "--no-progress", "--param", "depth_frames=all"])
    assert rc == 0
    return asl, mcap, tmp / "out.mcap"


def test_end_to_end_output_readable_by_rosbags_and_mcap(e2e):
    asl, _, out = e2e
    seq = read_asl(asl)
    msgs = _read(out)
    poses = msgs["/vi3_node/poses"]
    n_clips = sum(start + CLIP_FRAMES[-1] < len(seq.stamps) for start in range(0, len(seq.stamps), CLIP_HOP))
    statuses = _statuses(msgs)
    claimed = [int(s.values["clip"]) for s in statuses if s.values["result"] == "init"]
    # One PoseArray per claimed clip; a clip is claimed once the online window's error model supports its scale
    # (the first clip of a stream, on its own, rarely is), and says why not otherwise.
    assert len(statuses) == n_clips == 5 and len(poses) == len(claimed) >= n_clips - 2
    assert all(s.values["init_status"] == "ok" or "relative sigma" in s.values["reason"] for s in statuses)
    # where the front end lost its tracks, per clip: the shared frame counted by the clip that tracked it
    assert [s.values["front_end"].split(" frames")[0] for s in statuses] == ["8", "7", "7", "7", "7"], statuses[0]
    scales = []
    for k, pa in zip(claimed, poses):
        idx = k * CLIP_HOP + CLIP_FRAMES
        assert stamp_to_ns(pa.header.stamp) == seq.stamps_ns[idx[-1]] and pa.header.frame_id == "vi3_clip"
        T = poses_to_T(pa.poses)
        np.testing.assert_allclose(T[0], np.eye(4), atol=1e-6)
        scales.append(scale_traj(T, seq.gt.at(seq.stamps[idx]).T_WB @ seq.calib.T_BC))
    assert 0.9 <= np.median(scales) <= 1.1, scales  # Scale (Traj.) of the fast path: metric
    depth = msgs["/vi3_node/depth"]
    assert len(depth) == 8 * len(claimed) and {d.encoding for d in depth} == {"32FC1"}
    first = claimed[0] * CLIP_HOP
    assert [stamp_to_ns(d.header.stamp) for d in depth[:8]] == seq.stamps_ns[first + CLIP_FRAMES].tolist()
    d0 = image_to_numpy(depth[0])
    assert d0.dtype == np.float32 and np.nanmedian(d0) > 0.3
    for pc in msgs["/vi3_node/points"]:
        cloud = point_cloud2_to_numpy(pc)
        assert cloud.dtype.names == ("x", "y", "z", "confidence") and pc.point_step == 16
        assert pc.height == 1 and pc.width == len(cloud) > 100 and pc.row_step == 16 * pc.width
        assert np.isfinite(cloud["z"]).all()
    assert all(float(s.values["scale"]) > 0 for s in statuses if s.values["result"] == "init")
    # one ~/odom per clip placed in odom: every claimed clip, and those at the window's scale the status names
    placed = [(s.values["result"], s.values["odom"]) for s in statuses]
    assert all(odom == "claimed" for result, odom in placed if result == "init"), placed
    assert all(odom in ("window scale, not claimed", "not placed") for result, odom in placed if result != "init")
    assert len(msgs["/vi3_node/odom"]) == sum(odom != "not placed" for _, odom in placed)
    assert "/diagnostics" in msgs
    # the same file through mcap + mcap-ros2-support
    with out.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        decoded = [(ch.topic, m) for _, ch, _, m in reader.iter_decoded_messages()]
    topics = {t for t, _ in decoded}
    assert {"/vi3_node/poses", "/vi3_node/depth", "/vi3_node/points", "/vi3_node/status"} <= topics
    first = next(m for t, m in decoded if t == "/vi3_node/poses")
    np.testing.assert_allclose([first.poses[-1].position.x, first.poses[-1].position.z],
                               [poses[0].poses[-1].position.x, poses[0].poses[-1].position.z])


def test_depth_comes_with_the_camera_info_that_back_projects_it_onto_the_points(e2e):
    """Issue 25: ~/depth had no CameraInfo for its intrinsics (undistorted, at the backbone's resolution), so
    depth_image_proc and RViz could not back-project it. ~/depth/camera_info: one per depth image, same stamp and
    frame, no distortion, P = [K | 0]; back-projected with it, the last frame's depth gives the clip's ~/points."""
    _, _, out = e2e
    msgs = _read(out)
    depth, info = msgs["/vi3_node/depth"], msgs["/vi3_node/depth/camera_info"]
    assert len(info) == len(depth) > 0
    for d, ci in zip(depth, info):
        assert (stamp_to_ns(ci.header.stamp), ci.header.frame_id) == (stamp_to_ns(d.header.stamp), d.header.frame_id)
        assert (ci.width, ci.height) == (d.width, d.height) and ci.distortion_model == "plumb_bob"
        assert not np.any(ci.d) and np.array_equal(np.reshape(ci.p, (3, 4))[:, :3], np.reshape(ci.k, (3, 3)))
    pa, cloud = msgs["/vi3_node/poses"][0], point_cloud2_to_numpy(msgs["/vi3_node/points"][0])
    last = 7  # the first claimed clip's 8 depth images come first (depth_frames all), its last frame last
    assert depth[last].header.stamp == pa.header.stamp
    z = image_to_numpy(depth[last]).astype(np.float64)
    v, u = np.mgrid[0:z.shape[0], 0:z.shape[1]]
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(np.reshape(info[last].k, (3, 3))).T
    T = poses_to_T(pa.poses)[-1]  # the last camera in the clip frame
    P = (rays * z[..., None]).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    pts = np.stack([cloud["x"], cloud["y"], cloud["z"]], -1).astype(np.float64)
    nearest = np.array([np.min(np.linalg.norm(P - p, axis=1)) for p in pts[::50]])
    assert np.all(nearest < 1e-3 * np.maximum(np.linalg.norm(pts[::50], axis=1), 1.0))


def test_replay_is_deterministic_and_refined_results_follow_init(bag3, tmp_path):
    """Two replays of one bag in ttr mode (a few steps): identical messages; each clip's fast init result comes
    first on ~/init/*, then the refined one on ~/poses etc., and ~/status says which is which."""
    asl, src = bag3
    mcap = _edited(src, tmp_path / "cut", lambda topic, t, m: [(t, m)], until_ns=_two_clips(asl))
    runs = []
    for name in ("a.mcap", "b.mcap"):
        assert vi3_main(["replay", str(mcap), "--output", str(tmp_path / name), "--calib", str(_calib_file(tmp_path)),
                         "--mode", "ttr", "--no-progress", "--param", "ttr_steps=2", "--param", "publish_tf=true",
                         "--param", "max_scale_sigma=10"]) == 0
        runs.append(_read(tmp_path / name))
    a, b = runs
    assert a.keys() == b.keys()
    store = jazzy_types().typestore
    for topic in a:
        assert len(a[topic]) == len(b[topic]), topic
        for ma, mb in zip(a[topic], b[topic]):
            if topic.endswith(("status", "diagnostics")):  # wall-clock latencies and timings differ, nothing else
                strip = [[{k: v for k, v in s.values.items() if not k.startswith(("latency", "timing"))}
                          for s in diagnostic_array_to_statuses(m)] for m in (ma, mb)]
                assert strip[0] == strip[1], topic
            else:
                msgtype = type(ma).__msgtype__
                assert bytes(store.serialize_cdr(ma, msgtype)) == bytes(store.serialize_cdr(mb, msgtype)), topic
    results = [(s.values["clip"], s.values["result"]) for s in _statuses(a)]
    assert results == [(str(k), r) for k in range(2) for r in ("init", "ttr")]
    assert len(a["/vi3_node/init/poses"]) == len(a["/vi3_node/poses"]) == len(a["/tf"]) == 2
    assert all("loss_" in " ".join(s.values) for s in _statuses(a) if s.values["result"] == "ttr")


# ----------------------------------------------------------------------------------------------------- faults
def _outcomes(msgs) -> list[tuple[str, str, str]]:
    return [(s.values["clip"], s.values["result"], s.values["reason"]) for s in _statuses(msgs)]


def _assert_recovers(msgs, after_clip: int) -> None:
    """Some clip after ``after_clip`` produced metric output."""
    ok = [int(s.values["clip"]) for s in _statuses(msgs) if s.values["result"] == "init"]
    assert any(k > after_clip for k in ok), _outcomes(msgs)
    assert len(msgs["/vi3_node/poses"]) == len(ok)


def _diag_messages(msgs) -> list[str]:
    return [s.message for s in _statuses(msgs, "/diagnostics")]


def _clip_window(asl: Path, clip: int) -> tuple[int, int]:
    """First and last frame stamps (ns) of clip ``clip`` of the unedited sequence."""
    seq = read_asl(asl)
    idx = clip * CLIP_HOP + CLIP_FRAMES
    return int(seq.stamps_ns[idx[0]]), int(seq.stamps_ns[idx[-1]])


def _two_clips(asl: Path) -> int:
    """Fault bags are cut after the second clip (and its IMU margin): the faulty clip and one to recover on."""
    return _clip_window(asl, 1)[1] + 60_000_000


def test_fault_imu_gap_inside_clip(bag3, tmp_path):
    asl, src = bag3
    t0, t1 = _clip_window(asl, 0)
    mid = (t0 + t1) // 2
    bag = _edited(src, tmp_path / "gap", lambda topic, t, m: [] if topic == "/imu0" and mid <= t < mid + 100_000_000
                  else [(t, m)], until_ns=_two_clips(asl))
    summary, msgs = _run(bag, tmp_path / "out.mcap")
    first = _statuses(msgs)[0]
    assert first.values["result"] == "none" and first.values["init_status"] == "rejected"
    assert "IMU gap" in first.values["reason"] and first.level == 2
    assert any("IMU gap" in m for m in _diag_messages(msgs))
    _assert_recovers(msgs, 0)


def test_fault_nan_imu_samples(bag3, tmp_path):
    asl, src = bag3
    t0, t1 = _clip_window(asl, 0)

    def nan(topic, t, m):
        if topic == "/imu0" and t0 < t < t0 + 30_000_000:
            m.linear_acceleration.y = float("nan")
        return [(t, m)]

    summary, msgs = _run(_edited(src, tmp_path / "nan", nan, until_ns=_two_clips(asl)), tmp_path / "out.mcap")
    first = _statuses(msgs)[0]
    assert first.values["init_status"] == "rejected" and "NaN" in first.values["reason"]
    assert any("NaN" in m for m in _diag_messages(msgs))
    _assert_recovers(msgs, 0)


def test_fault_dropped_frames(bag3, tmp_path):
    """Issue 25: a lost frame the stride skips (frame 5) changes nothing, a lost frame the clip needs (frame 8) is
    replaced by the next (frame 9); neither throws the clip away (each used to be a frame_gap), both are counted."""
    asl, src = bag3
    t0, t1 = _clip_window(asl, 0)
    lost = {t0 + 5 * 50_000_000, t0 + 8 * 50_000_000}
    bag = _edited(src, tmp_path / "drop", lambda topic, t, m: [] if topic == "/cam0/image_raw" and t in lost
                  else [(t, m)], until_ns=_clip_window(asl, 2)[1] + 60_000_000)
    summary, msgs = _run(bag, tmp_path / "out.mcap")
    assert summary.drops == {"image_lost": 2} and "frame_gap" not in summary.drops
    assert any("image_lost: 1 frame(s) missing" in m for m in _diag_messages(msgs))
    first = _statuses(msgs)[0]
    assert first.values["result"] == "init" and "image_lost:2" in first.values["input_drops"]
    assert (first.values["t_first"], first.values["t_last"]) == (f"{t0 * 1e-9:.9f}", f"{t1 * 1e-9:.9f}")
    poses = msgs["/vi3_node/poses"][0]
    assert stamp_to_ns(poses.header.stamp) == t1 and len(poses.poses) == 8
    _assert_recovers(msgs, 0)


def test_time_going_back_for_good_resets_the_stream_and_it_goes_on(bag3, tmp_path):
    """Issue 25: the same seconds again with the same stamps (``ros2 bag play --loop``, a restarted driver or
    simulator) were all dropped as out of order while /diagnostics said imu_odom: running. The lasting jump back is
    detected, named on /diagnostics and in the next status, the buffers, the window and ~/odom/imu start over, and the
    second pass is processed like the first, in a new odom segment."""
    asl, src = bag3
    seq = read_asl(asl)
    span = int(max(seq.stamps_ns[-1], seq.imu_ns[-1]) - min(seq.stamps_ns[0], seq.imu_ns[0])) + 5_000_000
    bag = _edited(src, tmp_path / "loop", lambda topic, t, m: [(t, m), (t + span, m)], until_ns=2**62)
    summary, msgs = _run(bag, tmp_path / "out.mcap")
    assert summary.drops["time_reset"] == 1
    assert any(m.startswith("time_reset: imu stamps went back") for m in _diag_messages(msgs))
    statuses = sorted(_statuses(msgs), key=lambda st: int(st.values["clip"]))
    first_pass = [st for st in statuses if st.values.get("odom_segment") == "0"]
    second = [st for st in statuses if int(st.values["clip"]) >= len(first_pass)]
    assert len(first_pass) == 3 and len(second) >= 2, _outcomes(msgs)
    assert all(st.values["result"] == "init" and st.values.get("odom_segment") == "1" for st in second), \
        _outcomes(msgs)
    assert "time_reset:1" in second[0].values["input_drops"]
    assert "reset: time went back (imu stamps went back" in second[0].values["online"]
    assert float(second[0].values["t_first"]) < float(first_pass[-1].values["t_first"])
    imu_odom = [stamp_to_ns(m.header.stamp) for m in msgs["/vi3_node/odom/imu"]]
    assert len(set(imu_odom)) < len(imu_odom)  # the second pass published its own IMU-rate odometry
    last = _statuses(msgs, "/diagnostics")[-1].values
    assert last["imu_odom"] == "running" and last["drop_time_reset"] == "1"


def test_fault_out_of_order_stamps(bag3, tmp_path):
    asl, src = bag3
    t0, _ = _clip_window(asl, 0)
    late = t0 + 3 * 50_000_000

    def swap(topic, t, m):  # frame 3 arrives again after frame 4, and an IMU sample is repeated late
        if topic == "/cam0/image_raw" and t == late + 50_000_000:
            store = jazzy_types().typestore
            old = store.deserialize_cdr(store.serialize_cdr(m, "sensor_msgs/msg/Image"), "sensor_msgs/msg/Image")
            old.header.stamp = ns_to_stamp(late, types=jazzy_types())
            return [(t, m), (t + 1, old)]
        if topic == "/imu0" and t == late:
            return [(t, m), (t + 10_000_000, m)]
        return [(t, m)]

    summary, msgs = _run(_edited(src, tmp_path / "ooo", swap, until_ns=_two_clips(asl)), tmp_path / "out.mcap")
    assert summary.drops["image_out_of_order"] == 1 and summary.drops["imu_out_of_order"] == 1
    first = _statuses(msgs)[0]
    assert "image_out_of_order:1" in first.values["input_drops"] and first.level == 1  # flagged
    assert any("image_out_of_order" in m for m in _diag_messages(msgs))
    _assert_recovers(msgs, 0)


def test_fault_stationary_stretch(bag3, tmp_path):
    asl, src = bag3
    seq = read_asl(asl)
    t0, t1 = _clip_window(asl, 0)
    T_WB = seq.gt.at(np.array([t0 * 1e-9])).T_WB[0]
    f_B = T_WB[:3, :3].T @ np.array([0.0, 0.0, 9.81])  # specific force at rest
    frozen = {}

    def still(topic, t, m):  # the drone hovers motionless over clip 0: one repeated image, gravity-only IMU
        if t > t1 + 20_000_000:
            return [(t, m)]
        if topic == "/cam0/image_raw":
            frozen.setdefault("data", m.data.copy())
            m.data = frozen["data"]
        elif topic == "/imu0":
            m.angular_velocity.x = m.angular_velocity.y = m.angular_velocity.z = 0.0
            m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z = map(float, f_B)
        return [(t, m)]

    # cut after the third clip: the second shares the frozen frame (an image of the start at a later pose)
    summary, msgs = _run(_edited(src, tmp_path / "still", still, until_ns=_clip_window(asl, 2)[1] + 60_000_000),
                         tmp_path / "out.mcap")
    first = _statuses(msgs)[0]
    # The clip publishes no geometry, says why on ~/status and /diagnostics, and the stream goes on.
    assert (first.values["result"], first.values.get("init_status")) == ("none", "unobservable"), first.values
    assert "unobservable" in first.values["reason"]
    assert first.level >= 1 and first.values["reason"]
    assert any(first.values["reason"] in m for m in _diag_messages(msgs))
    assert "/vi3_node/poses" in msgs, _outcomes(msgs)
    assert stamp_to_ns(msgs["/vi3_node/poses"][0].header.stamp) > t1
    _assert_recovers(msgs, 0)


def test_fault_missing_calibration_then_camera_info(bag3, tmp_path):
    """No calibration file: clips before the first CameraInfo are skipped with calibration_missing; /tf_static gives
    T_BC and CameraInfo the intrinsics, exactly as the node subscribes to them; later clips produce output."""
    asl, src = bag3
    t0, t1 = _clip_window(asl, 1)
    types = jazzy_types()
    c = EUROC_CAM0
    info = [("/cam0/camera_info", t, calib_to_camera_info(c.K, "plumb_bob", np.r_[c.dist, 0.0], c.size, stamp_ns=t,
                                                          frame_id="cam0", types=types))
            for t in range(t0 + 20_000_000, t1 + 2_000_000_000, 50_000_000)]  # after clip 0 (its last frame is t0)
    tf = tf_message([(c.T_BC, "imu0", "cam0", t0 - 50 * 10**9)], types=types)
    first_t = int(read_asl(asl).imu_ns[0])
    bag = _edited(src, tmp_path / "calib", lambda topic, t, m: [(t, m)], until_ns=_two_clips(asl),
                  extra={"/cam0/camera_info": "sensor_msgs/msg/CameraInfo", "/tf_static": "tf2_msgs/msg/TFMessage"},
                  extra_msgs=info + [("/tf_static", first_t, tf)])
    summary, msgs = _run(bag, tmp_path / "out.mcap", calib="", camera_info_topic="/cam0/camera_info",
                         use_tf_static=True)
    first = _statuses(msgs)[0]
    assert first.values["result"] == "skipped" and first.values["reason"] == "calibration_missing"
    assert "CameraInfo" in first.values["detail"]
    assert any("calibration_missing" in m for m in _diag_messages(msgs))
    _assert_recovers(msgs, 0)


# -------------------------------------------------------------------------------------------- input forms
def _ros1_with_calibration(src: Path, dst: Path, *, until_ns: int) -> Path:
    """The ROS 1 bag ``src`` up to log time ``until_ns`` plus, as a ROS 1 driver records them, ``/tf_static``
    (imu0 -> cam0 = EUROC_CAM0's T_BC) and ``sensor_msgs/CameraInfo`` with ROS 1 field names (D, K, R, P) on
    /cam0/camera_info, one per frame from the first frame on."""
    store = get_typestore(Stores.ROS1_NOETIC)  # a fresh one: TFMessage is registered here only
    store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    types, c = ros1_types(), EUROC_CAM0
    with Ros1Reader(src) as reader, Ros1Writer(dst) as writer:
        conns = {conn.topic: writer.add_connection(conn.topic, conn.msgtype, typestore=store)
                 for conn in reader.connections}
        info = writer.add_connection("/cam0/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store)
        tf = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=store)
        first = True
        for conn, t, raw in reader.messages(stop=until_ns + 1):
            if first:
                msg = store.types["tf2_msgs/msg/TFMessage"](transforms=[transform_stamped(
                    c.T_BC, parent="imu0", child="cam0", stamp_ns=t, types=types)])
                writer.write(tf, t, store.serialize_ros1(msg, tf.msgtype))
                first = False
            if conn.topic == "/cam0/image_raw":
                header = store.types["std_msgs/msg/Header"](seq=0, stamp=ns_to_stamp(t, types=types), frame_id="cam0")
                roi = store.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                                      do_rectify=False)
                msg = store.types["sensor_msgs/msg/CameraInfo"](
                    header=header, height=c.size[1], width=c.size[0], distortion_model="plumb_bob",
                    D=np.r_[c.dist, 0.0], K=c.K.reshape(9), R=np.eye(3).reshape(9),
                    P=np.c_[c.K, np.zeros(3)].reshape(12), binning_x=0, binning_y=0, roi=roi)
                writer.write(info, t, store.serialize_ros1(msg, info.msgtype))
            writer.write(conns[conn.topic], t, raw)
    return dst


@pytest.fixture(scope="module")
def calibrated_inputs(bag3, tmp_path_factory):
    """One clip of the 2.5 s sequence with CameraInfo and /tf_static in every form the reader takes: ROS 1 bag,
    rosbag2 directory (converted by rosbags), its bare .mcap file and a make-bag folder (OUT/mcap/)."""
    asl, src = bag3
    tmp = tmp_path_factory.mktemp("calibrated")
    ros1 = _ros1_with_calibration(src.parent / "seq.bag", tmp / "ros1.bag", until_ns=_clip_window(asl, 0)[1]
                                  + 60_000_000)
    rosbag2 = convert_to_rosbag2(ros1, tmp / "make_bag" / "mcap")
    return {"ros1": ros1, "rosbag2": rosbag2, "mcap_file": next(rosbag2.glob("*.mcap")), "make_bag": rosbag2.parent}


@pytest.mark.parametrize("form", ["ros1", "rosbag2", "mcap_file", "make_bag"])
def test_calibration_messages_from_every_bag_form(calibrated_inputs, form, tmp_path):
    """No calibration file: CameraInfo (ROS 1 field names, as converted bags keep them) and /tf_static come through
    the one reader in record order, whatever form the bag has, and calibrate the clip."""
    summary, msgs = _run(calibrated_inputs[form], tmp_path / "out.mcap", calib="",
                         camera_info_topic="/cam0/camera_info", use_tf_static=True)
    assert _outcomes(msgs) == [("0", "init", "ok")] and len(msgs["/vi3_node/poses"]) == 1
    if form == "rosbag2":  # without /tf_static there is no T_BC: the same bag then says so
        _, msgs = _run(calibrated_inputs[form], tmp_path / "no_tf.mcap", calib="",
                       camera_info_topic="/cam0/camera_info")
        assert _outcomes(msgs)[0][1:] == ("skipped", "calibration_missing")
        assert not (tmp_path / "no_tf.mcap").exists()  # no result: the statuses are kept as no_tf.partial.mcap
        assert "extrinsics" in _statuses(msgs)[0].values["detail"]


def test_asl_input_ignores_calibration_topics(bag3, tmp_path):
    """An ASL folder has no CameraInfo or /tf_static: asking for them reads nothing more, calib_file calibrates
    (short clips: they reach the initialisation, which is all this checks)."""
    asl, _ = bag3
    summary, msgs = _run(asl, tmp_path / "out.mcap", camera_info_topic="/cam0/camera_info", use_tf_static=True,
                         clip_length=2, stride=1, hop=40)
    statuses = _statuses(msgs)
    assert summary.clips == len(statuses) == 2
    assert all(s.values["result"] != "skipped" and s.values["init_status"] for s in statuses)


# -------------------------------------------------------------------------------------------- diagnostics
def test_dropped_inputs_are_counted_and_published_per_period(bag3, tmp_path):
    """Every IMU message of a stretch arrives twice: each copy is dropped (imu_duplicate) and counted exactly, but
    /diagnostics is published per clip, per diagnostics_period of bag time and once when the reason first appears
    (stamped with the dropped message's exact stamp), not per dropped message."""
    asl, src = bag3
    seq = read_asl(asl)
    t0, _ = _clip_window(asl, 0)
    # from a stamp that float seconds cannot carry exactly (its ns do not survive ns -> s -> ns)
    first = next(int(n) for n in seq.imu_ns if n > t0 and round(int(n) * 1e-9 * 1e9) != n)
    until = _two_clips(asl)
    twice = lambda topic, t, m: [(t, m), (t, m)] if topic == "/imu0" and t >= first else [(t, m)]
    summary, msgs = _run(_edited(src, tmp_path / "dup", twice, until_ns=until), tmp_path / "out.mcap",
                         diagnostics_period=0.5)
    n_dup = int(np.sum((seq.imu_ns >= first) & (seq.imu_ns <= until)))
    assert n_dup > 200 and summary.drops == {"imu_duplicate": n_dup}
    diag = msgs["/diagnostics"]
    periods = int(np.ceil(summary.bag_s / 0.5))
    assert len(diag) <= summary.clips + periods + 2, len(diag)  # clips, periods, the first drop, the final counts
    statuses = [diagnostic_array_to_statuses(m)[0] for m in diag]
    news = [(stamp_to_ns(m.header.stamp), s) for m, s in zip(diag, statuses) if s.message.startswith("imu_dup")]
    assert len(news) == 1 and news[0][0] == first and str(first) in news[0][1].message
    assert statuses[-1].values["drop_imu_duplicate"] == str(n_dup)  # the final summary: exact totals
    per_period = [int(s.message.rsplit(":", 1)[1]) for s in statuses if s.message.startswith("input drops")]
    assert len(per_period) >= 2 and sum(per_period) == n_dup  # every drop in exactly one period's count
    per_clip = sum(int(s.values["input_drops"].split(":")[1]) for s in _statuses(msgs) if s.values["input_drops"])
    assert 0 < per_clip <= n_dup


def test_bench_replay_reports_speed_and_cpu_seconds_per_clip(bag3):
    """``vi3 bench replay --input ASL``: every clip processed, a realtime factor, a latency and the process CPU
    seconds per clip."""
    asl, _ = bag3
    out = bench_replay(argparse.Namespace(input=str(asl), backbone="classical", device="cpu", repeats=1, realtime=False,
                                          backbone_delay=None, param=[]))
    assert out["clips"] >= 2 and sum(out["outcomes"].values()) == out["clips"]
    assert out["realtime_factor"] > 0 and out["median_latency_ms"] > 0
    assert 0 < out["cpu_s_per_clip"] < 60


def test_a_recorded_backbone_replays_what_the_backbone_gave_and_bench_pipeline_costs_the_rest(bag4, tmp_path):
    """``vi3 bench pipeline``'s instrument: a replay through the recorded predictions publishes what the replay
    through the backbone published (every ~/status value but the timings and latencies, every pose), and a clip
    the recording never saw is a clear error; the bench reports the CPU per clip of everything else and of
    ``~/odom/imu`` per sample."""
    _, mcap = bag4
    settings = resolve({"calib_file": str(_calib_file(tmp_path)), **OPEN_GATE})
    recording = Recording()
    live = replay(mcap, tmp_path / "live.mcap", settings=settings, progress=False,
                  backbone=RecordingBackbone(make_backbone("classical"), recording))
    served = replay(mcap, tmp_path / "served.mcap", settings=settings, progress=False,
                    backbone=RecordedBackbone(recording))
    assert len(recording) == live.clips == served.clips >= 4
    a, b = _read(live.output), _read(served.output)
    keep = lambda s: {k: v for k, v in s.values.items() if not k.startswith(("timing_", "latency"))}
    assert [keep(s) for s in _statuses(a)] == [keep(s) for s in _statuses(b)]
    assert [poses_to_T(m.poses).tolist() for m in a["/vi3_node/poses"]] == \
        [poses_to_T(m.poses).tolist() for m in b["/vi3_node/poses"]]
    empty = replay(mcap, tmp_path / "empty.mcap", settings=settings, progress=False,
                   backbone=RecordedBackbone(Recording()))
    assert empty.outcomes == {"skipped:error": empty.clips}, empty.outcomes

    # a bag as the input: its IMU is read from the bag (an ASL-only reader once failed here after every replay)
    out = bench_pipeline(argparse.Namespace(input=str(mcap), backbone="classical", device="cpu", repeats=1,
                                            backbone_delay=None, param=[f"calib_file={_calib_file(tmp_path)}"]))
    assert out["clips"] == out["recorded_clips"] >= 4 and sum(out["outcomes"].values()) == out["clips"]
    assert 0 < out["cpu_s_per_clip"] < 5 and 0 < out["imu_odom_us_per_sample"] < 10_000
