"""GT-free initialisation on simulated clips (n = 8, stride 2 at 20 Hz, 200 Hz IMU with EuRoC noise, gyro bias
N(0, 0.02), a 0.1 m/s^2 accelerometer bias, unknown scale in [0.1, 10], 1 mm / 0.3 deg per-frame pose noise, medians
over clips): the default error-model fit ("eiv") and the paper's Eq. S ("tls", kept as the ablation)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vi3_core import so3
from vi3_core.fit import metric_fit
from vi3_core.init import InitOptions, initialise, validate
from vi3_core.sim.imu import ImuNoise
from vi3_core.sim.visual import InitCase, PoseNoise, make_init_case
from vi3_core.types import ImuSamples, InitStatus

NOISY = dict(pose_noise=PoseNoise(pos_m=0.001, rot_deg=0.3))
PAPER = InitOptions(scale_solver="tls")
#: The error model told that the IMU is exact (for noise-free data the fit must then be exact and claim it).
EXACT = InitOptions(accel_noise_density=0.0, gyro_noise_density=0.0, gyro_scale_error=0.0, scale_rel_floor=0.0)


def _run(case: InitCase, **kw):
    return initialise(case.geometry, case.imu, case.stamps, case.T_BC, **kw)


def _tilted(g: np.ndarray, deg: float, rng: np.random.Generator) -> np.ndarray:
    axis = np.cross(g, rng.standard_normal(3))
    return so3.exp(axis / np.linalg.norm(axis) * np.radians(deg)) @ g


def _errors(case: InitCase, r) -> dict:
    return dict(bg=np.linalg.norm(r.bg - case.bg), g=np.degrees(so3.angle_between(r.g, case.g)),
                s=abs(r.scale / case.scale - 1.0), v1_dir=np.degrees(so3.angle_between(r.v1, case.v1)),
                v1_mag=abs(np.linalg.norm(r.v1) - np.linalg.norm(case.v1)) / np.linalg.norm(case.v1))


def _medians(n_clips: int, seed_deg: float | None = None, options: InitOptions | None = None, **case_kw) -> dict:
    errs = []
    for i in range(n_clips):
        case = make_init_case(i, **case_kw)
        seeds = None if seed_deg is None else {"geocalib": _tilted(case.g, seed_deg, np.random.default_rng(i))}
        r = _run(case, seeds=seeds, options=options)
        assert r.status is InitStatus.OK, r.reason
        errs.append(_errors(case, r) | {"s_ols": abs(r.diagnostics["s_ols"] / case.scale - 1.0)})
    return {k: float(np.median([e[k] for e in errs])) for k in errs[0]}


@pytest.mark.slow
@pytest.mark.parametrize("options, motion", [(EXACT, "medium"), (PAPER, "agile")], ids=["eiv", "tls"])
def test_zero_noise_is_exact_from_the_inertial_seed(options, motion):
    """Noise-free data: the error-model fit (told the IMU is exact) is exact on realistic motion. The paper's fixed
    point is exact on well excited (agile) motion only: on the gentler medium preset, noise-free clip 63 converges to
    a wrong fixed point (scale 18 % off, gravity 2.2 deg) and is claimed; the fit's joint solution does not."""
    errs = []
    for i in range(100):
        case = make_init_case(i, imu_noise=ImuNoise.zero(), motion=motion, accel_bias=False)
        r = _run(case, options=options)
        assert r.ok and r.gravity_source == "imu_fixed_point", r.reason
        errs.append(_errors(case, r))
        # Every clip is close; weakly accelerated ones amplify the integrator's O(dt^2) error a little.
        assert errs[-1]["s"] < 1e-3 and errs[-1]["g"] < 0.05, errs[-1]
        # The metric target reproduces the true body trajectory.
        np.testing.assert_allclose(r.target.p, case.T_B1Bi[:, :3, 3], atol=1e-3)
        np.testing.assert_allclose(r.target.T_wc[0], np.eye(4), atol=1e-12)
    m = {k: float(np.median([e[k] for e in errs])) for k in errs[0]}
    # The integrator's O(dt^2) error weighs more against the gentle accelerations of the medium preset.
    assert m["s"] < 5e-4 and m["v1_mag"] < 5e-4 and m["g"] < 0.01 and m["bg"] < 2e-4, m


@pytest.mark.slow
def test_paper_solver_meets_targets():
    m = _medians(100, options=PAPER, imu_noise=ImuNoise(), **NOISY)
    assert m["bg"] <= 0.008 and m["g"] <= 1.6, m
    assert m["s"] <= 0.5 and m["v1_dir"] <= 1.5 and m["v1_mag"] <= 0.5, m
    # TLS is closer to the truth than OLS under this noise (regression dilution).
    assert m["s"] < m["s_ols"], m


@pytest.mark.slow
def test_paper_solver_with_gravity_seed_one_degree_off():
    m = _medians(100, seed_deg=1.0, options=PAPER, imu_noise=ImuNoise(), **NOISY)
    assert m["s"] <= 0.3 and m["v1_mag"] <= 0.3, m


@pytest.mark.slow
def test_error_model_claims_only_what_its_sigma_supports():
    """Per-clip claims of the default fit on noisy clips: every claimed scale within 3 sigma and under 10 % off, sigma
    below the limit, every other clip unobservable with its sigma (or its missing excitation) in the reason."""
    claimed, errs = 0, []
    for i in range(100):
        case = make_init_case(i, pose_noise=PoseNoise(pos_m=0.0003, rot_deg=0.02))
        r = _run(case)
        if r.ok:
            claimed += 1
            e = abs(r.scale / case.scale - 1.0)
            assert e < 3 * r.scale_sigma / r.scale and e < 0.1 and r.scale_sigma / r.scale <= 0.04, (i, e)
            errs.append(e)
        else:
            assert r.status is InitStatus.UNOBSERVABLE and np.isnan(r.scale), r.reason
            assert "relative sigma" in r.reason or "acceleration RMS" in r.reason, r.reason
    assert claimed >= 5 and np.median(errs) < 0.03, (claimed, errs)


@pytest.mark.parametrize("options", [InitOptions(), PAPER], ids=["eiv", "tls"])
@pytest.mark.parametrize("kind", ["stationary", "pure_rotation", "hover"])
def test_degenerate_motion_is_unobservable(kind, options):
    for i in range(10):
        r = _run(make_init_case(i, kind=kind, **NOISY), options=options)
        assert r.status is InitStatus.UNOBSERVABLE, (kind, i, r.reason, r.diagnostics.get("accel_rms"))
        assert "unobservable" in r.reason
        assert np.isnan(r.scale) and r.target is None


def test_lever_arm_is_metric_and_never_scaled():
    """A 40 cm lever arm and extreme scales: still exact without noise."""
    for scale in (0.1, 10.0):
        case = make_init_case(3, imu_noise=ImuNoise.zero(), scale=scale)
        T_BC = case.T_BC.copy()
        T_BC[:3, 3] = [0.25, -0.2, 0.25]
        # Rebuild the visual poses for the new extrinsics from the same body motion.
        T_wc = so3.inv_T(T_BC) @ case.T_B1Bi @ T_BC
        T_wc[:, :3, 3] /= scale
        geometry = dataclasses.replace(case.geometry, T_wc=T_wc)
        r = initialise(geometry, case.imu, case.stamps, T_BC, options=EXACT)
        assert r.ok and abs(r.scale / scale - 1) < 5e-4, (r.reason, r.scale, scale)  # integrator's O(dt^2)


def test_a_clip_whose_fit_has_not_settled_claims_no_scale(monkeypatch):
    """A clip claimed at its error model's sigma (26 %, the gate opened to 50 %) is unobservable where no step still to
    go is small enough (``SETTLED_SIGMAS`` 0), its reason naming the step, and its ``ScaleFit`` says it has not
    settled."""
    case, gate = make_init_case(0, **NOISY), InitOptions(max_scale_sigma=0.5)
    r = _run(case, options=gate)
    assert r.ok and r.fit.settled, r.reason
    monkeypatch.setattr(metric_fit, "SETTLED_SIGMAS", 0.0)
    r = _run(case, options=gate)
    assert r.status is InitStatus.UNOBSERVABLE and not r.fit.settled, r.reason
    assert r.reason.startswith("scale unobservable: the fit has not settled (the Gauss-Newton step"), r.reason


def test_fixed_point_iterates_to_convergence_not_three_steps():
    """The paper's "2-3 iterations" stop far from the fixed point; Steffensen reaches the same point fast."""
    for i in (5, 10):
        case = make_init_case(i, imu_noise=ImuNoise.zero())
        fast = _run(case, options=PAPER)
        plain = _run(case, options=InitOptions(scale_solver="tls", fp_accelerate=False, fp_max_iters=20_000))
        three = _run(case, options=InitOptions(scale_solver="tls", fp_accelerate=False, fp_max_iters=3))
        assert fast.diagnostics["fp_imu_converged"] and plain.diagnostics["fp_imu_converged"]
        assert fast.iterations < plain.iterations
        assert np.degrees(so3.angle_between(fast.g, plain.g)) < 1e-3
        assert not three.diagnostics["fp_imu_converged"]
        assert np.degrees(so3.angle_between(three.g, case.g)) > 10 * np.degrees(so3.angle_between(fast.g, case.g))


def test_consensus_guard_rejects_a_wrong_seed_and_keeps_a_good_one():
    rng = np.random.default_rng(0)
    for i in range(10):
        case = make_init_case(i, imu_noise=ImuNoise(), **NOISY)
        bad = _run(case, seeds={"geocalib": _tilted(case.g, 60.0, rng)})
        assert bad.gravity_source == "imu_fixed_point" and "geocalib" in bad.diagnostics["rejected_seeds"]
        good = _run(case, seeds={"geocalib": _tilted(case.g, 1.0, rng)})
        assert good.gravity_source == "seed:geocalib"
        forced = _run(case, seeds={"geocalib": _tilted(case.g, 60.0, rng)}, options=InitOptions(use_consensus=False))
        assert forced.gravity_source == "seed:geocalib"


def test_orientation_from_the_imu_message_is_a_seed():
    """The paper adopts a seed that passes the guard as it is; the default fit starts from it and refines it."""
    case = make_init_case(2, imu_noise=ImuNoise(), with_orientation=True, **NOISY)
    r = _run(case, options=PAPER)
    assert r.gravity_source == "seed:orientation"
    assert np.degrees(so3.angle_between(r.g, case.g)) < 0.05
    refined = _run(case)
    assert refined.gravity_source == "seed:orientation"
    assert np.degrees(so3.angle_between(refined.g, case.g)) < 1.0


@pytest.mark.slow
def test_long_window_seed_from_imu_history():
    from vi3_core.sim.imu import imu_stamps, simulate_imu
    from vi3_core.sim.trajectory import make_trajectory

    errs = []
    for i in range(10):
        case = make_init_case(i, imu_noise=ImuNoise(), **NOISY)
        history = simulate_imu(make_trajectory("drone", seed=i), imu_stamps(case.stamps[0] - 8, case.stamps[0] + 8),
                               bg0=case.bg, seed=i + 7).samples
        r = initialise(case.geometry, case.imu, case.stamps, case.T_BC, imu_history=history, options=PAPER)
        assert r.gravity_source == "seed:long_window", r.gravity_source
        errs.append(np.degrees(so3.angle_between(r.g, case.g)))
    assert np.median(errs) < 1.0, errs


def test_first_pair_ablation_runs_and_differs():
    case = make_init_case(1, imu_noise=ImuNoise(), **NOISY)
    a = _run(case, options=PAPER)
    b = _run(case, options=InitOptions(scale_solver="tls", v1_method="first_pair"))
    assert a.ok and b.ok and b.diagnostics["v1_method"] == "first_pair"
    assert not np.allclose(a.v1, b.v1)


def test_motionless_backbone_output_is_unobservable_not_an_exception():
    case = make_init_case(0, imu_noise=ImuNoise(), **NOISY)
    still = case.geometry.T_wc.copy()
    still[:, :3, 3] = 0.0
    r = initialise(dataclasses.replace(case.geometry, T_wc=still), case.imu, case.stamps, case.T_BC)
    assert r.status is InitStatus.UNOBSERVABLE and "no change of velocity" in r.reason


def test_short_imu_history_is_not_used_as_a_gravity_seed():
    from vi3_core.sim.imu import imu_stamps, simulate_imu
    from vi3_core.sim.trajectory import make_trajectory

    case = make_init_case(0, imu_noise=ImuNoise(), **NOISY)
    history = simulate_imu(make_trajectory("drone", seed=0), imu_stamps(case.stamps[0] - 2, case.stamps[-1]),
                           bg0=case.bg, seed=7).samples
    r = initialise(case.geometry, case.imu, case.stamps, case.T_BC, imu_history=history)
    assert r.gravity_source == "imu_fixed_point" and "long_window" not in r.diagnostics["seeds"]


@pytest.mark.parametrize("options", [InitOptions(), PAPER], ids=["eiv", "tls"])
def test_anti_aligned_visual_motion_is_not_given_a_scale(options):
    case = make_init_case(4, imu_noise=ImuNoise(), **NOISY)
    flipped = case.geometry.T_wc.copy()
    flipped[:, :3, 3] *= -1.0
    r = initialise(dataclasses.replace(case.geometry, T_wc=flipped), case.imu, case.stamps, case.T_BC, options=options)
    assert r.status is InitStatus.UNOBSERVABLE and "disagree" in r.reason, r.reason


def test_backbone_rotation_failure_is_rejected_with_the_angle():
    """A frame whose rotation is off by degrees (a 3DFM failure) is rejected before any scale is claimed."""
    case = make_init_case(6, pose_noise=PoseNoise(pos_m=0.001, rot_deg=0.1))
    broken = case.geometry.T_wc.copy()
    broken[4, :3, :3] = so3.exp(np.radians([0.0, 4.0, 0.0])) @ broken[4, :3, :3]
    r = initialise(dataclasses.replace(case.geometry, T_wc=broken), case.imu, case.stamps, case.T_BC)
    assert r.status is InitStatus.REJECTED and "backbone failure" in r.reason and "frames" in r.reason, r.reason
    assert r.diagnostics["rotation_residual_deg"] > 2.0
    assert _run(case).status is not InitStatus.REJECTED  # the intact clip passes


def _with_imu(case: InitCase, **changes) -> ImuSamples:
    imu = case.imu
    fields = dict(t=imu.t.copy(), gyro=imu.gyro.copy(), accel=imu.accel.copy())
    fields.update(changes)
    return ImuSamples(**fields)


@pytest.mark.parametrize("fault, expect", [
    ("nan", "NaN"), ("gap", "gap"), ("non_monotonic", "not strictly increasing"), ("short", "covers"),
    ("sparse", "IMU sample"), ("stamps", "frame stamps"),
])
def test_bad_data_is_rejected_with_a_reason(fault, expect):
    case = make_init_case(0, **NOISY)
    imu, stamps = case.imu, case.stamps
    options = InitOptions(max_imu_gap=0.1)
    mid = len(imu.t) // 2
    if fault == "nan":
        accel = imu.accel.copy()
        accel[mid, 1] = np.nan
        imu = _with_imu(case, accel=accel)
    elif fault == "gap":
        keep = np.ones(len(imu.t), bool)
        keep[mid:mid + 30] = False
        imu = imu.select(keep)
    elif fault == "non_monotonic":
        t = imu.t.copy()
        t[mid], t[mid + 1] = t[mid + 1], t[mid]
        imu = _with_imu(case, t=t)
    elif fault == "short":
        imu = imu.select(imu.t < stamps[-2])
    elif fault == "sparse":
        options = InitOptions(max_imu_gap=0.1, min_samples_per_interval=5)
        imu = imu.select((np.arange(len(imu.t)) % 9 == 0) | (imu.t <= stamps[0]) | (imu.t >= stamps[-1]))
    elif fault == "stamps":
        stamps = stamps.copy()
        stamps[3] = stamps[2]
    r = initialise(case.geometry, imu, stamps, case.T_BC, options=options)
    assert r.status is InitStatus.REJECTED and expect in r.reason, r.reason


def test_a_gap_just_over_the_limit_is_named_with_the_digits_that_show_it():
    """A 0.0500001 s IMU gap against max_imu_gap 0.05: the message never reads "0.050 s ... (max 0.050 s)"."""
    t = np.concatenate([np.arange(5) * 0.01, 0.04 + 0.0500001 + np.arange(5) * 0.01])
    imu = ImuSamples(t, np.zeros((len(t), 3)), np.zeros((len(t), 3)))
    reason = validate.check_imu(imu, np.array([0.0, 0.05, 0.13]), InitOptions(max_imu_gap=0.05))
    assert reason is not None and "IMU gap of 0.0500001 s > max_imu_gap 0.0500000 s" in reason, reason


def test_a_gap_of_exactly_max_imu_gap_at_an_epoch_passes_on_its_integer_ns():
    """Issue 25: at EuRoC's epoch float64 seconds resolve ~0.24 us, so a 50 ms gap between two ns stamps read
    0.0500002 s > 0.0500000 s and rejected the clip. Samples that carry their ns stamps are judged on them."""
    t0 = 1_403_636_579_758_555_392  # EuRoC MH_01's first IMU stamp
    ns = np.concatenate([t0 + np.arange(5) * 10_000_000, t0 + 40_000_000 + 50_000_000 + np.arange(5) * 10_000_000])
    stamps = ns[[0, 4, 9]] * 1e-9
    options = InitOptions(max_imu_gap=0.05)
    floats = ImuSamples(ns * 1e-9, np.zeros((len(ns), 3)), np.zeros((len(ns), 3)))
    assert "IMU gap of 0.0500002 s > max_imu_gap 0.0500000 s" in validate.check_imu(floats, stamps, options)
    exact = ImuSamples(ns * 1e-9, np.zeros((len(ns), 3)), np.zeros((len(ns), 3)), t_ns=ns)
    assert validate.check_imu(exact, stamps, options) is None
    assert validate.check_imu(exact.select(slice(1, None)), stamps[1:], options) is None  # t_ns follows select
    ns[5:] += 1
    late = ImuSamples(ns * 1e-9, np.zeros((len(ns), 3)), np.zeros((len(ns), 3)), t_ns=ns)
    assert "IMU gap of 0.050000001 s > max_imu_gap 0.050000000 s" in validate.check_imu(late, stamps, options)
