"""``vi3_core.fit.metric_fit``: the backbone positions regressed on the IMU with an error model, over one clip and a
window, its marginalisation, and the preintegration's bias Jacobians it rests on. Simulated EuRoC-like clips
(``make_init_case``: EuRoC IMU noise, a 0.1 m/s^2 accelerometer bias, an unknown scale in [0.1, 10])."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vi3_core import so3
from vi3_core.fit import FitClip, ImuNoiseModel, MetricFit, ScaleLink, fit_stamps, marginalise
from vi3_core.fit.layout import PriorLayout, StateLayout
from vi3_core.fit.metric_fit import _links_whitener
from vi3_core.fit.prior import GaussianPrior, sqrt_of_info
from vi3_core.init import InitOptions, initialise
from vi3_core.online.window import Member, Window
from vi3_core.preintegration import preintegrate
from vi3_core.sim.imu import EUROC_NOISE, ImuNoise, imu_stamps, simulate_imu
from vi3_core.sim.trajectory import make_trajectory
from vi3_core.sim.visual import PoseNoise, make_init_case, noisy_poses

#: An IMU model that says "exact": for noise-free data the fit must then be exact too.
EXACT = ImuNoiseModel(accel_noise_density=0.0, gyro_noise_density=0.0, gyro_scale_error=0.0, rel_floor=0.0)
REALISTIC = PoseNoise(pos_m=0.003, rot_deg=0.1)


def _fit(case, noise: ImuNoiseModel | None = None):
    noise = noise or ImuNoiseModel()
    bg = case.bg
    clips = [FitClip(case.stamps, case.geometry.T_wc)]
    fit = MetricFit(clips, preintegrate(case.imu, fit_stamps(clips), bg, jacobians=True), case.T_BC, noise=noise,
                    gravity_norm=9.81)
    return fit.solve(fit.initial_state(case.g))


def test_bias_jacobians_match_finite_differences():
    case = make_init_case(3)
    bg, ba = case.bg, np.array([0.05, -0.1, 0.08])
    pre = preintegrate(case.imu, case.stamps, bg, ba, jacobians=True)
    for i, e in enumerate(1e-6 * np.eye(3)):
        moved = preintegrate(case.imu, case.stamps, bg + e, ba)
        np.testing.assert_allclose(so3.log(moved.R @ np.swapaxes(pre.R, 1, 2)) / 1e-6, pre.J.phi_bg[..., i],
                                   atol=1e-5)
        np.testing.assert_allclose((moved.alpha - pre.alpha) / 1e-6, pre.J.alpha_bg[..., i], atol=1e-5)
        np.testing.assert_allclose((moved.beta - pre.beta) / 1e-6, pre.J.beta_bg[..., i], atol=1e-5)
        shifted = preintegrate(case.imu, case.stamps, bg, ba + e * 1e6)  # exact: linear in ba
        np.testing.assert_allclose(shifted.alpha - pre.alpha, pre.J.alpha_ba[..., i], atol=1e-10)
    assert np.abs(pre.J.alpha_bg).max() > 1e-3  # not trivially zero
    corrected = pre.corrected(bg + 1e-3, ba + 0.02)
    fresh = preintegrate(case.imu, case.stamps, bg + 1e-3, ba + 0.02)
    np.testing.assert_allclose(corrected.alpha, fresh.alpha, atol=1e-6)
    np.testing.assert_allclose(corrected.R, fresh.R, atol=1e-7)


def test_single_clip_is_exact_without_noise():
    case = make_init_case(5, imu_noise=ImuNoise.zero())
    res = _fit(case, EXACT)
    s = res.state
    assert abs(res.scale[0] / case.scale - 1) < 5e-4 and res.converged  # the integrator's O(dt^2)
    assert np.degrees(so3.angle_between(s.g, case.g)) < 0.01 and np.linalg.norm(s.v[0] - case.v1) < 1e-3
    assert res.sigma_v[0] * case.scale < 1e-5  # no visual noise found where there is none


@pytest.mark.slow
def test_eq_s_is_biased_low_by_visual_noise_and_the_fit_is_not():
    """3 mm / 0.1 deg per frame: Eq. S divides by noise-inflated velocity increments (regression dilution). The fit's
    errors are centred on zero relative to their own sigma (on realistic motion a single clip's sigma is large: its
    median ratio alone says little), and its error model covers them."""
    ratio_tls, z = [], []
    for i in range(60):
        case = make_init_case(i, pose_noise=REALISTIC)
        res = _fit(case)
        z.append((res.scale[0] / case.scale - 1) / res.scale_rel_sigma[0])
        tls = initialise(case.geometry, case.imu, case.stamps, case.T_BC, options=InitOptions(scale_solver="tls"))
        ratio_tls.append(tls.diagnostics["s_tls"] / case.scale)
    z = np.array(z)
    assert np.median(ratio_tls) < 0.7, ratio_tls
    assert abs(np.median(z)) < 0.5 and np.mean(np.abs(z) < 2) >= 0.9, z  # Eq. S: 0.39 of the true scale


@pytest.mark.slow
def test_visual_noise_is_recovered_from_the_clips_own_residuals():
    for pos in (0.001, 0.005):
        found = []
        for i in range(30):
            case = make_init_case(i, pose_noise=PoseNoise(pos_m=pos))
            found.append(_fit(case).sigma_v[0] * case.scale)
        assert 0.75 * pos < np.median(found) < 1.25 * pos, (pos, np.median(found))


def _window_case(seed: int, n_clips: int, pose_noise: PoseNoise, *, ba=(0.1, -0.05, 0.08),
                 imu_noise: ImuNoise = EUROC_NOISE):
    """Consecutive 8-frame clips (stride 2 at 20 Hz, one every 0.8 s) of one simulated flight, each with its own
    scale: (imu, clips, true scales, true bg, true gravity [K,3] in each clip's first body frame, T_BC)."""
    rng = np.random.default_rng(seed)
    traj = make_trajectory("drone", seed=seed)
    starts = 5.0 + 0.8 * np.arange(n_clips)
    imu = simulate_imu(traj, imu_stamps(4.9, starts[-1] + 0.8), noise=imu_noise, bg0=np.array([0.01, -0.02, 0.015]),
                       ba0=np.asarray(ba), seed=seed)
    T_BC = make_init_case(0).T_BC
    scales = np.exp(rng.uniform(-1.0, 1.0, n_clips))
    clips = []
    for t0, s in zip(starts, scales):
        stamps = t0 + np.arange(8) * 0.1
        T_WC = traj.T_WB(stamps) @ T_BC
        T_wc = so3.inv_T(T_WC[0]) @ T_WC
        clips.append(FitClip(stamps, noisy_poses(T_wc, scale=s, noise=pose_noise, rng=rng), None))
    g = np.einsum("kji,j->ki", traj.rotation(starts), np.array([0.0, 0.0, -9.81]))
    return imu.samples, clips, scales, imu.bg[0], g, T_BC


def _solve_window(imu, clips, bg, g, T_BC, sigma_v, priors=(), **options):
    """``sigma_v``: each clip's visual noise in its model units [K] (or one value for all); ``options``: MetricFit's."""
    clips = [FitClip(c.stamps, c.T_wc, s) for c, s in zip(clips, np.broadcast_to(sigma_v, len(clips)))]
    pre = preintegrate(imu.window(clips[0].stamps[0], clips[-1].stamps[-1]), fit_stamps(clips), bg, jacobians=True)
    fit = MetricFit(clips, pre, T_BC, noise=ImuNoiseModel(), gravity_norm=9.81, **options)
    return fit, fit.solve(fit.initial_state(g), priors=priors)


def test_window_recovers_every_scale_gravity_and_the_accel_bias():
    imu, clips, scales, bg, g, T_BC = _window_case(1, 8, REALISTIC)
    _, res = _solve_window(imu, clips, bg, g[0], T_BC, sigma_v=0.003 / scales)
    assert np.all(np.abs(res.scale / scales - 1) < 3 * res.scale_rel_sigma), (res.scale / scales, res.scale_rel_sigma)
    assert np.median(np.abs(res.scale / scales - 1)) < 0.03
    assert np.degrees(so3.angle_between(res.state.g, g[0])) < 1.0
    assert np.linalg.norm(res.state.ba - np.array([0.1, -0.05, 0.08])) < 0.08


def test_a_scale_has_settled_where_the_step_still_to_go_moves_it_by_a_quarter_sigma_at_most():
    """A window's fit stopped early (one step a pass) from scales three times too large. The Gauss-Newton step still
    to go from there (``FitResult.next_step``) is the step the fit takes next, and says how far each clip's scale is
    from where the fit ends, in its sigmas (the linearised ones: the unconverged residual put the variance factor at
    500): no clip has settled. One step a pass later every clip has, within half a sigma of the end."""
    imu, clips, scales, bg, g, T_BC = _window_case(1, 6, REALISTIC)
    lams = StateLayout(6).lams

    def stopped(iterations: int):
        fit, _ = _solve_window(imu, clips, bg, g[0], T_BC, sigma_v=0.003 / scales)
        early = fit.solve(fit.initial_state(g[0], lam=1.0 / (3.0 * scales)), iterations=iterations)
        taken, _ = fit._gauss_newton(early.state.copy(), early.sigma_v, (), 1, 1e-4, False)
        np.testing.assert_allclose(early.state.lam - taken.lam, early.next_step[lams], rtol=1e-6)
        done = fit.solve(early.state)
        assert not early.converged and done.converged
        assert all(done.settled(k) and done.step_sigmas(k) < 0.01 for k in range(6))
        sigma = np.sqrt(np.diag(early.cov)[lams] / early.variance_factor)
        return early, np.abs(early.state.lam - done.state.lam) / sigma

    early, to_go = stopped(1)
    step = np.array([early.step_sigmas(k) for k in range(6)])
    assert early.variance_factor > 10 and not any(early.settled(k) for k in range(6)), (early.variance_factor, step)
    assert np.all((step > 0.5 * to_go) & (step < 2 * to_go)), (step, to_go)
    later, to_go = stopped(2)
    assert all(later.settled(k) for k in range(6)) and to_go.max() < 0.5, to_go


def test_window_makes_weak_clips_observable_that_are_not_on_their_own():
    imu, clips, scales, bg, g, T_BC = _window_case(2, 8, REALISTIC)
    own = []
    for c, g_k in zip(clips, g):
        pre = preintegrate(imu, fit_stamps([c]), bg, jacobians=True)
        fit = MetricFit([c], pre, T_BC, noise=ImuNoiseModel(), gravity_norm=9.81)
        own.append(fit.solve(fit.initial_state(g_k)).scale_rel_sigma[0])
    _, res = _solve_window(imu, clips, bg, g[0], T_BC, sigma_v=0.003 / scales)
    assert np.median(res.scale_rel_sigma) < 0.5 * np.median(own), (res.scale_rel_sigma, own)


@pytest.mark.parametrize("walk", [0.0, 1e-5])
def test_errors_in_variables_jacobian_is_the_derivative_of_the_whitened_residual(walk):
    """With the levels estimated, each scale's column carries the whitening's own dependence on it (the IMU's part of
    the visual rows' covariance grows with lam^2): it matches a finite difference of the whitened residual, with the
    visual rows whitened by weights (no walk) or by a Cholesky factor (a walk); without it, it does not."""
    imu, clips, scales, bg, g, T_BC = _window_case(1, 5, REALISTIC)
    clips = [FitClip(c.stamps, c.T_wc, 0.003 / s) for c, s in zip(clips, scales)]
    pre = preintegrate(imu.window(clips[0].stamps[0], clips[-1].stamps[-1]), fit_stamps(clips), bg, jacobians=True)
    sigma_v = 0.003 / scales
    for levels in (True, False):
        fit = MetricFit(clips, pre, T_BC, noise=ImuNoiseModel(), gravity_norm=9.81, estimate_levels=levels)
        fit.walk, fit.imu_level = walk, 3.0
        s = fit.initial_state(g[0])
        y, A, _, _ = fit.linearise(s, sigma_v, ())
        col, h = fit.layout.lam(2), 1e-6 * s.lam[2]
        moved = s.copy()
        moved.lam[2] += h
        fd = (fit.linearise(moved, sigma_v, ())[0] - y) / h
        err = np.abs(fd - A[:, col]).max() / np.abs(A[:, col]).max()
        assert (err < 1e-5) if levels else (err > 1e-3), (levels, err)


def test_a_clip_seen_at_constant_velocity_is_not_claimed_at_a_vanishing_scale():
    """A backbone that puts the clip's cameras on a straight line at constant speed, where the IMU felt acceleration:
    the best fit explains the motion as lam v (a velocity in model units) with lam near 0 and |v| near 1e5 m/s. lam's
    column is then orders of magnitude above the others', and before the columns were scaled for the covariance's
    cut-off, gravity's and the biases' directions were dropped and lam read as known to its 1 % floor (scale 1.3e5)."""
    imu, clips, _, bg, g, T_BC = _window_case(5, 1, PoseNoise(pos_m=0.001, rot_deg=0.05))
    T = clips[0].T_wc.copy()
    stamps = clips[0].stamps
    t = T[:, :3, 3]
    along = (stamps - stamps[0]) / (stamps[-1] - stamps[0])
    T[:, :3, 3] = t[0] + along[:, None] * (t[-1] - t[0]) + np.random.default_rng(5).normal(0.0, 1e-4, t.shape)
    clip = FitClip(stamps, T)
    pre = preintegrate(imu.window(stamps[0], stamps[-1]), fit_stamps([clip]), bg, jacobians=True)
    fit = MetricFit([clip], pre, T_BC, noise=ImuNoiseModel(), gravity_norm=9.81)
    res = fit.solve(fit.initial_state(g[0]))
    assert abs(res.state.lam[0]) < 1e-4 and np.linalg.norm(res.state.v[0]) > 1e4, (res.state.lam, res.state.v)
    assert res.scale_rel_sigma[0] > 1.0, res.scale_rel_sigma


def _online_levels(seed: int, accel_noise_density: float, levels: bool):
    """A 24 s flight of 30 clips, 0.5 mm / 0.02 deg pose noise (where the IMU's part of the error model matters) and an
    IMU at ``accel_noise_density`` against the model's 0.02, fed clip by clip to an online ``Window`` (8 s, as the
    estimator does): (each clip's scale error and relative sigma when it was the newest, from the 10th clip on; the
    window's final noise levels)."""
    imu, clips, scales, bg, g, T_BC = _window_case(seed, 30, PoseNoise(pos_m=0.0005, rot_deg=0.02),
                                                   imu_noise=ImuNoise(accel_noise_density=accel_noise_density))
    window = Window(noise=ImuNoiseModel(), gravity_norm=9.81, window_s=8.0, max_clips=12, noise_levels=levels)
    err, rel = [], []
    for k, (clip, scale) in enumerate(zip(clips, scales)):
        member = Member(clip.stamps, clip.T_wc, 0.0005 / scale, float("nan"), np.full(3, np.nan), g[k])
        sol = window.solve(member, imu, bg, 5e-4, T_BC)
        window.commit(sol)
        if k >= 10:
            err.append(sol.result.scale[-1] / scale - 1)
            rel.append(sol.result.scale_rel_sigma[-1])
    return np.array(err), np.array(rel), window.levels


@pytest.mark.slow
def test_online_window_learns_the_imu_level_and_is_not_attenuated_by_a_noisy_imu():
    """An IMU three times noisier than the model says (a level of 9): with the model's level the window's scales are
    attenuated (biased high, their sigmas too small: 75 % within 2 sigma); with ``noise_levels`` the level learnt over
    the flight comes out near 9 and the errors are covered (the clips of a window share their errors, so 40 clips of
    two flights centre only to about half a sigma). An IMU a third as noisy (a level of 0.09): the level is learnt,
    and the scales, fitted at it, stay covered by sigmas that take the IMU at no less than its model."""
    err, rel, _ = _online_levels(0, 0.06, False)
    assert np.median(err / rel) > 0.5 and np.mean(np.abs(err) < 2 * rel) < 0.8, (np.median(err / rel), np.median(rel))
    runs = [_online_levels(seed, 0.06, True) for seed in (0, 1)]
    err, rel = (np.concatenate([r[i] for r in runs]) for i in (0, 1))
    assert all(3.0 < r[2][0] < 27.0 for r in runs), [r[2] for r in runs]
    assert abs(np.median(err / rel)) < 0.6 and np.mean(np.abs(err) < 2 * rel) >= 0.85, \
        (np.median(err / rel), np.median(rel))
    err, rel, levels = _online_levels(0, 0.006, True)
    assert levels[0] < 0.3 and abs(np.median(err / rel)) < 0.5 and np.mean(np.abs(err) < 2 * rel) >= 0.9, \
        (levels, np.median(err / rel))


def test_a_clips_trajectory_off_its_depth_is_no_confident_claim_with_its_traj_depth_sigma():
    """Eight linked clips (the links: the true depth ratios at 1 %), one of whose trajectories is 13 % short of its
    depth: taken at one scale, the links carry that clip's trajectory scale 12 % off at a 2 % sigma; with its
    traj_depth_sigma (10 %) the window leaves it to its own IMU (within 2 sigma) and the other clips as they were."""
    imu, clips, scales, bg, g, T_BC = _window_case(3, 8, PoseNoise(pos_m=0.01, rot_deg=0.1))
    off, shrink = 5, 0.87
    T = clips[off].T_wc.copy()
    T[:, :3, 3] *= shrink
    truth = scales.copy()
    truth[off] /= shrink
    links = [ScaleLink(float(np.log(scales[k - 1] / scales[k])), 0.01) for k in range(1, len(clips))]
    out = {}
    for tau in (0.0, 0.1):
        fitted = [FitClip(c.stamps, T if k == off else c.T_wc, 0.01 / s, tau if k == off else 0.0)
                  for k, (c, s) in enumerate(zip(clips, scales))]
        pre = preintegrate(imu.window(fitted[0].stamps[0], fitted[-1].stamps[-1]), fit_stamps(fitted), bg,
                           jacobians=True)
        fit = MetricFit(fitted, pre, T_BC, noise=ImuNoiseModel(), gravity_norm=9.81, scale_links=links)
        res = fit.solve(fit.initial_state(g[0]))
        out[tau] = (res.scale / truth - 1, res.scale_rel_sigma)
    (err0, sig0), (err1, sig1) = out[0.0], out[0.1]
    assert abs(err0[off]) > 4 * sig0[off], (err0, sig0)
    assert abs(err1[off]) < 2 * sig1[off], (err1, sig1)
    others = np.arange(len(clips)) != off
    assert np.all(np.abs(err1[others]) < 2 * sig1[others]) and np.allclose(sig1[others], sig0[others], rtol=0.1)


def test_the_scale_links_whitener_is_a_random_effect_per_clip():
    """Links 1, 2 (sharing clip 1) and 4: variances sigma^2 + tau_k^2 + tau_(k-1)^2, -tau_1^2 between the first two,
    none with the link that shares no clip."""
    W = _links_whitener([(1, 0.0, 0.01), (2, 0.0, 0.02), (4, 0.0, 0.01)], [0.0, 0.05, 0.03, 0.0, 0.1])
    C = np.linalg.inv(W.T @ W)
    np.testing.assert_allclose(C, [[0.01**2 + 0.05**2, -0.05**2, 0.0],
                                   [-0.05**2, 0.02**2 + 0.05**2 + 0.03**2, 0.0],
                                   [0.0, 0.0, 0.01**2 + 0.1**2]], atol=1e-12)
    assert np.allclose(W, np.tril(W))


def test_marginalising_old_clips_keeps_their_evidence():
    """Dropping the first clips into a prior leaves the remaining estimates where the full window put them (up to what
    the prior deliberately loses: the biases' random walk, the attitude's walk to the frame it is carried into, and
    the ties' and the fit's variance factors)."""
    imu, clips, scales, bg, g, T_BC = _window_case(3, 7, REALISTIC)
    fit, full = _solve_window(imu, clips, bg, g[0], T_BC, sigma_v=0.003 / scales)
    for drop in (1, 3):
        prior = marginalise(fit, full, drop)
        R_f = fit.pre.R[fit.blocks[drop].first]
        _, reduced = _solve_window(imu, clips[drop:], bg, R_f.T @ full.state.g, T_BC, sigma_v=0.003 / scales[drop:],
                                   priors=(prior,))
        assert np.all(np.abs(reduced.scale / full.scale[drop:] - 1) < 0.5 * full.scale_rel_sigma[drop:])
        walk = np.sqrt(np.sum(fit.attitude_walk[1:drop + 1] ** 2))  # rad: the widening of the prior's g
        assert so3.angle_between(reduced.state.g, R_f.T @ full.state.g) < 1e-3 + walk
        alone = _solve_window(imu, clips[drop:], bg, R_f.T @ full.state.g, T_BC, sigma_v=0.003 / scales[drop:])[1]
        assert np.median(reduced.scale_rel_sigma) < np.median(alone.scale_rel_sigma)  # the prior carries evidence


def test_marginalising_a_fit_whose_covariance_floors_the_imu_level_keeps_its_estimates():
    """With the noise levels estimated and an IMU level below the model's, the window's covariance is taken at the
    model's level (``MetricFit.solve``) but its state was fitted at the lower one: the marginal prior carries the
    gradient where the state was fitted, so a window of the remaining clips at the same level finds the same scales
    (within a tenth of a sigma; with the gradient at the floor's level they moved by up to 0.3 sigma)."""
    imu, clips, scales, bg, g, T_BC = _window_case(3, 7, PoseNoise(pos_m=0.0005, rot_deg=0.02))
    sigma_v = 0.0005 / scales

    def solve(clips, sigma_v, g, priors=()):
        clips = [FitClip(c.stamps, c.T_wc, s) for c, s in zip(clips, sigma_v)]
        pre = preintegrate(imu.window(clips[0].stamps[0], clips[-1].stamps[-1]), fit_stamps(clips), bg,
                           jacobians=True)
        fit = MetricFit(clips, pre, T_BC, noise=ImuNoiseModel(), gravity_norm=9.81, estimate_levels=True)
        fit.imu_level = 0.05
        return fit, fit.solve(fit.initial_state(g), priors=priors)

    fit, full = solve(clips, sigma_v, g[0])
    assert (fit.fitted_imu_level, fit.imu_level) == (0.05, 1.0)
    for drop in (1, 3):
        R_f = fit.pre.R[fit.blocks[drop].first]
        _, reduced = solve(clips[drop:], sigma_v[drop:], R_f.T @ full.state.g, (marginalise(fit, full, drop),))
        moved = (reduced.scale / full.scale[drop:] - 1) / full.scale_rel_sigma[drop:]
        assert np.all(np.abs(moved) < 0.1), moved


def test_widening_a_prior_adds_the_bias_walk_and_leaves_free_directions_free():
    """``GaussianPrior.widened``: where the information is invertible, the covariance plus the biases' walk, inverted
    (to 1e-8), the mean kept; with g's radial direction free (as ``marginalise`` makes them) that direction stays
    free and the rest is the covariance form on the complement. The prior in tests/core/data was a window's on a
    generated sequence (``difficult`` seed 11, clip 34): widening it through the covariance ended the evaluation
    with "Eigenvalues did not converge"."""
    Z = PriorLayout
    q = np.zeros(Z.n)
    q[Z.ba], q[Z.bg] = 2e-5, 3e-9
    rng = np.random.default_rng(4)
    S = rng.standard_normal((Z.n, Z.n)) * 10 ** rng.uniform(1, 4, Z.n)
    prior = GaussianPrior(rng.standard_normal(Z.n), S, rng.standard_normal(Z.n))
    wide = prior.widened(2e-5, 3e-9)
    expected = np.linalg.inv(np.linalg.inv(S.T @ S) + np.diag(q))
    np.testing.assert_allclose(wide.sqrt_info.T @ wide.sqrt_info, expected, rtol=1e-8,
                               atol=1e-8 * np.abs(expected).max())

    def mean(p: GaussianPrior) -> np.ndarray:
        return p.center - np.linalg.lstsq(p.sqrt_info, p.offset, rcond=None)[0]

    np.testing.assert_allclose(mean(wide), mean(prior), atol=1e-9)

    free = np.zeros(Z.n)
    free[Z.g] = [0.2, -9.8, 0.5] / np.linalg.norm([0.2, -9.8, 0.5])
    W = np.linalg.svd(np.eye(Z.n) - np.outer(free, free))[0][:, :-1]  # [n,n-1] the complement of ``free``
    S_free = rng.standard_normal((Z.n - 1, Z.n - 1)) * 10 ** rng.uniform(1, 4, Z.n - 1) @ W.T
    wide = GaussianPrior(np.zeros(Z.n), S_free, rng.standard_normal(Z.n - 1)).widened(2e-5, 3e-9)
    assert np.abs(wide.sqrt_info @ free).max() < 1e-9 * np.abs(wide.sqrt_info).max()
    info_W = W.T @ S_free.T @ S_free @ W
    expected = W @ np.linalg.inv(np.linalg.inv(info_W) + W.T @ np.diag(q) @ W) @ W.T
    np.testing.assert_allclose(wide.sqrt_info.T @ wide.sqrt_info, expected, atol=1e-8 * np.abs(expected).max())

    saved = np.load(Path(__file__).parent / "data" / "prior_widening_failed.npz")
    prior = GaussianPrior(saved["center"], saved["sqrt_info"], saved["offset"])
    wide = prior.widened(float(saved["ba_var"]), float(saved["bg_var"]))
    w = np.linalg.eigvalsh(wide.sqrt_info.T @ wide.sqrt_info)
    assert np.all(np.isfinite(w)) and w[0] > -1e-9 * w[-1] and w[1] > 1e-6 * w[-1], w
    np.testing.assert_allclose(mean(wide), mean(prior), atol=1e-9)


def test_square_root_of_an_information_with_an_unknown_it_says_nothing_about():
    """``sqrt_of_info``: an unknown with no information (a zero diagonal) whose row holds round-off (1e-18) from the
    Schur complement comes back as no information; the diagonal's floor was absolute (1e-300), which scaled that
    row by 1e150 and returned S^T S off by 1e131."""
    rng = np.random.default_rng(0)
    A = rng.standard_normal((20, 5)) * [1.0, 10.0, 1e2, 1e3, 1e4]
    info = np.zeros((6, 6))
    info[:5, :5] = A.T @ A
    info[5, :5] = info[:5, 5] = 1e-18
    S = sqrt_of_info(info)
    np.testing.assert_allclose(S.T @ S, info, atol=1e-12 * np.abs(info).max())


@pytest.mark.parametrize("bad", ["model_noise", "bias_sigma"])
def test_noise_model_rejects_invalid_values(bad):
    with pytest.raises(ValueError, match="ImuNoiseModel"):
        ImuNoiseModel(accel_noise_density=-1.0) if bad == "model_noise" else ImuNoiseModel(accel_bias_sigma=0.0)
