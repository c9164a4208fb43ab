"""The paper's metrics on constructed cases with known answers."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from vi3_core import so3
from vi3_core.dataset.sequence import gt_camera_poses
from vi3_core.eval import metrics
from vi3_core.init.oracle import gt_init_state
from vi3_core.types import GroundTruth, InitResult, InitStatus


def _gt_poses(n: int = 6, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    R = so3.exp(rng.normal(scale=0.2, size=(n, 3)))
    p = np.cumsum(rng.normal(scale=0.3, size=(n, 3)), axis=0)
    return so3.relative_to_first(so3.make_T(R, p))


def _gt_depth(n: int = 6, hw: tuple[int, int] = (12, 16), seed: int = 1) -> np.ndarray:
    d = np.random.default_rng(seed).uniform(0.5, 8.0, size=(n, *hw))
    d[:, 0, :3] = np.nan  # invalid GT pixels must be ignored, not propagated
    return d


def test_prediction_twice_gt_gives_scale_two_and_zero_absrel_and_delta() -> None:
    T_gt, D_gt = _gt_poses(), _gt_depth()
    T_pred = T_gt.copy()
    T_pred[:, :3, 3] *= 2.0
    m = metrics.geometry_metrics(T_pred, T_gt, 2.0 * D_gt, D_gt)
    assert m.scale_traj == pytest.approx(2.0, abs=1e-12)
    assert m.scale_depth == pytest.approx(2.0, abs=1e-12)
    assert m.absrel == pytest.approx(0.0, abs=1e-12)
    assert m.delta125 == 0.0
    assert m.rot_deg == pytest.approx(0.0, abs=1e-6)
    # RMSE of (2p - p) = RMSE of |p|
    expected = np.sqrt(np.mean(np.sum(T_gt[:, :3, 3] ** 2, axis=1)))
    assert m.trans_rmse_m == pytest.approx(expected, rel=1e-12)


def test_perfect_prediction() -> None:
    T_gt, D_gt = _gt_poses(), _gt_depth()
    m = metrics.geometry_metrics(T_gt, T_gt, D_gt, D_gt)
    assert (m.trans_rmse_m, m.scale_traj, m.absrel, m.delta125, m.scale_depth) == pytest.approx((0, 1, 0, 1, 1))


def test_rotated_prediction_gives_expected_geodesic_angle() -> None:
    T_gt = _gt_poses()
    T_pred = T_gt.copy()
    # rotate every frame after the first by 3 deg about a fixed axis (frame 0 stays the reference): mean = 3 * 5/6
    R_err = so3.exp(np.radians(3.0) * np.array([0.0, 0.6, 0.8]))
    T_pred[1:, :3, :3] = T_gt[1:, :3, :3] @ R_err
    assert metrics.rot_error_deg(T_pred, T_gt) == pytest.approx(3.0 * 5 / 6, rel=1e-9)
    assert metrics.trans_rmse(T_pred, T_gt) == pytest.approx(0.0, abs=1e-12)


def test_rotation_of_whole_prediction_is_not_aligned_away() -> None:
    """Both trajectories are re-anchored at their first frame; a constant world rotation of the prediction
    (not just of frame 0) is an error that shows up in Trans, as the paper does no alignment."""
    T_gt = _gt_poses()
    Rw = so3.make_T(so3.exp(np.array([0.0, 0.0, np.radians(30.0)])), np.zeros(3))
    T_pred = np.einsum("ij,njk->nik", Rw, T_gt)
    T_pred[0] = np.eye(4)
    assert metrics.trans_rmse(T_pred, T_gt) > 0.05


def test_stationary_gt_frames_are_excluded_from_scale_traj() -> None:
    T_gt = _gt_poses()
    T_gt[1, :3, 3] = [0.004, 0.0, 0.0]  # < 1 cm from frame 0: excluded, whatever the prediction says there
    T_pred = T_gt.copy()
    T_pred[:, :3, 3] *= 1.5
    T_pred[1, :3, 3] = [5.0, 0.0, 0.0]
    assert metrics.scale_traj(T_pred, T_gt) == pytest.approx(1.5)
    # a fully stationary clip has no defined ratio
    T_still = np.tile(np.eye(4), (5, 1, 1))
    T_still[:, 0, 3] = np.linspace(0, 0.009, 5)
    assert np.isnan(metrics.scale_traj(T_pred[:5], T_still))


def test_absrel_is_scale_invariant_per_frame_and_delta_counts_inliers() -> None:
    D_gt = _gt_depth(n=3)
    D_pred = D_gt * np.array([0.5, 3.0, 7.0])[:, None, None]  # different wrong scale per frame
    assert metrics.absrel_median_aligned(D_pred, D_gt) == pytest.approx(0.0, abs=1e-12)
    D_half = D_gt.copy()
    D_half[:, :, :8] *= 1.1  # inliers
    D_half[:, :, 8:] *= 1.3  # outliers
    valid = np.isfinite(D_gt)
    expected = valid[:, :, :8].sum() / valid.sum()
    assert metrics.delta_inlier(D_half, D_gt) == pytest.approx(expected)


def test_depth_metrics_ignore_invalid_prediction_pixels() -> None:
    D_gt = _gt_depth(n=2)
    D_pred = 2.0 * D_gt
    D_pred[:, 5, :] = np.nan
    D_pred[:, 6, :] = 0.0
    assert metrics.scale_depth(D_pred, D_gt) == pytest.approx(2.0)
    assert np.isnan(metrics.scale_depth(np.full_like(D_gt, np.nan), D_gt))


def test_depth_grid_mismatch_is_a_named_error() -> None:
    with pytest.raises(ValueError, match="same grid"):
        metrics.scale_depth(np.ones((2, 4, 4)), np.ones((2, 8, 8)))


def test_resample_depth_nearest_keeps_values_and_nan() -> None:
    H, W = 40, 60
    K_src = np.array([[50.0, 0, 30.0], [0, 50.0, 20.0], [0, 0, 1]])
    v, u = np.mgrid[0:H, 0:W]
    depth = (1.0 + u + 100.0 * v).astype(np.float32)[None]
    depth[0, 10:20, 10:20] = np.nan
    # half resolution with a 2-pixel crop on the left (cx shifted accordingly)
    K_dst = np.array([[25.0, 0, 14.0], [0, 25.0, 10.0], [0, 0, 1]])
    out = metrics.resample_depth(depth, K_src, K_dst, (20, 28))
    assert out.shape == (1, 20, 28)
    vals = out[np.isfinite(out)]
    assert np.isin(vals, depth[np.isfinite(depth)]).all()  # no invented values
    # destination (u=3, v=2) -> source u = 2*(3-14)+30 = 8, v = 2*(2-10)+20 = 4
    assert out[0, 2, 3] == depth[0, 4, 8]
    assert np.isnan(out[0, 6, 8])  # source (12, 16) is in the NaN block
    # a destination wider than the source: out-of-image pixels are NaN
    wide = metrics.resample_depth(depth, K_src, np.array([[50.0, 0, 40], [0, 50.0, 20.0], [0, 0, 1]]), (40, 80))
    assert np.isnan(wide[0, :, :10]).all() and np.isfinite(wide[0, 25:, 10:70]).all()


def _gt_clip_state() -> GroundTruth:
    R_WB1 = so3.exp(np.array([0.3, -0.2, 1.0]))
    T_WB = np.tile(np.eye(4), (3, 1, 1))
    T_WB[:, :3, :3] = R_WB1
    v_WB = np.tile([1.0, 0.5, -0.2], (3, 1))
    return GroundTruth(T_WB=T_WB, v_WB=v_WB, bg=np.array([0.01, -0.02, 0.005]), ba=np.zeros(3))


def test_init_metrics_against_gt_in_first_body_frame() -> None:
    gt = _gt_clip_state()
    g, v1, bg = gt_init_state(gt)
    R_WB1 = gt.T_WB[0, :3, :3]
    np.testing.assert_allclose(R_WB1 @ g, gt.g_W, atol=1e-12)
    np.testing.assert_allclose(R_WB1 @ v1, gt.v_WB[0], atol=1e-12)
    # estimate: gravity tilted by 2 deg, velocity rotated by 5 deg and 10 % too long, bias off by 0.003
    axis = np.cross(g, [1.0, 0, 0])
    g_hat = so3.exp(np.radians(2.0) * axis / np.linalg.norm(axis)) @ g
    axis_v = np.cross(v1, [0, 0, 1.0])
    v_hat = 1.1 * so3.exp(np.radians(5.0) * axis_v / np.linalg.norm(axis_v)) @ v1
    bg_hat = bg + np.array([0.003, 0.0, 0.0])
    init = InitResult(status=InitStatus.OK, reason="", bg=bg_hat, g=g_hat, scale=1.0, v1=v_hat)
    m = metrics.init_metrics(init, gt)
    assert m.gravity_err_deg == pytest.approx(2.0, rel=1e-9)
    assert m.v1_dir_deg == pytest.approx(5.0, rel=1e-9)
    assert m.v1_mag_err == pytest.approx(0.1, rel=1e-9)
    assert m.v1_mag_ratio == pytest.approx(1.1, rel=1e-9)
    assert m.gyro_bias_err == pytest.approx(0.003, rel=1e-9)
    assert m.gyro_bias_rel == pytest.approx(0.003 / np.linalg.norm(bg), rel=1e-9)


def test_gt_camera_poses_compose_extrinsics_and_reanchor() -> None:
    gt = _gt_clip_state()
    T_WB = gt.T_WB.copy()
    T_WB[:, :3, 3] = [[0, 0, 0], [1, 0, 0], [2, 1, 0]]
    T_BC = so3.make_T(so3.exp(np.array([0.1, 1.5, 0.0])), np.array([0.05, -0.02, 0.01]))
    T = gt_camera_poses(GroundTruth(T_WB=T_WB, v_WB=gt.v_WB, bg=gt.bg, ba=gt.ba), T_BC)
    np.testing.assert_allclose(T[0], np.eye(4), atol=1e-12)
    # pure body translation with constant attitude: camera displacement = R_CB R_WB^T dp
    R_CW = T_BC[:3, :3].T @ T_WB[0, :3, :3].T
    np.testing.assert_allclose(T[2, :3, 3], R_CW @ np.array([2.0, 1.0, 0.0]), atol=1e-12)


def test_gt_without_biases_gives_nan_bias_error_not_a_crash() -> None:
    gt = _gt_clip_state()
    no_bias = GroundTruth(T_WB=gt.T_WB, v_WB=gt.v_WB, bg=np.full(3, np.nan), ba=np.full(3, np.nan))
    g, v1, _ = gt_init_state(no_bias)
    m = metrics.init_metrics(InitResult(status=InitStatus.OK, reason="", g=g, v1=v1, scale=1.0), no_bias)
    assert np.isnan(m.gyro_bias_err) and np.isnan(m.gyro_bias_rel)
    assert m.gravity_err_deg == pytest.approx(0.0, abs=1e-9) and m.v1_mag_err == pytest.approx(0.0, abs=1e-12)


def test_chained_scale_median_skips_the_first_clips():
    from vi3_core.eval.chained import SCALE_SKIP_CLIPS, median_after_skip

    err = np.array([0.9] * SCALE_SKIP_CLIPS + [0.01, np.nan, 0.03, 0.2])
    assert median_after_skip(err) == 0.03 and np.isnan(median_after_skip(err[:SCALE_SKIP_CLIPS]))


def _line(n: int, x0: float = 0.0) -> np.ndarray:
    """[n,4,4] body poses moving 1 m per frame along x, level."""
    T = np.repeat(np.eye(4)[None], n, 0)
    T[:, 0, 3] = x0 + np.arange(n, dtype=np.float64)
    return T


def test_drift_counts_the_distance_flown_between_poses():
    """With the GT track, a stretch without poses (clips not claimed, or dropped) counts the metres actually flown,
    not the straight line between the poses around it."""
    from vi3_core.dataset.sequence import GroundTruthTrack
    from vi3_core.eval.chained import chained_metrics, gt_path_length

    t = np.linspace(0.0, 2.0, 201)
    T = np.repeat(np.eye(4)[None], len(t), 0)
    T[:, 0, 3], T[:, 1, 3] = t, 0.5 * np.sin(np.pi * t)  # out 0.5 m sideways and back while moving 2 m along x
    track = GroundTruthTrack(t=t, T_WB=T)
    stamps = np.array([0.0, 0.1, 1.9, 2.0])  # poses only at both ends
    T_WB = track.at(stamps).T_WB
    T_OB = T_WB.copy()
    T_OB[-1, 0, 3] += 0.1  # 10 cm off at the end
    flown = gt_path_length(track, 0.0, 2.0)
    assert 2.9 < flown < 2.95  # the arc: the integral of sqrt(1 + (pi/2 cos(pi t))^2) over [0, 2] is 2.93
    frames_only = chained_metrics(T_OB, T_WB, stamps=stamps)
    m = chained_metrics(T_OB, T_WB, stamps=stamps, path_length=functools.partial(gt_path_length, track))
    assert frames_only.distance_m == pytest.approx(np.linalg.norm(np.diff(T_WB[:, :3, 3], axis=0), axis=1).sum())
    assert m.distance_m == pytest.approx(flown) and m.distance_m > frames_only.distance_m + 0.3
    assert m.drift_pct == pytest.approx(100 * 0.1 / flown, rel=0.05)


def test_chained_trajectory_is_scored_per_segment():
    """A jump at a segment start (the estimator placed a clip without a trustworthy IMU bridge) is not drift: each
    segment is aligned on its own first pose; a jump inside a segment is."""
    from vi3_core.eval.chained import chained_metrics, segment_bounds

    stamps = 0.1 * np.arange(10)
    T_WB = _line(10)
    T_OB = _line(10)
    T_OB[5:, 1, 3] += 2.0  # the estimate jumps 2 m sideways at frame 5, then tracks again
    whole = chained_metrics(T_OB, T_WB, stamps=stamps)
    split = chained_metrics(T_OB, T_WB, stamps=stamps, segment_starts=[stamps[5]])
    assert len(whole.segments) == 1 and whole.drift_pct == pytest.approx(100 * 2.0 / 9.0)
    assert whole.ate_m == pytest.approx(np.sqrt(5 * 4.0 / 10))
    assert len(split.segments) == 2 and split.ate_m == pytest.approx(0.0, abs=1e-12)
    assert [(s.t0, s.t1, s.frames, s.distance_m) for s in split.segments] == [(0.0, 0.4, 5, 4.0),
                                                                            (stamps[5], stamps[9], 5, 4.0)]
    assert split.distance_m == 8.0 and split.drift_pct == pytest.approx(0.0, abs=1e-12)
    # a segment that drifts: 1 m of error at its end over its 4 m
    T_OB[9, 0, 3] += 1.0
    m = chained_metrics(T_OB, T_WB, stamps=stamps, segment_starts=[stamps[5]])
    assert m.segments[1].drift_pct == pytest.approx(25.0) and m.segments[0].drift_pct == pytest.approx(0.0)
    assert m.drift_pct == pytest.approx(100 * 1.0 / 8.0) and m.ate_m == pytest.approx(np.sqrt(1.0 / 10))
    d = m.as_dict()
    assert d["segments"] == 2 and len(d["per_segment"]) == 2 and d["per_segment"][1]["drift_pct"] == 25.0
    # starts at the first stamp or outside the trajectory add no segment
    assert segment_bounds(stamps, [0.0, 5.0]) == [slice(0, 10)]
