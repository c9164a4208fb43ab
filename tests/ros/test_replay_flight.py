"""``vi3 replay --px4`` (and ``mavros_odom``) on a generated sequence with exact ground truth: the VehicleOdometry
decoded from the output MCAP with the definition the MCAP carries (no px4_msgs here), against the ``~/odom/imu`` and
``~/odom`` messages of the same replay and against the ground truth.

The sequence is a 2.5 s generated flight (EuRoC's IMU mount: x up, z forward) played twice, the second time after
3 s without data: the first clip of each pass claims no scale, and the second pass starts a new odom segment."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from test_replay import _calib_file, _converted_bag, _edited

from msg_adapters.diagnostics import diagnostic_array_to_statuses
from msg_adapters.poses import odometry_to_numpy
from msg_adapters.px4 import NAME, POSE_FRAME_FRD, VELOCITY_FRAME_BODY_FRD, vehicle_odometry_to_px4
from msg_adapters.stamps import ns_to_stamp, stamp_to_ns
from msg_adapters.types import jazzy_types
from vi3_core import so3
from vi3_core.dataset.asl import read_asl
from vi3_core.sim.trajectory import R_MOUNT
from vi3_ros.cli import main as vi3_main
from vi3_ros.flight_frames import NED_FROM_ENU, frd_rotation
from vi3_ros.flight_odom import MAVROS_RESET_PAUSE_S, scale_quality
from vi3_ros.imu_odom import ODOM_YAW_SIGMA

pytestmark = pytest.mark.slow  # a replay of a generated sequence

EUROC = "+z,+y,-x"
R_FRD_B = frd_rotation(EUROC)
GAP_NS = 3_000_000_000


def _quat_R(q_wxyz: np.ndarray) -> np.ndarray:
    return so3.quat_to_R(np.roll(q_wxyz, -1))


@pytest.fixture(scope="module")
def flown(cache_dir, tmp_path_factory):
    """(sequence, shift ns of the second pass, {topic: [(log ns, message)]}, the output's connections' types)."""
    asl, src = _converted_bag(cache_dir, seconds=2.5, seed=1)
    seq = read_asl(asl)
    shift = int(max(seq.stamps_ns[-1], seq.imu_ns[-1]) - min(seq.stamps_ns[0], seq.imu_ns[0])) + GAP_NS
    store, types = jazzy_types().typestore, jazzy_types()

    def twice(topic, t, m):
        again = store.deserialize_cdr(store.serialize_cdr(m, m.__msgtype__), m.__msgtype__)
        again.header.stamp = ns_to_stamp(stamp_to_ns(m.header.stamp) + shift, types=types)
        return [(t, m), (t + shift, again)]

    tmp = tmp_path_factory.mktemp("flight")
    bag = _edited(src, tmp / "twice", twice, until_ns=2**62)
    out = tmp / "out.mcap"
    assert vi3_main(["replay", str(bag), "--output", str(out), "--calib", str(_calib_file(tmp)), "--px4",
                     "--no-progress", "--param", "mavros_odom=true", "--param", f"frd_axes={EUROC}",
                     "--param", "base_frame=imu0"]) == 0
    msgs: dict[str, list] = {}
    with AnyReader([out]) as reader:  # the types from the MCAP's own schemas
        schemas = {c.topic: c.msgtype for c in reader.connections}
        for c, t, raw in reader.messages():
            msgs.setdefault(c.topic, []).append((t, reader.deserialize(raw, c.msgtype)))
    return seq, shift, msgs, schemas


def _clips(msgs) -> list[dict[str, str]]:
    return [st.values for _, m in msgs["/vi3_node/status"] for st in diagnostic_array_to_statuses(m)]


def _px4(msgs):
    return [vehicle_odometry_to_px4(m) for _, m in msgs["/fmu/in/vehicle_visual_odometry"]]


def test_px4_odometry_is_sent_from_the_first_claim_and_resets_at_the_new_segment(flown):
    seq, shift, msgs, schemas = flown
    assert schemas["/fmu/in/vehicle_visual_odometry"] == NAME
    clips = _clips(msgs)
    outcome = [(c["result"], c.get("odom_segment")) for c in clips]
    assert outcome == [("none", "0"), ("init", "0"), ("init", "0"), ("none", "0"), ("init", "1"), ("init", "1")]
    px4 = _px4(msgs)
    imu = [stamp_to_ns(m.header.stamp) for _, m in msgs["/vi3_node/odom/imu"]]
    samples = np.array([o.timestamp_sample_us for o in px4])
    # One per ~/odom/imu message, its sample's stamp in microseconds; in replay published at the measurement time.
    assert samples.tolist() == [round(t / 1000) for t in imu] and len(samples) > 300
    assert all(o.timestamp_us == o.timestamp_sample_us for o in px4)
    # Nothing before the first chained clip's last frame (clip 0, a window of one, is not placed), none while the IMU
    # was missing.
    first_claim = float(clips[1]["t_last"])
    assert samples[0] * 1e-6 > first_claim and samples[0] * 1e-6 - first_claim < 0.02
    second_pass = samples * 1000 > seq.stamps_ns[-1] + GAP_NS // 2
    assert samples[second_pass][0] * 1e-6 > float(clips[4]["t_last"])
    # reset_counter: the odom segment, incremented exactly once, at the second pass's first sample.
    counters = np.array([o.reset_counter for o in px4])
    assert np.array_equal(counters, second_pass.astype(int))
    assert {(o.pose_frame, o.velocity_frame) for o in px4} == {(POSE_FRAME_FRD, VELOCITY_FRAME_BODY_FRD)}
    # quality: the anchoring clip's relative scale sigma (rounded in ~/status) against max_scale_sigma 0.04
    anchors = [float(c["t_last"]) for c in clips if c["odom"] != "not placed"]
    rel = [float(c["scale_rel_sigma"]) for c in clips if c["odom"] != "not placed"]
    for o in px4:  # the latest clip chained before the sample, or the one before (the sample completing a clip)
        k = int(np.searchsorted(anchors, o.timestamp_sample_us * 1e-6)) - 1
        assert any(abs(o.quality - scale_quality(rel[j], 0.04)) <= 1 for j in {max(k - 1, 0), k}), (o, rel)


def test_a_scale_too_loose_to_claim_is_flown_at_quality_1_and_nothing_else_of_it_published(cache_dir, tmp_path):
    """max_scale_sigma 0.1 % claims nothing: the clips the window knows to odom_max_scale_sigma go into ~/odom and to
    PX4 at quality 1 (EKF2_EV_QMIN 2 refuses them), their ~/status says so, no poses, depth or points are published,
    and the replay, whose only output is that odometry, keeps it and exits 0."""
    _, src = _converted_bag(cache_dir, seconds=2.5, seed=1)
    out = tmp_path / "out.mcap"
    assert vi3_main(["replay", str(src), "--output", str(out), "--calib", str(_calib_file(tmp_path)), "--px4",
                     "--no-progress", "--param", f"frd_axes={EUROC}", "--param", "base_frame=imu0",
                     "--param", "max_scale_sigma=0.001"]) == 0
    msgs: dict[str, list] = {}
    with AnyReader([out]) as reader:
        for c, t, raw in reader.messages():
            msgs.setdefault(c.topic, []).append((t, reader.deserialize(raw, c.msgtype)))
    clips = _clips(msgs)
    placed = [c for c in clips if c["odom"] == "window scale, not claimed"]
    assert all(c["result"] == "none" for c in clips) and len(placed) >= 2, clips
    assert all(float(c["scale_rel_sigma"]) <= 0.1 for c in placed)
    assert len(msgs["/vi3_node/odom"]) == len(placed)
    counted = [int(kv.value) for _, m in msgs["/diagnostics"] for st in m.status for kv in st.values
               if kv.key == "odom_only"]
    assert counted and counted[-1] == len(placed), counted  # /diagnostics counts them too
    assert not {"/vi3_node/poses", "/vi3_node/depth", "/vi3_node/points"} & msgs.keys()
    px4 = _px4(msgs)
    assert len(px4) > 100 and {o.quality for o in px4} == {1}
    first = min(float(c["t_last"]) for c in placed)
    assert px4[0].timestamp_sample_us * 1e-6 >= first - 1e-6


def test_px4_states_are_odom_imus_in_ned_and_frd(flown):
    """The same state as ~/odom/imu: position on the NED axes, the vehicle's FRD attitude and body velocity and rate
    (EuRoC's IMU turned by frd_axes), all in SI units."""
    _, _, msgs, _ = flown
    for o, (_, m) in zip(_px4(msgs), msgs["/vi3_node/odom/imu"]):
        T, v_B, w_B, _, _ = odometry_to_numpy(m)
        np.testing.assert_allclose(o.position, NED_FROM_ENU @ T[:3, 3], atol=1e-5)
        np.testing.assert_allclose(_quat_R(o.q), NED_FROM_ENU @ T[:3, :3] @ R_FRD_B.T, atol=1e-5)
        np.testing.assert_allclose(o.velocity, R_FRD_B @ v_B, atol=1e-5)
        np.testing.assert_allclose(o.angular_velocity, R_FRD_B @ w_B, atol=1e-5)


def test_px4_variances_are_the_estimators_mapped_to_ned_and_frd(flown):
    """Position: ~/odom's variance at the anchoring clip plus ~/odom/imu's growth, on NED's axes. Attitude (FRD body
    axes): the tilt as ~/odom/imu has grown it from ~/odom's, the yaw ~/odom's pi^2 plus the propagation's. Velocity:
    ~/odom/imu's, on the FRD body axes. They grow with the time since the chained clip."""
    _, _, msgs, _ = flown
    odom = [(stamp_to_ns(m.header.stamp), odometry_to_numpy(m)[3]) for _, m in msgs["/vi3_node/odom"]]
    odom_ns = np.array([t for t, _ in odom])
    chained_pos = np.array([np.diag(cov)[:3] for _, cov in odom])
    growth = []
    for o, (_, m) in zip(_px4(msgs), msgs["/vi3_node/odom/imu"]):
        T, _, _, pose_cov, twist_cov = odometry_to_numpy(m)
        var = np.diag(pose_cov)
        chained = o.position_variance - var[[1, 0, 2]]
        k = int(np.searchsorted(odom_ns, o.timestamp_sample_us * 1000)) - 1
        assert any(np.allclose(chained, chained_pos[j][[1, 0, 2]], rtol=1e-4) for j in {max(k - 1, 0), k}), chained
        R_FB_O = R_FRD_B @ T[:3, :3].T
        np.testing.assert_allclose(o.orientation_variance, R_FB_O**2 @ (var[3:] + [0.0, 0.0, ODOM_YAW_SIGMA**2]),
                                   rtol=1e-4)
        np.testing.assert_allclose(o.velocity_variance, R_FRD_B**2 @ np.diag(twist_cov)[:3], rtol=1e-4)
        growth.append(var[0])
    assert max(growth) > 10 * min(growth) > 0


def test_px4_odometry_follows_the_ground_truth(flown):
    """First pass: after the one yaw that ties odom to the world (odom's yaw is the first clip's), PX4's attitude is
    the true vehicle's FRD attitude within 3 deg and its displacement the true one's on the NED axes within 15 %."""
    seq, _, msgs, _ = flown
    px4 = [o for o in _px4(msgs) if o.reset_counter == 0]
    gt = seq.gt.at(np.array([o.timestamp_sample_us * 1e-6 for o in px4]))
    R_WF = gt.T_WB[:, :3, :3] @ R_FRD_B.T  # the true vehicle FRD in the world (z up)
    R_LF = np.stack([_quat_R(o.q) for o in px4])
    R_OW = NED_FROM_ENU.T @ R_LF[0] @ R_WF[0].T  # odom <- world: a yaw, up to the estimate's tilt error
    R_LW = NED_FROM_ENU @ so3.exp(np.array([0.0, 0.0, np.arctan2(R_OW[1, 0], R_OW[0, 0])]))
    err = np.degrees(so3.angle(np.swapaxes(R_LF, 1, 2) @ R_LW @ R_WF))
    assert err.max() < 3.0, err
    d_true = R_LW @ (gt.T_WB[-1, :3, 3] - gt.T_WB[0, :3, 3])
    d = px4[-1].position - px4[0].position
    assert np.linalg.norm(d - d_true) < 0.15 * np.linalg.norm(d_true) and np.linalg.norm(d_true) > 0.3, (d, d_true)


def test_mavros_odometry_is_the_vehicles_flu_pose_and_pauses_at_the_new_segment(flown):
    seq, _, msgs, _ = flown
    mavros = msgs["/mavros/odometry/out"]
    imu = {stamp_to_ns(m.header.stamp): odometry_to_numpy(m)[0] for _, m in msgs["/vi3_node/odom/imu"]}
    assert {(m.header.frame_id, m.child_frame_id) for _, m in mavros} == {("odom", "base_link")}
    stamps = np.array([stamp_to_ns(m.header.stamp) for _, m in mavros])
    for s, (_, m) in zip(stamps, mavros):
        T = odometry_to_numpy(m)[0]
        np.testing.assert_allclose(T, imu[s] @ so3.make_T(R_MOUNT.T, np.zeros(3)), atol=1e-6)  # IMU -> FLU
        assert so3.angle_between(T[:3, 2], [0.0, 0.0, 1.0]) < np.radians(30)  # a multirotor's FLU z: up-ish
    first, second = stamps[stamps < seq.stamps_ns[-1] + GAP_NS // 2], stamps[stamps > seq.stamps_ns[-1] + GAP_NS]
    imu_ns = np.array(sorted(imu))
    assert np.array_equal(first, imu_ns[imu_ns <= first[-1]])  # the first segment: every state
    second_imu = imu_ns[imu_ns > seq.stamps_ns[-1] + GAP_NS]
    assert second[0] - second_imu[0] >= MAVROS_RESET_PAUSE_S * 1e9 > second[0] - second_imu[0] - 10_000_000
