"""``vi3_core.online``: priors carried across clips, their consistency tests and reset, the chained odom trajectory,
and the odom outputs of replay. Estimator tests use the ground-truth camera poses of a generated sequence as the
"backbone" (up to a scale of 1/3, with a few millimetres of noise, like a 3DFM's), so they run in seconds."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from msg_adapters.diagnostics import diagnostic_array_to_statuses
from msg_adapters.poses import odometry_to_numpy, poses_to_T, tf_message_to_list
from msg_adapters.stamps import stamp_to_ns
from vi3_core import so3
from vi3_core.dataset.asl import read_asl
from vi3_core.dataset.calib import write_euroc_sensor_yaml
from vi3_core.dataset.generate import EUROC_CAM0, cached_sequence
from vi3_core.dataset.sequence import make_clip, sample_clips
from vi3_core.eval.chained import chained_metrics
from vi3_core.eval.metrics import gt_camera_poses
from vi3_core.eval.tum import read_tum
from vi3_core.init import initialise_clip
from vi3_core.init.oracle import gt_init_state, oracle_init
from vi3_core.init.position_fit import fit_positions
from vi3_core.online import OnlineEstimator, OnlineOptions
from vi3_core.online.window import WindowClip, WindowSystem
from vi3_core.preintegration import accel_bias_jacobians, preintegrate
from vi3_core.types import AnchorResult, Geometry
from vi3_ros.cli import main as vi3_main

TRUE_SCALE = 3.0  # metric = 3 x the fake backbone's translation


@pytest.fixture(scope="module")
def seq(cache_dir):
    return read_asl(cached_sequence(cache_dir, seconds=10.0, seed=0, with_depth=False))


def _geometry(clip, noise_m: float, rng: np.random.Generator) -> Geometry:
    """GT camera poses in C1 with ``noise_m`` of position noise, divided by TRUE_SCALE; flat depth."""
    T = gt_camera_poses(clip.gt, clip.T_BC).copy()
    T[1:, :3, 3] += rng.normal(0.0, noise_m, (clip.n - 1, 3))
    T[:, :3, 3] /= TRUE_SCALE
    n = clip.n
    return Geometry(T, np.repeat(clip.K[None], n, 0), np.full((n, 4, 4), 1.0), np.ones((n, 4, 4)))


def _run(seq, *, noise_m: float = 0.003, clips=None, corrupt_at: int | None = None,
         options: OnlineOptions | None = None):
    """The estimator over sliding clips: (estimator, per-clip online scale errors, GT-free scale errors, decisions)."""
    rng = np.random.default_rng(0)
    est = OnlineEstimator(options=options)
    online, free, decisions = [], [], []
    for k, idx in enumerate(clips or sample_clips(len(seq.stamps), n=8, stride=2, mode="sliding")):
        if k == corrupt_at:
            est.state = replace(est.state, v_O=est.state.v_O + np.array([2.0, 0.0, 0.0]))  # a wrong velocity prior
        clip = make_clip(seq, idx, with_depth=False, history_s=est.options.max_gap_s)  # as the node's buffer
        geo = _geometry(clip, noise_m, rng)
        free.append(abs(initialise_clip(clip, geo).scale / TRUE_SCALE - 1.0))
        init = est.initialise(clip, geo)
        result = AnchorResult(geometry=geo.scaled(init.scale) if init.ok else geo, base=geo, init=init,
                              mode="init" if init.ok else "none", alpha=init.scale, target=init.target)
        est.update(clip, result)
        online.append(abs(init.scale / TRUE_SCALE - 1.0))
        decisions.append(est.last.describe())
    return est, np.array(online), np.array(free), decisions


def test_position_fit_recovers_the_scale_of_exact_geometry(seq):
    clip = make_clip(seq, sample_clips(len(seq.stamps), mode="sliding")[2], with_depth=False)
    R1 = clip.gt.T_WB[0, :3, :3]
    g, v1 = R1.T @ clip.gt.g_W, R1.T @ clip.gt.v_WB[0]
    pre = preintegrate(clip.imu, clip.stamps, clip.gt.bg, clip.gt.ba)
    geo = _geometry(clip, 0.0, np.random.default_rng(0))
    fit = fit_positions(geo.T_wc, pre, clip.T_BC, g, v1)
    assert abs(fit.scale / TRUE_SCALE - 1) < 0.02 and fit.rms < 0.02
    wrong = fit_positions(geo.T_wc, pre, clip.T_BC, g, v1 + np.array([0.5, 0.0, 0.0]))
    assert wrong.rms > 5 * fit.rms  # a wrong velocity shows in the residual


def test_accel_bias_jacobians_are_exact(seq):
    """beta and alpha are linear in ba: preintegrating with ba = e_i moves them by exactly the Jacobian's column."""
    stamps = seq.stamps[10:60:3]
    imu, bg = seq.imu.window(stamps[0], stamps[-1]), np.array([0.01, -0.02, 0.005])
    base = preintegrate(imu, stamps, bg)
    J_beta, J_alpha = accel_bias_jacobians(imu, stamps, bg)
    for i, e in enumerate(np.eye(3)):
        moved = preintegrate(imu, stamps, bg, e)
        np.testing.assert_allclose(moved.alpha - base.alpha, J_alpha[..., i], atol=1e-12)
        np.testing.assert_allclose(moved.beta - base.beta, J_beta[..., i], atol=1e-12)
    assert np.abs(J_alpha[-1]).max() > 0.5 * (stamps[-1] - stamps[0]) ** 2 * 0.5  # not trivially zero


def _scaled(T: np.ndarray, s: float) -> np.ndarray:
    T = T.copy()
    T[:, :3, 3] *= s
    return T


def _window(seq, clips, scales, *, ba=(0.0, 0.0, 0.0)):
    """The window of ``clips`` with exact camera poses divided by ``scales``, GT gyro bias, the default weights and
    ``ba`` [3] m/s^2 added to the IMU's accelerometer."""
    members = [WindowClip(c.stamps, _scaled(gt_camera_poses(c.gt, c.T_BC), 1.0 / s)) for c, s in zip(clips, scales)]
    imu = seq.imu.window(clips[0].stamps[0], clips[-1].stamps[-1])
    imu = replace(imu, accel=imu.accel + np.asarray(ba))
    o = OnlineOptions()
    return WindowSystem(members, imu, np.asarray(clips[0].gt.bg).reshape(3), clips[0].T_BC, gravity_norm=9.81,
                        ba_weight=o.ba_weight, link_weight_s=o.velocity_link_s)


@pytest.mark.parametrize("ba", [np.zeros(3), np.array([0.08, -0.05, 0.12])])
def test_window_fit_recovers_each_clips_scale_gravity_and_velocity(seq, ba):
    """Exact camera positions at a different scale per clip, real IMU noise, with and without an EuRoC-sized
    accelerometer bias: every scale, gravity, velocity and the bias."""
    idx = sample_clips(len(seq.stamps), n=8, stride=2, mode="sliding")[2:9]
    clips = [make_clip(seq, i, with_depth=False) for i in idx]
    scales = np.linspace(0.5, 4.0, len(clips))
    system = _window(seq, clips, scales, ba=ba)
    fit = system.solve()
    true_ba = ba + np.mean([c.gt.ba for c in clips], axis=0)  # the added bias on top of the sequence's own
    assert np.linalg.norm(fit.ba - true_ba) < 0.05, (fit.ba, true_ba)
    np.testing.assert_allclose(fit.scales, scales, rtol=0.02)  # IMU noise and drifting biases over 5 s
    assert fit.rms.max() < 0.003 and np.all(fit.scale_rel_sigma < 0.01)
    for k, clip in enumerate(clips):
        g_gt, v_gt, _ = gt_init_state(clip.gt)
        g, v = system.state_at(k, fit)
        assert np.degrees(so3.angle_between(g, g_gt)) < 0.3 and np.linalg.norm(v - v_gt) < 0.02, k


def test_window_fit_exposes_a_broken_clip_and_an_unobservable_one(seq):
    idx = sample_clips(len(seq.stamps), n=8, stride=2, mode="sliding")[2:7]
    clips = [make_clip(seq, i, with_depth=False) for i in idx]
    good = _window(seq, clips, np.ones(len(clips))).solve()
    members = [WindowClip(c.stamps, gt_camera_poses(c.gt, c.T_BC)) for c in clips]
    last = members[-1]
    twisted = members[:-1] + [WindowClip(last.stamps, _scaled(last.T_wc, 1.0)[:, :, [1, 0, 2, 3]][:, [1, 0, 2, 3]])]
    broken = WindowClip(last.stamps, _scaled(last.T_wc, 0.0))
    imu = seq.imu.window(clips[0].stamps[0], clips[-1].stamps[-1])
    bg = np.asarray(clips[0].gt.bg).reshape(3)
    kw = dict(gravity_norm=9.81, ba_weight=1.0, link_weight_s=0.05)
    bad = WindowSystem(twisted, imu, bg, clips[0].T_BC, **kw).solve()
    assert bad.rms.max() > 10 * good.rms.max()  # swapped axes: positions no IMU motion can explain
    still = WindowSystem(members[:-1] + [broken], imu, bg, clips[0].T_BC, **kw).solve()
    assert not still.scale_rel_sigma[-1] < 0.05  # no visual translation: no scale, however the IMU moved


def test_priors_improve_scale_over_independent_clips_and_chain_stays_level(seq):
    est, online, free, decisions = _run(seq)
    assert sum("priors: g,v1" in d for d in decisions) >= len(decisions) // 2, decisions
    assert max(int(d.split()[1]) for d in decisions) >= 5  # the window grows to several clips
    after = slice(3, None)
    assert np.nanmedian(online[after]) <= 0.5 * np.nanmedian(free[after]), (online, free)
    traj = est.trajectory
    T_WB = seq.gt.at(traj.stamps).T_WB
    m = chained_metrics(traj.T_OB, T_WB, resets=len(traj.resets))
    assert len(traj.stamps) == len(np.unique(traj.stamps)) and np.all(np.diff(traj.stamps) > 0)
    assert m.gravity_err_deg < 1.0 and m.drift_pct < 10.0 and m.resets == 0, m


def test_a_gap_shorter_than_max_gap_is_bridged_by_the_imu(seq):
    """Clips dropped by a busy worker (a 2 s hole) keep the window: the IMU bridges the gap, no reset."""
    clips = [idx for idx in sample_clips(len(seq.stamps), n=8, stride=2, mode="sliding")
             if not 4.0 <= seq.stamps[idx[0]] - seq.stamps[0] < 6.0]
    est, online, free, decisions = _run(seq, clips=clips)
    assert not any("reset" in d for d in decisions[1:]) and not est.trajectory.resets, decisions
    assert np.nanmedian(online[3:]) <= 0.5 * np.nanmedian(free[3:]), (online, free)


def test_overlapping_clips_share_the_window(seq):
    """Clips that overlap (hop < clip span) share frames; the window takes them as they come."""
    _, online, free, decisions = _run(seq, clips=sample_clips(len(seq.stamps), n=8, stride=2, mode="sliding", hop=8))
    assert not any("reset" in d for d in decisions[1:]) and max(int(d.split()[1]) for d in decisions) >= 8
    assert np.nanmedian(online[3:]) <= 0.5 * np.nanmedian(free[3:]), (online, free)


def test_determinism(seq):
    a, b = _run(seq)[0].trajectory, _run(seq)[0].trajectory
    assert np.array_equal(a.stamps, b.stamps) and np.array_equal(a.T_OB, b.T_OB)


def test_image_gap_resets_and_recovers_within_three_clips(seq):
    clips = [idx for idx in sample_clips(len(seq.stamps), n=8, stride=2, mode="sliding")
             if not 4.0 <= seq.stamps[idx[0]] - seq.stamps[0] < 6.0]  # 2 s without images
    est, _, _, decisions = _run(seq, clips=clips, options=OnlineOptions(max_gap_s=1.0))  # forced: the gap > 1 s
    k = next(i for i, d in enumerate(decisions) if "reset: gap" in d)
    assert decisions[k].startswith("window 1 clips"), decisions[k]  # the window restarted from this clip
    assert k > 0 and any("priors: g,v1" in d for d in decisions[k + 1:k + 4]), decisions
    assert len(est.trajectory.resets) == 1


def test_corrupted_velocity_prior_is_rejected_and_named(seq):
    baseline = _run(seq)[3]
    k = next(i for i, d in enumerate(baseline) if i >= 2 and "priors: g,v1" in d)
    decisions = _run(seq, corrupt_at=k)[3]
    assert decisions[:k] == baseline[:k]
    assert "v1 prior rejected" in decisions[k] and "priors: g;" in decisions[k], decisions[k]
    assert "reset" not in decisions[k]  # the clip itself still takes the window's estimate


def _read(path) -> dict[str, list]:
    out: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for conn, _, raw in reader.messages():
            out.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
    return out


def test_replay_writes_odometry_path_and_tf_in_odom(cache_dir, tmp_path):
    asl = cached_sequence(cache_dir, seconds=2.5, seed=1, with_depth=False)
    calib = tmp_path / "cam0.yaml"
    write_euroc_sensor_yaml(EUROC_CAM0, calib)
    out = tmp_path / "out.mcap"
    assert vi3_main(["replay", str(asl), "--output", str(out), "--calib", str(calib), "--backbone", "classical",
                     "--no-progress", "--param", "publish_odom_tf=true", "--param", "outputs_in_odom=true"]) == 0
    msgs = _read(out)
    odom, paths = msgs["/vi3_node/odom"], msgs["/vi3_node/path"]
    assert len(odom) == len(paths) >= 2
    assert {(o.header.frame_id, o.child_frame_id) for o in odom} == {("odom", "base_link")}
    tfs = [t for m in msgs["/tf"] for t in tf_message_to_list(m)]
    assert [(p, c) for _, p, c, _ in tfs] == [("odom", "base_link")] * len(odom)
    T_last = odometry_to_numpy(odom[-1])[0]
    np.testing.assert_allclose(tfs[-1][0], T_last, atol=1e-9)
    path_T = poses_to_T([p.pose for p in paths[-1].poses])
    np.testing.assert_allclose(path_T[-1], T_last, atol=1e-9)
    stamps = [stamp_to_ns(p.header.stamp) for p in paths[-1].poses]
    assert stamps == sorted(set(stamps)) and stamps[-1] == stamp_to_ns(odom[-1].header.stamp)
    assert {p.header.frame_id for p in msgs["/vi3_node/poses"]} == {"odom"}
    statuses = [s for m in msgs["/vi3_node/status"] for s in diagnostic_array_to_statuses(m)]
    assert all("online" in s.values for s in statuses if s.values.get("result") == "init")


def test_vi3_eval_chained_json_and_tum(cache_dir, tmp_path, capsys):
    asl = cached_sequence(cache_dir, seconds=2.5, seed=1, with_depth=False)
    common = ["eval", str(asl), "--json", "--clips", "sliding", "--max-clips", "2", "--no-progress"]
    assert vi3_main([*common, "--export-tum", str(tmp_path)]) == 0
    obj = json.loads(capsys.readouterr().out)
    chained = obj["chained"]
    assert {"ate_m", "drift_pct", "gravity_err_deg", "resets", "scale_err_median", "independent_scale_err_median",
            "scale_outliers", "independent_scale_outliers"} <= set(chained) and chained["resets"] == 0
    assert all(np.isfinite(chained[k]) for k in ("ate_m", "drift_pct", "gravity_err_deg"))
    assert chained["scale_err_median"] is None  # 2 clips: none after the first 3
    assert len(chained["decisions"]) == obj["n_clips"] == 2 and obj["vi3"]["scale_traj"] is not None
    stamps, T = read_tum(tmp_path / "odom_vi3.txt")
    assert len(stamps) == chained["frames"] == 16 and np.all(np.diff(stamps) > 0)
    assert vi3_main([*common, "--independent"]) == 0
    assert "chained" not in json.loads(capsys.readouterr().out)


def test_vi3_eval_pools_several_sequences(cache_dir, tmp_path, capsys):
    """Several inputs: each sequence reported, then their clips pooled (JSON "sequences" + "pooled"); plots and TUM
    files are named after the sequences."""
    paths = [cached_sequence(cache_dir, seconds=2.5, seed=seed, with_depth=False) for seed in (1, 3)]
    rc = vi3_main(["eval", *map(str, paths), "--json", "--clips", "sliding", "--max-clips", "2", "--no-progress",
                   "--plot", str(tmp_path / "eval.png"), "--export-tum", str(tmp_path / "tum")])
    obj = json.loads(capsys.readouterr().out)
    assert rc == 0 and [s["n_clips"] for s in obj["sequences"]] == [2, 2]
    names = [s["sequence"] for s in obj["sequences"]]
    assert len(set(names)) == 2 and obj["pooled"]["n_clips"] == 4
    pooled = obj["pooled"]["chained"]
    assert pooled["sequences"] == 2 and pooled["resets"] == 0
    assert pooled["drift_pct_max"] == max(s["chained"]["drift_pct"] for s in obj["sequences"])
    assert pooled["scale_outliers"] == sum(s["chained"]["scale_outliers"] for s in obj["sequences"])
    assert all((tmp_path / f"eval_{n}.png").is_file() and (tmp_path / "tum" / n / "odom_vi3.txt").is_file()
               for n in names)


def test_oracle_init_without_gt_biases_uses_the_clips_own_gyro_bias(cache_dir):
    """GT tracks without biases (Vicon-only bags): the oracle keeps GT gravity and v1, estimates bg GT-free."""
    # TODO(lead): realistic data. With the default accelerometer bias (0.098 m/s^2 in room_seed0_10s) the oracle,
    # which cannot know it here, is 2.9 % off the scale.
    seq = read_asl(cached_sequence(cache_dir, seconds=4.0, seed=0, motion="agile", accel_bias=False,
                                   with_depth=False))
    clip = make_clip(seq, sample_clips(len(seq.stamps), mode="sliding")[3], with_depth=False)
    geo = _geometry(clip, 0.0, np.random.default_rng(0))
    no_bias = replace(clip, gt=replace(clip.gt, bg=None, ba=None))
    result = oracle_init(no_bias, geo)
    assert result.ok and abs(result.scale / TRUE_SCALE - 1) < 0.02, result.reason
    assert np.linalg.norm(result.bg - np.asarray(clip.gt.bg).reshape(3)) < 0.005


def test_bad_stream_input_is_named_and_does_not_poison_the_window(seq):
    """A NaN IMU sample is rejected with its clip only; a clip older than the window restarts it; a clip without
    any IMU is rejected, not a crash."""
    rng = np.random.default_rng(0)
    est = OnlineEstimator()
    idx = sample_clips(len(seq.stamps), n=8, stride=2, mode="sliding")
    decisions = []
    for k in [1, 2, 3, 4, 5, 6, 7, 2]:  # the last clip repeats an old one: out of order
        clip = make_clip(seq, idx[k], with_depth=False)
        if k == 4:
            accel = clip.imu.accel.copy()
            accel[len(accel) // 2] = np.nan
            clip = replace(clip, imu=replace(clip.imu, accel=accel))
        geo = _geometry(clip, 0.003, rng)
        init = est.initialise(clip, geo)
        est.update(clip, AnchorResult(geometry=geo.scaled(init.scale) if init.ok else geo, base=geo, init=init,
                                      mode="init" if init.ok else "none", alpha=init.scale, target=init.target))
        decisions.append((init.status.value, est.last.describe()))
    assert decisions[3][0] == "rejected" and "reset" in decisions[3][1]  # the NaN clip
    assert all(status == "ok" for status, _ in decisions[5:7]) and "reset" not in decisions[5][1], decisions
    assert "reset: clip out of order" in decisions[-1][1], decisions[-1]
    empty = make_clip(seq, idx[8], with_depth=False)
    empty = replace(empty, imu=empty.imu.select(np.zeros(0, dtype=int)), imu_history=None)
    assert not OnlineEstimator().initialise(empty, _geometry(empty, 0.0, rng)).ok
