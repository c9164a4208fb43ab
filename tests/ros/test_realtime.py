"""The node's timing in replay and the odometry between clips: ``vi3 replay --realtime`` (the node's latest-wins
worker thread fed at the recorded rate, a slow model emulated with ``backbone_delay``), ``~/odom/imu`` (the chained
state propagated at IMU rate, corrected when a clip lands) and the clip buffer's IMU history that bridges the clips
a busy worker drops, on generated sequences."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from msg_adapters.diagnostics import diagnostic_array_to_statuses
from msg_adapters.poses import odometry_to_numpy
from msg_adapters.stamps import stamp_to_ns
from msg_adapters.types import jazzy_types
from vi3_core.dataset.calib import write_euroc_sensor_yaml
from vi3_core.dataset.generate import EUROC_CAM0, cached_sequence
from vi3_ros.clip_buffer import ClipBuffer
from vi3_ros.imu_odom import ODOM_YAW_SIGMA, SIGMA_FLOOR
from vi3_ros.params import resolve
from vi3_ros.pipeline import MAX_IMU_RATE_HZ, buffer_options
from vi3_ros.replay import replay
from vi3_ros.replay_bench import bench_replay
from vi3_ros.replay_odom import correction_jumps, read_odometry

pytestmark = pytest.mark.slow  # every test here runs replays, evaluations or generated sequences

OPEN_GATE = {"max_scale_sigma": 10.0}  # plumbing, not which clips may claim a scale (see tests/ros/test_replay.py)


@pytest.fixture(scope="module")
def seq4(cache_dir, tmp_path_factory) -> tuple[Path, Path]:
    """(ASL folder of a generated 4 s sequence, its calibration file)."""
    calib = tmp_path_factory.mktemp("calib") / "cam0.yaml"
    write_euroc_sensor_yaml(EUROC_CAM0, calib)
    return cached_sequence(cache_dir, seconds=4.0, seed=0, with_depth=False), calib


@pytest.fixture(scope="module")
def seq8(cache_dir, seq4) -> tuple[Path, Path]:
    """(ASL folder of a generated 8 s sequence, its calibration file): in real time on a loaded 2-core machine the
    first clip may land seconds after its frames, and IMU must still follow it."""
    return cached_sequence(cache_dir, seconds=8.0, seed=0, with_depth=False), seq4[1]


def _replay(seq4, out: Path, realtime: bool = False, **params):
    asl, calib = seq4
    summary = replay(asl, out, settings=resolve({"calib_file": str(calib), **OPEN_GATE, **params}), progress=False,
                     realtime=realtime)
    return summary, read_odometry(summary.output)


def _messages(path: Path, topic: str) -> list[tuple[int, object]]:
    """(log time ns, message) of ``topic``."""
    with AnyReader([path], default_typestore=jazzy_types().typestore) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [(t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages(connections=conns)]


@pytest.fixture(scope="module")
def replayed4(seq4, tmp_path_factory):
    """(summary, odometry) of the replay of ``seq4`` with the defaults (the gate open)."""
    return _replay(seq4, tmp_path_factory.mktemp("replayed4") / "out.mcap")


def test_imu_rate_odometry_follows_the_chained_state_and_is_corrected_within_its_sigma(replayed4):
    summary, odo = replayed4
    assert summary.outcomes == {"init": summary.clips} and summary.clips >= 4
    odom = [m for _, m in _messages(summary.output, "/vi3_node/odom")]
    odom_ns = np.array([stamp_to_ns(m.header.stamp) for m in odom])
    # Every IMU sample after the first chained clip's last frame, at the IMU's 200 Hz, in odom -> base_link.
    imu_msgs = [m for _, m in _messages(summary.output, "/vi3_node/odom/imu")]
    assert {(m.header.frame_id, m.child_frame_id) for m in imu_msgs} == {("odom", "base_link")}
    assert odo.imu_ns[0] > odom_ns[0] and np.all(np.diff(odo.imu_ns) > 0)
    assert np.median(np.diff(odo.imu_ns)) == pytest.approx(5e6, rel=0.01)
    assert len(odo.imu_ns) == pytest.approx((odo.imu_ns[-1] - odom_ns[0]) / 5e6, abs=2)
    # Each clip restarts the propagation from its ~/odom pose and velocity, once the sample that completes the clip
    # (the first past its last frame, still published from the previous state) has been handed on: the next message
    # is the new state carried forward, and the covariance starts again from (nearly) zero.
    var = np.trace(odo.imu_pose_cov[:, :3, :3], axis1=1, axis2=2)
    for m in odom[1:]:
        T, v_B, _, _, _ = odometry_to_numpy(m)
        k = int(np.searchsorted(odo.imu_ns, stamp_to_ns(m.header.stamp), side="right")) + 1
        dt = (odo.imu_ns[k] - stamp_to_ns(m.header.stamp)) * 1e-9
        assert 0.005 < dt <= 0.011
        assert np.linalg.norm(odo.imu_T[k, :3, 3] - T[:3, 3] - T[:3, :3] @ v_B * dt) < 1e-3
        assert var[k] < 1e-4 < var[k - 1]
    jumps, sigmas, resumes = correction_jumps(odo)
    assert len(jumps) == len(odom) - 1 and resumes == 0 and np.all(sigmas > 0)
    assert np.all(jumps <= 3.0 * sigmas), (jumps, sigmas)  # a correction stays within the propagated uncertainty
    between = np.split(var, np.flatnonzero(np.diff(var) < 0) + 1)
    assert all(np.all(np.diff(b) > 0) for b in between)  # uncertainty grows with the time since the last clip



def test_odom_covariances_are_the_chained_states_never_zero_and_grow_with_the_distance(replayed4):
    """Issue 25: ~/odom carried all-zero covariances, which a fusion node reads as certain. Pose covariance (odom):
    position from the scale's relative sigma and the gravity direction's over the metres flown since the segment
    started (plus the bridges), roll and pitch the gravity direction's sigma, yaw unknown (pi); twist (base_link): the
    window's velocity sigma and the gyro noise; every diagonal entry at least SIGMA_FLOOR^2."""
    summary, _ = replayed4
    odom = [odometry_to_numpy(m) for _, m in _messages(summary.output, "/vi3_node/odom")]
    statuses = [s for _, m in _messages(summary.output, "/vi3_node/status") for s in diagnostic_array_to_statuses(m)]
    rel = [float(s.values["scale_rel_sigma"]) for s in statuses if s.values["result"] == "init"]
    assert len(odom) == len(rel) >= 4
    pose = np.array([o[3] for o in odom])
    twist = np.array([o[4] for o in odom])
    P = np.array([o[0][:3, 3] for o in odom])
    for cov in (*pose, *twist):
        np.testing.assert_array_equal(cov, cov.T)
        assert np.all(np.diag(cov) >= SIGMA_FLOOR**2) and np.all(cov[~np.eye(6, dtype=bool)] == 0)
    np.testing.assert_allclose(pose[:, 5, 5], ODOM_YAW_SIGMA**2)
    assert np.all(np.sqrt(pose[:, 3, 3]) < 0.05) and np.all(np.diag(twist[0])[:3] < 0.5**2)  # tilt, velocity
    sigma_p = np.sqrt(pose[:, 0, 0])
    flown = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    assert np.all(sigma_p >= np.minimum.accumulate(rel) * flown)  # at least the scales' share of the distance
    assert np.all(np.diff(sigma_p) > 0)  # growing with it: a later, better scale does not undo earlier clips' errors


def test_imu_rate_odometry_stops_when_its_position_sigma_exceeds_the_limit(seq4, tmp_path):
    """imu_odom_max_sigma: no ~/odom/imu message with a horizontal position 1-sigma above it; the propagation stops
    until the next chained clip, and /diagnostics says why."""
    limit = 0.002
    summary, odo = _replay(seq4, tmp_path / "capped.mcap", imu_odom_max_sigma=limit)
    assert summary.outcomes == {"init": summary.clips} and len(odo.imu_ns) > 0
    assert np.sqrt(odo.imu_pose_cov[:, 0, 0]).max() <= limit
    odom_ns = [stamp_to_ns(m.header.stamp) for _, m in _messages(summary.output, "/vi3_node/odom")]
    assert len(odo.imu_ns) < 0.9 * (odo.imu_ns[-1] - odom_ns[0]) / 5e6  # stopped between clips
    states = {s.values.get("imu_odom", "") for _, m in _messages(summary.output, "/diagnostics")
              for s in diagnostic_array_to_statuses(m) if s.name == "vi3: pipeline"}
    assert any(st.startswith("stopped: position 1-sigma ") and f"> imu_odom_max_sigma {limit:g} m" in st
               for st in states), states
    jumps, _, resumes = correction_jumps(odo)  # restarts after a stop are resumes, not jumps of a running stream
    assert resumes >= 1 and len(jumps) + resumes == len(odom_ns) - 1


def test_realtime_replay_drops_what_a_busy_worker_cannot_take_and_the_odometry_chains_across(seq8, tmp_path):
    delay = 1.0
    summary, odo = _replay(seq8, tmp_path / "rt.mcap", realtime=True, backbone_delay=delay)
    assert summary.as_dict()["realtime"] is True and summary.wall_s >= summary.bag_s
    processed = summary.results + summary.outcomes["none"]
    assert summary.outcomes["skipped:worker_busy"] >= 1 and processed >= 2
    assert processed + summary.outcomes["skipped:worker_busy"] == summary.clips
    assert min(summary.latencies_ms) >= 1000 * delay
    statuses = [(t, s) for t, m in _messages(summary.output, "/vi3_node/status")
                for s in diagnostic_array_to_statuses(m)]
    done = [(t, s) for t, s in statuses if s.values["result"] != "skipped"]
    skipped = [s for _, s in statuses if s.values["result"] == "skipped"]
    assert {s.values["reason"] for s in skipped} == {"worker_busy"}
    # Logged when published (the replay clock), a backbone_delay and more after the clip's last frame.
    assert all(t - stamp_to_ns(m.header.stamp) >= delay * 1e9
               for t, m in _messages(summary.output, "/vi3_node/odom"))
    assert all(t * 1e-9 - float(s.values["t_last"]) >= delay for t, s in done)
    # The clips the worker dropped are bridged by the IMU: one odom segment, no window restart; a chained clip adds
    # its 8 frames to the path, 7 when it shares its first with the clip chained before it (none was dropped).
    assert odo.segment_starts == [] and odo.window_resets == []
    assert 7 * summary.results < len(odo.path_ns) <= 8 * summary.results
    assert all(s.values["odom_segment"] == "0" for _, s in done)
    # ~/odom/imu starts once the first clip lands (its catch-up is not published), one message per later sample.
    first_landed = min(t for t, _ in _messages(summary.output, "/vi3_node/odom"))
    imu_log = np.array([t for t, _ in _messages(summary.output, "/vi3_node/odom/imu")])
    assert len(imu_log) > 0 and imu_log.min() >= first_landed
    assert odo.imu_ns[0] >= stamp_to_ns(_messages(summary.output, "/vi3_node/odom")[0][1].header.stamp) + delay * 1e9


def test_the_clip_buffer_keeps_imu_back_to_the_longest_bridge_in_bounded_memory():
    """With ``online`` the buffer hands every clip the IMU of the last ``online_max_bridge`` seconds (the gap back to
    the previous clip the worker processed), from a ring whose size does not grow with the stream."""
    opts = buffer_options(resolve({}))
    max_bridge = resolve({}).online.online_max_bridge
    assert opts.imu_history == max_bridge and opts.imu_buffer >= max_bridge * MAX_IMU_RATE_HZ
    buf = ClipBuffer(opts)
    storage = buf._imu._t.nbytes + buf._imu._rows.nbytes
    frame = np.zeros((2, 2), np.uint8)
    clips = []
    for k in range(int(150 * MAX_IMU_RATE_HZ)):  # 150 s of IMU at the fastest rate the buffer is sized for
        ns = k * 2_500_000
        out = buf.add_imu(ns, np.zeros(3), np.array([0.0, 0.0, 9.81]))
        if k % 20 == 0:  # 20 Hz frames
            out += buf.add_image(ns, frame)
        clips += [c for c in out if hasattr(c, "imu_history")]
        assert len(buf._imu) <= opts.imu_buffer
    assert not buf.counts and len(clips) > 100
    assert buf._imu._t.nbytes + buf._imu._rows.nbytes == storage
    for c in clips:
        t0 = c.stamps[0]
        back = min(max_bridge, t0)  # the first minute has less behind it
        assert c.imu_history.t[0] <= t0 - back + 1e-9 and c.imu_history.t[-1] >= c.stamps[-1]
        assert c.imu_history.t[0] > t0 - max_bridge - 1.0 / MAX_IMU_RATE_HZ  # no more than asked for
    since = buf.imu_since(100.0)
    assert since.t[0] == 100.0 and since.t[-1] == buf._imu.t[-1]


def test_bench_replay_scores_the_odometry_against_ground_truth(seq4):
    asl, _ = seq4
    params = [f"{k}={v}" for k, v in OPEN_GATE.items()] + ["imu_odom_rate=50"]
    out = bench_replay(argparse.Namespace(input=str(asl), backbone="classical", device="cpu", repeats=1,
                                          realtime=False, backbone_delay=None, param=params))
    odom, imu = out["odom"], out["imu_odom"]
    # every clip chained, each after the first sharing its first frame with the one before
    assert odom["segments"] == 1 and odom["window_resets"] == 0 and odom["frames"] == 7 * out["clips"] + 1
    assert 0 < odom["ate_m"] < 0.1 and odom["drift_pct"] < 5 and odom["distance_m"] > 1
    assert imu["rate_hz"] == pytest.approx(50, rel=0.01) and imu["max_jump_sigma"] <= 3  # imu_odom_rate: 50 Hz
