"""The GT-free inertial initialiser (paper Sec. "Inertial state initialization"): a facade that validates the
data, estimates bg (Eq. bg), runs the scale/gravity fixed point from each gravity seed, applies the consensus
guard (Eq. guard), recovers v1 (Eq. v0), checks observability and builds the metric IMU target trajectory.

Physical assumptions: constant biases over the clip, negligible accelerometer bias (Kaiser et al.), and
enough acceleration during the clip for velocity increments to observe scale. With constant velocity, hover,
pure rotation or no motion the scale is unobservable: the result then says so and claims no scale.
"""

from __future__ import annotations

import math

import numpy as np

from vi3_core import so3
from vi3_core.init import gravity_seeds, validate
from vi3_core.init.gyro_bias import body_rotations, gyro_bias_eq, refine_gyro_bias, rotation_check
from vi3_core.init.metric_fit import FitClip, MetricFit
from vi3_core.init.options import InitOptions
from vi3_core.init.position_fit import body_position_terms
from vi3_core.init.velocity_gravity import ScaleGravitySystem
from vi3_core.preintegration import merged_grid, preintegrate
from vi3_core.threads import single_blas_thread
from vi3_core.types import Geometry, ImuSamples, InitResult, InitStatus


def _deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(float(so3.angle_between(a, b)))


def _parallax(geometry: Geometry) -> float:
    """Largest camera displacement from the first frame over the median valid depth (scale-free)."""
    sample = geometry.depth.reshape(-1)[::7]  # a subsample: the median of ~10^5 pixels costs milliseconds
    depth = sample[np.isfinite(sample) & (sample > 0)]
    if depth.size == 0:
        return float("inf")  # no depth to compare with: leave the decision to the inertial checks
    t = geometry.T_wc[:, :3, 3]
    return float(np.linalg.norm(t - t[0], axis=1).max() / np.median(depth))


def select_gravity(system: ScaleGravitySystem, g_imu: np.ndarray, seeds: dict[str, np.ndarray],
                   options: InitOptions) -> tuple[np.ndarray, str, float, dict]:
    """Consensus between external seeds and the inertial fixed point (Eq. guard).

    Returns the adopted gravity, its source, the consensus angle (deg, NaN when no external seed) and
    diagnostics. An external seed X is an outlier when min(angle(g_X, FP(g_X)), angle(g_X, FP(g_imu))) >
    max(angle(FP(g_X), FP(g_imu)), gamma_min); then the next seed is tried, and with none left the inertial
    fixed point is adopted, provided it is not inverted relative to the raw accelerometer seed.
    """
    kw = dict(solver=options.scale_solver, tol_deg=options.fp_tol_deg, max_iters=options.fp_max_iters,
              accelerate=options.fp_accelerate)
    fp_imu = system.fixed_point(g_imu, **kw)
    diag: dict = {"fp_imu_iterations": fp_imu.iterations, "fp_imu_converged": fp_imu.converged,
                  "g_imu_seed": g_imu, "g_imu_fp": fp_imu.g}
    consensus = float("nan")
    for name in options.seed_priority:
        g_x = seeds.get(name)
        if g_x is None:
            continue
        g_x = options.gravity_norm * np.asarray(g_x, dtype=np.float64) / np.linalg.norm(g_x)
        if not options.use_consensus:
            return g_x, f"seed:{name}", consensus, diag
        fp_x = system.fixed_point(g_x, **kw)
        consensus = _deg(fp_x.g, fp_imu.g)
        closest = min(_deg(g_x, fp_x.g), _deg(g_x, fp_imu.g))
        diag[f"seed_{name}_closest_deg"] = closest
        if not closest > max(consensus, options.gamma_min_deg):  # Eq. guard
            return g_x, f"seed:{name}", consensus, diag
        diag.setdefault("rejected_seeds", []).append(name)
    if float(fp_imu.g @ g_imu) < 0.0:
        return g_imu, "imu_seed (inertial fixed point inverted)", consensus, diag
    return fp_imu.g, "imu_fixed_point", consensus, diag


def initialise(geometry: Geometry, imu: ImuSamples, stamps: np.ndarray, T_BC: np.ndarray, *,
               options: InitOptions | None = None, seeds: dict[str, np.ndarray] | None = None,
               imu_history: ImuSamples | None = None) -> InitResult:
    """GT-free initialisation of one clip.

    geometry: up-to-scale backbone output (T_wc in the first camera frame C1); imu: samples covering the clip;
    stamps: [n] frame times, s; T_BC: [4,4] camera pose in the body frame; seeds: external gravity seeds in B1
    by name ("orientation", "geocalib", "long_window"; see ``gravity_seeds``); imu_history: seconds of IMU
    around the clip for the long-window seed. Bad data yields status ``rejected`` with the reason, never raises.
    """
    with single_blas_thread():
        return _initialise(geometry, imu, stamps, T_BC, options or InitOptions(), seeds, imu_history)


def _initialise(geometry: Geometry, imu: ImuSamples, stamps: np.ndarray, T_BC: np.ndarray, options: InitOptions,
                seeds: dict[str, np.ndarray] | None, imu_history: ImuSamples | None) -> InitResult:
    stamps = np.asarray(stamps, dtype=np.float64)
    reason = (validate.check_stamps(stamps) or validate.check_geometry(geometry, len(stamps))
              or validate.check_imu(imu, stamps, options))
    if reason:
        return InitResult(InitStatus.REJECTED, reason)
    G = options.gravity_norm
    dt_imu = float(np.median(np.diff(imu.t)))
    eiv = options.scale_solver == "eiv"

    # Gyro bias: Eq. bg, then the all-pairs refinement; then the backbone's rotations must agree with it.
    R_vis = body_rotations(geometry.T_wc[:, :3, :3], T_BC)
    grid = merged_grid(imu, stamps)
    bg = gyro_bias_eq(R_vis, grid.gyro_mean, np.diff(stamps), dt_imu)
    bg_eq = bg.copy()
    bg = refine_gyro_bias(imu, stamps, R_vis, bg, options.bg_refine_iters, grid=grid)
    check = rotation_check(imu, stamps, R_vis, bg, grid=grid)
    worst, i, j = check.worst()
    if worst > options.max_rotation_deg:
        return InitResult(InitStatus.REJECTED, rotation_failure(worst, i, j, options.max_rotation_deg), bg=bg,
                          diagnostics={"rotation_residual_deg": worst})
    pre = preintegrate(imu, stamps, bg, grid=grid, jacobians=eiv)

    a, b = body_position_terms(geometry.T_wc, pre.R, T_BC)
    system = ScaleGravitySystem(a, b, pre, gravity_norm=G)

    all_seeds = dict(seeds or {})
    orient = gravity_seeds.orientation_seed(imu, stamps[0], G)
    if orient is not None:
        all_seeds.setdefault("orientation", orient)
    history = gravity_seeds.long_window_seed(imu_history, stamps[0], bg, G)
    if history is not None:
        all_seeds.setdefault("long_window", history)
    g_imu = gravity_seeds.imu_seed(pre, G)
    g, source, consensus, diag = select_gravity(system, g_imu, all_seeds, options)
    # Excitation is measured against the accelerometer's own gravity: what remains is the acceleration that
    # varies over the clip, the only part a gravity tilt cannot absorb (and it does not depend on s).
    accel_rms = system.accel_rms(g_imu)
    parallax = _parallax(geometry)
    diag.update(bg_eq=bg_eq, s_tls=system.scale(g, "tls"), s_ols=system.scale(g, "ols"), accel_rms=accel_rms,
                parallax=parallax, seeds=sorted(all_seeds), rotation_residual_deg=worst, g_seed=g)
    result = InitResult(InitStatus.OK, "ok", bg=bg, g=g, gravity_source=source, consensus_deg=consensus,
                        iterations=int(diag["fp_imu_iterations"]), diagnostics=diag)

    if eiv:
        fit = MetricFit([FitClip(stamps, geometry.T_wc)], pre, T_BC, noise=options.noise_model, gravity_norm=G,
                        bg_sigma=check.bias_sigma(len(stamps)))
        fit = fit.solve(fit.initial_state(g))
        st = fit.state
        s, rel = float(fit.scale[0]), float(fit.scale_rel_sigma[0])
        sigma_v_m = float(fit.sigma_v[0] / st.lam[0]) if st.lam[0] > 0 else float("nan")
        g_sigma, v1_sigma = fit.state_sigma(0)
        diag.update(scale_rel_sigma=rel, sigma_v_m=sigma_v_m, sigma_v_model=float(fit.sigma_v[0]),
                    fit_dof=float(fit.dof[0]), fit_converged=fit.converged, variance_factor=fit.variance_factor,
                    fit_lam=float(st.lam[0]), fit_v1=st.v[0], v1_sigma=v1_sigma, g_sigma_deg=math.degrees(g_sigma))
        result.g, result.bg, result.ba = st.g, st.bg, st.ba
        disagree = not s > 0.0
        weak = not rel <= options.max_scale_rel_sigma
    else:
        s, rel = system.scale(g, options.scale_solver), float("nan")
        alignment = system.alignment(g)
        diag["alignment"] = alignment
        disagree = not s > 0.0 or alignment < options.min_alignment
        weak = False

    why = None
    if system.visual_signal == 0.0:
        why = "scale unobservable: the backbone predicts no change of velocity"
    elif accel_rms < options.min_accel_rms:
        why = (f"scale unobservable: body acceleration RMS {accel_rms:.3f} m/s^2 < {options.min_accel_rms} "
               "(hover, constant velocity, pure rotation or no motion)")
    elif parallax < options.min_parallax:
        why = f"scale unobservable: visual baseline/depth {parallax:.4f} < {options.min_parallax} (no parallax)"
    elif disagree:
        why = ("scale unobservable: visual and inertial motion disagree "
               + (f"(cos {diag['alignment']:.2f} < {options.min_alignment}); " if not eiv else
                  "(the fitted scale is not positive); ") + "the paper's fallback s = 1 is not claimed")
    elif weak:
        why = (f"scale unobservable: relative sigma {rel:.3g} > {options.max_scale_rel_sigma} (visual noise "
               f"{1e3 * diag['sigma_v_m']:.1f} mm per axis, body acceleration RMS {accel_rms:.2f} m/s^2)")
    if why:
        result.status, result.reason = InitStatus.UNOBSERVABLE, why
        return result

    result.scale, result.scale_sigma = float(s), float(rel * s)
    if eiv:
        result.v1 = st.v[0]
        result.target = pre.corrected(st.bg, st.ba).propagate(st.g, st.v[0], T_BC)
    else:
        result.v1, result.diagnostics["v1_method"] = system.initial_velocity(s, g, options.v1_method)
        result.target = pre.propagate(g, result.v1, T_BC)
    return result


def rotation_failure(worst_deg: float, i: int, j: int, limit_deg: float) -> str:
    """The reason of a clip whose backbone rotations disagree with the bias-corrected gyro."""
    return (f"backbone failure: its relative rotation between frames {i} and {j} disagrees with the bias-corrected "
            f"gyro by {worst_deg:.2f} deg (limit {limit_deg} deg)")


def initialise_clip(clip, geometry: Geometry, *, options: InitOptions | None = None,
                    seeds: dict[str, np.ndarray] | None = None) -> InitResult:
    """``initialise`` on a ``Clip`` (uses its stamps, IMU, T_BC and IMU history)."""
    return initialise(geometry, clip.imu, clip.stamps, clip.T_BC, options=options, seeds=seeds,
                      imu_history=clip.imu_history)


__all__ = ["initialise", "initialise_clip", "rotation_failure", "select_gravity"]
