"""Report, JSON, plot and TUM export on clip evaluations built from known geometry (no backbone needed)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from matplotlib.image import imread

from vi3_core import so3
from vi3_core.eval import metrics, plot, report, tum
from vi3_core.eval.clip_eval import ClipEval
from vi3_core.types import AnchorResult, Geometry, ImuTrajectory, InitResult, InitStatus

N, H, W = 6, 24, 32
K = np.array([[20.0, 0, 16.0], [0, 20.0, 12.0], [0, 0, 1]])


def _geometry(T: np.ndarray, depth: np.ndarray, traj_depth_sigma: float = 0.0) -> Geometry:
    return Geometry(T_wc=T, K=np.tile(K, (len(T), 1, 1)), depth=depth.astype(np.float32),
                    conf=np.ones_like(depth, dtype=np.float32), traj_depth_sigma=traj_depth_sigma)


def _scaled(T: np.ndarray, s: float) -> np.ndarray:
    T = T.copy()
    T[:, :3, 3] *= s
    return T


def make_clip_eval(seed: int, *, ok: bool = True, base_scale: float = 0.4, vi3_scale: float = 1.05,
                   sigma: float = float("nan"), shrink: float = 1.0, with_depth: bool = True,
                   traj_depth_sigma: float = 0.0) -> ClipEval:
    """A clip whose base is ``base_scale`` and VI3 output ``vi3_scale`` times the truth, their positions ``shrink``
    times that (a trajectory at another scale than the depth, of the base's ``traj_depth_sigma``); ``sigma``: the
    init's relative scale sigma; ``with_depth``: scored against depth ground truth."""
    rng = np.random.default_rng(seed)
    p = np.column_stack([np.linspace(0, 1.0, N), 0.2 * np.sin(np.linspace(0, 2, N)), np.zeros(N)])
    T_gt = so3.relative_to_first(so3.make_T(so3.exp(rng.normal(scale=0.05, size=(N, 3))), p))
    depth_gt = rng.uniform(1.0, 5.0, size=(N, H, W))
    base = _geometry(_scaled(T_gt, base_scale * shrink), base_scale * depth_gt, traj_depth_sigma)
    vi3 = _geometry(_scaled(T_gt, vi3_scale * shrink), vi3_scale * depth_gt)
    target = ImuTrajectory(R=T_gt[:, :3, :3], p=p, v=np.zeros((N, 3)), T_wc=_scaled(T_gt, 0.98))
    status = InitStatus.OK if ok else InitStatus.UNOBSERVABLE
    g_true = np.array([-9.81, 0.0, 0.0])
    init = InitResult(status=status, reason="" if ok else "too little acceleration", g=g_true + [0, 0.1, 0],
                      v1=np.array([0.0, 0.0, 1.1]), scale=vi3_scale / base_scale, target=target if ok else None,
                      scale_sigma=sigma * vi3_scale / base_scale)
    result = AnchorResult(geometry=vi3 if ok else base, base=base, init=init, mode="init" if ok else "none",
                          alpha=init.scale, target=target if ok else None)
    truth = depth_gt if with_depth else None
    columns = {"base": metrics.geometry_metrics(base.T_wc, T_gt, base.depth, truth)}
    if ok:
        columns["init"] = metrics.geometry_metrics(vi3.T_wc, T_gt, vi3.depth, truth)
    gt_init = metrics.InitMetrics(gravity_err_deg=0.6, gyro_bias_err=0.002, gyro_bias_rel=0.1, v1_dir_deg=2.0,
                                  v1_mag_err=0.1, v1_mag_ratio=1.1)
    return ClipEval(indices=np.arange(10 * seed, 10 * seed + 2 * N, 2), stamps=0.1 * np.arange(N) + seed,
                    status=status.value, reason=init.reason, mode=result.mode, T_gt=T_gt,
                    down_c1=np.array([0.0, 1.0, 0.0]), init=init, result=result, fast=None, columns=columns,
                    init_metrics=gt_init)


@pytest.fixture(scope="module")
def evals() -> list[ClipEval]:
    return [make_clip_eval(1), make_clip_eval(2), make_clip_eval(3, ok=False)]


def test_summary_has_the_issue_keys_finite_and_paper_medians(evals) -> None:
    s = report.summarise(evals, mode="init", backbone="test", sequence="constructed")
    assert s["n_clips"] == 3 and s["n_ok"] == 2
    assert s["status_counts"] == {"ok": 2, "unobservable": 1, "rejected": 0}
    for block in ("base", "vi3"):
        assert set(s[block]) == {"trans_rmse_m", "rot_deg", "scale_traj", "scale_fit", "absrel", "delta125",
                                 "scale_depth"}
        assert all(np.isfinite(v) for v in s[block].values())
    assert {"gravity_err_deg", "gyro_bias_err", "v1_dir_deg", "v1_mag_err"} <= set(s["init"])
    assert s["base"]["scale_traj"] == pytest.approx(0.4) and s["base"]["scale_depth"] == pytest.approx(0.4)
    assert s["vi3"]["scale_traj"] == pytest.approx(1.05) and s["vi3"]["delta125"] == pytest.approx(1.0)
    assert s["base"]["delta125"] == 0.0 and s["vi3"]["absrel"] == pytest.approx(0.0, abs=1e-6)
    # JSON round trip, with no NaN tokens
    assert json.loads(report.to_json(s))["vi3"] == s["vi3"]


def _strict(text: str):
    def refuse(token):
        raise ValueError(f"not JSON: {token}")

    return json.loads(text, parse_constant=refuse)


def test_missing_values_are_null_not_nan() -> None:
    s = report.summarise([make_clip_eval(4, ok=False)], mode="ttr")
    assert all(v is None for v in s["vi3"].values())
    assert "NaN" not in report.to_json(s)


def test_to_json_is_strict_json_whatever_it_is_given() -> None:
    obj = {"a": float("nan"), "b": [np.inf, -np.inf, np.float32(0.5)], "c": {"d": np.array([1.0, np.nan])},
           "e": (np.int64(3), np.bool_(True)), "f": "text", "g": None}
    assert _strict(report.to_json(obj)) == {"a": None, "b": [None, None, 0.5], "c": {"d": [1.0, None]},
                                            "e": [3, True], "f": "text", "g": None}


def test_tables_show_base_and_vi3_columns(evals) -> None:
    text = report.format_tables(report.summarise(evals, mode="init"))
    header = next(line for line in text.splitlines() if line.startswith("Metric"))
    assert header.split()[1:] == ["Base", "IMU-init", "Base", "(all)"]
    scale_row = next(line for line in text.splitlines() if line.startswith("Scale (Traj.)"))
    assert scale_row.split()[-3:] == ["0.40", "1.05", "0.40"]
    assert "unobservable 1" in text and "medians over the 2 paired clips" in text


def test_columns_are_paired_over_the_same_clips_and_the_base_over_all_separately() -> None:
    """Backbone failures that the init refuses must not flatter VI3 against the base: every column's median is over
    the ok clips, the base over every clip is its own column."""
    evals = [make_clip_eval(1, base_scale=0.4), make_clip_eval(2, base_scale=0.5),
             make_clip_eval(3, ok=False, base_scale=0.1), make_clip_eval(4, ok=False, base_scale=0.1),
             make_clip_eval(5, ok=False, base_scale=0.1)]
    s = report.summarise(evals, mode="init")
    assert s["n_clips"] == 5 and s["n_paired"] == 2
    assert s["base"]["scale_traj"] == pytest.approx(0.45) and s["columns"]["base"] == s["base"]
    assert s["base_all"]["scale_traj"] == pytest.approx(0.1)
    assert s["vi3"]["scale_traj"] == pytest.approx(1.05)
    # a metric undefined in a column leaves that clip out of every column's median of that metric
    broken = make_clip_eval(6, base_scale=0.3)
    broken.columns["init"] = metrics.GeometryMetrics(**{**broken.columns["init"].as_dict(), "absrel": float("nan")})
    s = report.summarise(evals[:2] + [broken], mode="init")
    assert s["n_paired"] == 3 and s["base"]["scale_traj"] == pytest.approx(0.4)
    assert s["base"]["absrel"] == pytest.approx(np.median([evals[0].columns["base"].absrel,
                                                           evals[1].columns["base"].absrel]))


def test_no_clip_ok_gets_its_line_with_the_reason() -> None:
    s = report.summarise([make_clip_eval(3, ok=False), make_clip_eval(4, ok=False)], mode="init", sequence="slow")
    assert s["n_ok"] == 0 and s["n_paired"] == 0 and all(v is None for v in s["vi3"].values())
    assert "no clip ok of 2" in s["note"] and "too little acceleration" in s["note"]
    assert s["note"] in report.format_tables(s)
    overview = report.format_overview([s, {"sequence": "broken", "error": "input x: missing"}])
    rows = {line.split()[0]: line for line in overview.splitlines()[3:]}
    assert set(rows) == {"slow", "broken"} and "no clip ok" in rows["slow"] and "input x: missing" in rows["broken"]


def test_claimed_outliers_count_only_ok_clips_beside_the_medians() -> None:
    evals = [make_clip_eval(1, vi3_scale=1.05), make_clip_eval(2, vi3_scale=1.15), make_clip_eval(3, vi3_scale=0.8),
             make_clip_eval(4, vi3_scale=1.01), make_clip_eval(5, ok=False, vi3_scale=3.0)]
    s = report.summarise(evals, mode="init")
    assert s["claimed_outliers"] == {"count": 2, "claimed": 4, "share": 0.5}
    assert "more than 10 % off: 2 of 4 (50.0 %)" in report.format_tables(s)


def test_a_backbone_that_knows_its_scale_is_scored_by_it_not_by_noisy_positions() -> None:
    """The gt instrument knows the metres per model unit it predicted at: a claim whose positions read 15 % off
    (pose noise on a clip that barely moves) but whose scale is exact is no outlier, and the other way round."""
    exact = replace(make_clip_eval(1, vi3_scale=1.15, sigma=0.02), exact_scale=1.15 / 0.4)  # init.scale = 1.15/0.4
    wrong = replace(make_clip_eval(2, vi3_scale=1.0, sigma=0.02), exact_scale=1.0 / 0.4 / 1.2)
    s = report.summarise([exact, wrong], mode="init")
    assert [c["scale_fit"] for c in s["clips"]] == pytest.approx([1.15, 1.0])
    assert [c["scale_exact"] for c in s["clips"]] == pytest.approx([1.0, 1.2])
    assert s["claimed_outliers"] == {"count": 1, "claimed": 2, "share": 0.5}
    assert s["sigma_calibration"]["within_1sigma"] == pytest.approx(0.5)
    assert report.summarise([make_clip_eval(3)], mode="init")["clips"][0]["scale_exact"] is None


def test_claims_by_depth_tell_a_wrong_scale_from_a_trajectory_that_misfits_its_depth() -> None:
    """One scale serves the trajectory and the depth: a claim whose depth is right and whose positions are 20 % short
    of it is off by its trajectory only, and the backbone's clips show it as a trajectory apart from its depth; a
    claim 15 % off in both is off by both. Without depth ground truth neither is scored."""
    short = make_clip_eval(1, vi3_scale=1.0, sigma=0.05, shrink=0.8)
    wrong = make_clip_eval(2, vi3_scale=1.15, sigma=0.05)
    right = make_clip_eval(3, vi3_scale=1.02, sigma=0.05)
    s = report.summarise([short, wrong, right, make_clip_eval(4, ok=False, shrink=0.5)], mode="init")
    assert s["claimed_outliers"] == {"count": 2, "claimed": 3, "share": pytest.approx(2 / 3)}
    assert s["depth_claims"]["outliers"] == {"count": 1, "claimed": 3, "share": pytest.approx(1 / 3)}
    assert s["depth_claims"]["calibration"]["within_2sigma"] == pytest.approx(2 / 3)
    assert [c["scale_depth"] for c in s["clips"][:3]] == pytest.approx([1.0, 1.15, 1.02])
    assert s["trajectory_vs_depth"] == {"clips": 4, "median": pytest.approx(0.9), "apart": 2, "sigmas": None}
    assert ("by depth: claimed scales more than 10 % off: 1 of 3 (33.3 %)" in report.format_tables(s)
            and "2 of 4 clips more than 10 % apart" in report.format_tables(s))
    none = report.summarise([make_clip_eval(1, with_depth=False)], mode="init")
    assert none["depth_claims"] is None and none["trajectory_vs_depth"] is None
    assert "by depth" not in report.format_tables(none)


def test_the_trajectory_against_depth_is_scored_in_the_backbones_own_sigmas() -> None:
    """Five clips whose trajectories are 0.9-1.1 of their depth, the backbone saying 5 % (one clip) or 2.5 %: the
    report gives the robust spread of log(ratio) / traj_depth_sigma, and each clip's traj_depth_sigma."""
    shrinks, tds = [0.9, 0.95, 1.0, 1.05, 1.1], [0.05, 0.025, 0.025, 0.025, 0.025]
    s = report.summarise([make_clip_eval(i + 1, shrink=r, traj_depth_sigma=t) for i, (r, t) in
                          enumerate(zip(shrinks, tds))], mode="init")
    z = np.log(shrinks) / np.array(tds)
    spread = 1.4826 * np.median(np.abs(z - np.median(z)))
    assert s["trajectory_vs_depth"]["sigmas"] == pytest.approx(spread, rel=1e-3)
    assert [c["traj_depth_sigma"] for c in s["clips"]] == tds
    assert f"spread {spread:.2f} times its traj_depth_sigma" in report.format_tables(s)


def test_sigma_calibration_shares_and_no_sigma() -> None:
    """Relative sigmas known per clip: errors 0.05, 0.15, 0.2, 0.01 against sigmas 0.1, 0.1, 0.05, 0.02."""
    evals = [make_clip_eval(1, vi3_scale=1.05, sigma=0.1), make_clip_eval(2, vi3_scale=1.15, sigma=0.1),
             make_clip_eval(3, vi3_scale=0.8, sigma=0.05), make_clip_eval(4, vi3_scale=1.01, sigma=0.02),
             make_clip_eval(5, vi3_scale=1.3)]  # claimed without a sigma
    cal = report.summarise(evals, mode="init")["sigma_calibration"]
    assert cal["claimed"] == 5 and cal["with_sigma"] == 4
    assert cal["within_1sigma"] == pytest.approx(2 / 4) and cal["within_2sigma"] == pytest.approx(3 / 4)
    s = report.summarise(evals, mode="init")
    sigmas = [c["scale_rel_sigma"] for c in s["clips"]]
    assert sigmas[:4] == pytest.approx([0.1, 0.1, 0.05, 0.02]) and sigmas[4] is None
    assert "0.1000" in report.format_clips(s)
    none = report.summarise(evals[-1:], mode="init")
    assert none["sigma_calibration"]["within_2sigma"] is None and none["sigma_calibration"]["note"].startswith(
        "no sigma")
    assert "scale sigma: no sigma" in report.format_tables(none)


def test_ablation_table_lists_variants(evals) -> None:
    s = report.summarise(evals, mode="init")
    text = report.format_ablation({"TLS": s, "OLS": s})
    assert [line.split()[0] for line in text.splitlines()[-2:]] == ["TLS", "OLS"]


def _has_colour(img: np.ndarray, rgb: tuple[float, float, float], tol: float = 0.06, min_px: int = 30) -> bool:
    return int((np.abs(img[..., :3] - np.asarray(rgb)) < tol).all(axis=-1).sum()) >= min_px


def test_plot_is_a_png_with_the_four_trajectory_colours(tmp_path, evals) -> None:
    path = plot.save_plot(tmp_path / "eval.png", evals[:1], title="constructed")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = imread(path)
    assert img.shape[0] > 300 and img.shape[1] > 600
    from matplotlib.colors import to_rgb
    for name in ("gt", "base", "imu", "vi3"):
        assert _has_colour(img, to_rgb(plot.COLORS[name])), f"{name} ({plot.COLORS[name]}) not drawn"


def test_plot_without_vi3_has_no_green(tmp_path) -> None:
    from matplotlib.colors import to_rgb
    img = imread(plot.save_plot(tmp_path / "fail.png", [make_clip_eval(5, ok=False)]))
    assert _has_colour(img, to_rgb(plot.COLORS["base"]))
    assert not _has_colour(img, to_rgb(plot.COLORS["vi3"]), min_px=1)


def test_backproject_puts_points_at_depth_along_rays() -> None:
    T = np.tile(np.eye(4), (1, 1, 1))
    g = _geometry(T, np.full((1, H, W), 2.0))
    pts = plot.backproject(g, step=1)
    assert pts.shape == (H * W, 3)
    np.testing.assert_allclose(pts[:, 2], 2.0)
    np.testing.assert_allclose(pts[0], [(0 - 16.0) / 20.0 * 2.0, (0 - 12.0) / 20.0 * 2.0, 2.0])


def test_ground_basis_is_orthonormal_and_horizontal() -> None:
    down = np.array([0.1, 0.95, 0.2])
    B = plot.ground_basis(down)
    np.testing.assert_allclose(B @ B.T, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(B @ down, 0.0, atol=1e-12)


def test_tum_round_trip_and_export(tmp_path, evals) -> None:
    e = evals[0]
    stamps, T = tum.read_tum(tum.write_tum(tmp_path / "x.txt", e.stamps, e.T_gt))
    np.testing.assert_allclose(stamps, e.stamps)
    np.testing.assert_allclose(T, e.T_gt, atol=1e-8)
    paths = tum.export_tum(tmp_path / "tum", evals)
    names = sorted(p.name for p in paths)
    assert "clip000_vi3.txt" in names and "clip000_imu.txt" in names and "clip002_base.txt" in names
    assert "clip002_vi3.txt" not in names  # the unobservable clip has no metric output
    assert len(np.loadtxt(tmp_path / "tum" / "clip001_gt.txt")) == N


def test_trajectory_axes_draw_the_four_trajectories_projected_top_down(evals) -> None:
    from matplotlib.colors import same_color
    from matplotlib.figure import Figure

    e = evals[0]
    ax_traj, ax_cloud = Figure().subplots(1, 2)
    plot.draw_clip(ax_traj, ax_cloud, e)
    lines = {line.get_label(): line for line in ax_traj.get_lines()}
    assert set(lines) == {"GT", "Base 3DFM", "IMU", "VI3"}
    B = plot.ground_basis(e.down_c1)
    for label, name in (("GT", "gt"), ("Base 3DFM", "base"), ("IMU", "imu"), ("VI3", "vi3")):
        assert same_color(lines[label].get_color(), plot.COLORS[name])
        np.testing.assert_allclose(np.column_stack(lines[label].get_data()), e.trajectories()[name][:, :3, 3] @ B.T,
                                   atol=1e-12)
    assert len(ax_cloud.collections) == 2  # base and VI3 point clouds


def test_sigma_plot_is_log_log_with_the_one_and_two_sigma_lines(tmp_path) -> None:
    from matplotlib.figure import Figure

    from vi3_core.eval.claims import Claims

    chained = Claims.of([0.01, 0.2, 0.03], [0.02, 0.05, np.nan])
    own = Claims.of([0.1, np.nan], [0.04, 0.1])
    ax = Figure().subplots()
    plot.draw_sigma(ax, {"chained": chained, "own init": own})
    assert ax.get_xscale() == "log" and ax.get_yscale() == "log"
    lines = {line.get_label(): np.column_stack(line.get_data()) for line in ax.get_lines()}
    np.testing.assert_allclose(lines["error = sigma"][:, 1], lines["error = sigma"][:, 0])
    np.testing.assert_allclose(lines["error = 2 sigma"][:, 1], 2.0 * lines["error = 2 sigma"][:, 0])
    offsets = [c.get_offsets() for c in ax.collections]
    np.testing.assert_allclose(offsets[0], [[0.02, 0.01], [0.05, 0.2]])  # the clip without a sigma is not drawn
    np.testing.assert_allclose(offsets[1], [[0.04, 0.1]])
    path = plot.save_sigma_plot(plot.sigma_plot_path(tmp_path / "eval.png"), {"chained": Claims.of([0.1], [np.nan])})
    assert path.name == "eval_sigma.png" and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    empty = Figure().subplots()
    plot.draw_sigma(empty, {"chained": Claims.of([0.1], [np.nan])})
    assert [t.get_text() for t in empty.texts][0].startswith("no sigma") and not empty.collections


def _online_run(*, scored: bool):
    from vi3_core.eval import runner
    from vi3_core.eval.chained import chained_metrics

    stamps = 0.1 * np.arange(10)
    T_WB = np.repeat(np.eye(4)[None], 10, 0)
    T_WB[:, 0, 3] = np.arange(10.0)
    T_OB = T_WB.copy()
    T_OB[5:, 1, 3] += 2.0  # a jump where the second segment starts
    run = runner.OnlineRun(stamps, T_OB, T_WB, segment_starts=[0.5], decisions=["window 1 clips"] * 4, resets=2,
                           scale_err=np.array([0.9, 0.9, 0.9, 0.02]),
                           independent_status=["ok", "ok", "unobservable", "ok"],
                           independent_scale_err=np.array([0.5, 0.05, np.nan, 0.15]),
                           independent_rel_sigma=np.array([np.nan, 0.1, np.nan, 0.05]))
    if scored:
        run.metrics = chained_metrics(T_OB, T_WB, stamps=stamps, segment_starts=run.segment_starts)
    else:
        run.reason = "not applicable: the clips are not contiguous"
    return run


def test_chained_report_per_segment_resets_and_the_own_inits_claims(evals) -> None:
    ch = report.chained_summary(_online_run(scored=True))
    assert ch["applicable"] and ch["segments"] == 2 and ch["resets"] == 2 and ch["ate_m"] == pytest.approx(0.0)
    assert ch["independent_claimed_outliers"] == {"count": 2, "claimed": 3, "share": pytest.approx(2 / 3)}
    cal = ch["independent_sigma_calibration"]
    assert cal["with_sigma"] == 2 and cal["within_2sigma"] == 0.5 and cal["within_1sigma"] == 0.5
    assert [c["status"] for c in ch["independent_clips"]] == ["ok", "ok", "unobservable", "ok"]
    _strict(report.to_json(ch))
    text = report.format_chained(ch, report.summarise(evals, mode="init"))
    assert text.splitlines()[4].split()[0] == "segment"
    assert "own init: claimed scales more than 10 % off: 2 of 3" in text
    na = report.chained_summary(_online_run(scored=False))
    assert not na["applicable"] and na["ate_m"] is None and na["segments"] is None
    assert "not contiguous" in report.format_chained(na, report.summarise(evals, mode="init"))


def test_pooled_chained_names_the_sequences_it_could_not_score() -> None:
    pooled = report.pool_chained([("a", _online_run(scored=True)), ("b", _online_run(scored=False))])
    assert pooled["sequences"] == 2 and pooled["scored"] == 1 and pooled["segments"] == 2 and pooled["resets"] == 4
    assert pooled["not_scored"] == [{"sequence": "b", "reason": "not applicable: the clips are not contiguous"}]
    assert pooled["independent_claimed_outliers"]["count"] == 4
    assert "not scored: b: not applicable" in report.format_pooled_chained(pooled)
