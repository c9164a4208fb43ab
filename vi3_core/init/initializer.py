"""The GT-free inertial initialiser (paper Sec. "Inertial state initialization"): a facade that validates the
data, estimates bg (Eq. bg), runs the scale/gravity fixed point from each gravity seed, applies the consensus
guard (Eq. guard), then hands the clip to one scale solver: the error-model fit (default, ``_error_model_scale``:
scale, gravity, v1 and both biases with a sigma) or the paper's Eq. S / Eq. v0 (``_paper_scale``), checks
observability and builds the metric IMU target trajectory.

Physical assumptions: biases constant over the clip (the error-model fit estimates the accelerometer bias with a
prior; the paper's solvers assume it negligible, after Kaiser et al.), and enough acceleration during the clip for
velocity increments to observe scale. With constant velocity, hover, pure rotation or no motion the scale is
unobservable: the result then says so and claims no scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vi3_core import so3
from vi3_core.fit import FitClip, MetricFit
from vi3_core.fit.position import body_position_terms
from vi3_core.init import gravity_seeds, validate
from vi3_core.init.gyro_bias import RotationCheck, body_rotations, gyro_bias_eq, refine_gyro_bias, rotation_check
from vi3_core.init.options import InitOptions
from vi3_core.init.velocity_gravity import ScaleGravitySystem
from vi3_core.preintegration import Preintegration, merged_grid, preintegrate
from vi3_core.threads import single_blas_thread
from vi3_core.types import Geometry, ImuSamples, InitResult, InitStatus, ScaleFit


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


@dataclass
class _Inertial:
    """What both scale solvers start from (``_inertial``): the clip's stamps [n] s, gyro bias bg [3] rad/s, its
    rotation check, the preintegration (with bias Jacobians for the error-model fit), the paper's scale/gravity system,
    the adopted gravity g [3] (B1) with its source and consensus angle, the body acceleration RMS (m/s^2), the
    scale-free parallax and the diagnostics so far."""

    stamps: np.ndarray
    bg: np.ndarray
    check: RotationCheck
    pre: Preintegration
    system: ScaleGravitySystem
    g: np.ndarray
    source: str
    consensus: float
    accel_rms: float
    parallax: float
    diag: dict

    def result(self) -> InitResult:
        """The ok result of the gravity estimate, before a solver adds the scale."""
        return InitResult(InitStatus.OK, "ok", bg=self.bg, g=self.g, gravity_source=self.source,
                          consensus_deg=self.consensus, iterations=int(self.diag["fp_imu_iterations"]),
                          diagnostics=self.diag)


def _initialise(geometry: Geometry, imu: ImuSamples, stamps: np.ndarray, T_BC: np.ndarray, options: InitOptions,
                seeds: dict[str, np.ndarray] | None, imu_history: ImuSamples | None) -> InitResult:
    stamps = np.asarray(stamps, dtype=np.float64)
    reason = (validate.check_stamps(stamps) or validate.check_geometry(geometry, len(stamps))
              or validate.check_imu(imu, stamps, options))
    if reason:
        return InitResult(InitStatus.REJECTED, reason)
    inertial = _inertial(geometry, imu, stamps, T_BC, options, seeds, imu_history)
    if isinstance(inertial, InitResult):
        return inertial
    if options.scale_solver == "eiv":
        return _error_model_scale(inertial, geometry, T_BC, options)
    return _paper_scale(inertial, T_BC, options)


def _inertial(geometry: Geometry, imu: ImuSamples, stamps: np.ndarray, T_BC: np.ndarray, options: InitOptions,
              seeds: dict[str, np.ndarray] | None, imu_history: ImuSamples | None) -> _Inertial | InitResult:
    """The gyro bias (Eq. bg, then the all-pairs refinement), the check of the backbone's rotations against it (a
    rejected InitResult when they disagree), and gravity (Eqs. gimu / gls, fixed point, Eq. guard over the seeds)."""
    G = options.gravity_norm
    dt_imu = float(np.median(np.diff(imu.t)))
    R_vis = body_rotations(geometry.T_wc[:, :3, :3], T_BC)
    grid = merged_grid(imu, stamps)
    bg = gyro_bias_eq(R_vis, grid.gyro_mean, np.diff(stamps), dt_imu)
    bg_eq = bg.copy()
    bg = refine_gyro_bias(imu, stamps, R_vis, bg, options.bg_refine_iters, grid=grid)
    check = rotation_check(imu, stamps, R_vis, bg, grid=grid)
    worst, i, j = check.worst()
    if worst > options.max_rotation_error:
        return InitResult(InitStatus.REJECTED, rotation_failure(worst, i, j, options.max_rotation_error), bg=bg,
                          diagnostics={"rotation_residual_deg": worst})
    pre = preintegrate(imu, stamps, bg, grid=grid, jacobians=options.scale_solver == "eiv")
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
    return _Inertial(stamps, bg, check, pre, system, g, source, consensus, accel_rms, parallax, diag)


def _unobservable(inertial: _Inertial, options: InitOptions) -> str | None:
    """Why no solver can claim the clip's scale (no visual signal, too little acceleration or parallax), or None."""
    if inertial.system.visual_signal == 0.0:
        return "scale unobservable: the backbone predicts no change of velocity"
    if inertial.accel_rms < options.min_accel_rms:
        return (f"scale unobservable: body acceleration RMS {inertial.accel_rms:.3f} m/s^2 < min_accel_rms "
                f"{options.min_accel_rms} (hover, constant velocity, pure rotation or no motion)")
    if inertial.parallax < options.min_parallax:
        return (f"scale unobservable: visual baseline/depth {inertial.parallax:.4f} < {options.min_parallax} (no "
                "parallax)")
    return None


def _error_model_scale(inertial: _Inertial, geometry: Geometry, T_BC: np.ndarray,
                       options: InitOptions) -> InitResult:
    """The default solver (beyond the paper): the backbone's positions regressed on the IMU kinematics with the error
    model (``vi3_core.fit.MetricFit``), gravity, first-frame velocity and both biases refined jointly from the paper's
    gravity; the scale is claimed when its relative 1-sigma passes ``max_scale_sigma``. Assumes constant biases over
    the clip (the accelerometer bias has a prior of ``accel_bias_sigma``, the gyro bias one of its rotation-check
    spread) and visual noise independent per frame, estimated from the clip's own residuals."""
    fit = MetricFit([FitClip(inertial.stamps, geometry.T_wc)], inertial.pre, T_BC, noise=options.noise_model,
                    gravity_norm=options.gravity_norm, bg_sigma=inertial.check.bias_sigma(len(inertial.stamps)))
    res = fit.solve(fit.initial_state(inertial.g))
    st = res.state
    g_sigma, v1_sigma = res.state_sigma(0)
    own = ScaleFit(lam=float(st.lam[0]), scale_rel_sigma=float(res.scale_rel_sigma[0]), v1=st.v[0],
                   v1_sigma=v1_sigma, g_sigma=g_sigma, sigma_v=float(res.sigma_v[0]), dof=float(res.dof[0]),
                   variance_factor=res.variance_factor, settled=res.settled(0), time_offset=st.td,
                   time_offset_sigma=res.time_offset_sigma)
    result = inertial.result()
    result.g, result.bg, result.ba, result.fit = st.g, st.bg, st.ba, own
    s, rel = float(res.scale[0]), own.scale_rel_sigma
    why = _unobservable(inertial, options)
    if why is None and not s > 0.0:
        why = ("scale unobservable: visual and inertial motion disagree (the fitted scale is not positive); the "
               "paper's fallback s = 1 is not claimed")
    elif why is None and not rel <= options.max_scale_sigma:
        why = (f"scale unobservable: relative sigma {rel:.3g} > max_scale_sigma {options.max_scale_sigma} (visual "
               f"noise {1e3 * own.sigma_v_m:.1f} mm per axis, body acceleration RMS {inertial.accel_rms:.2f} m/s^2)")
    elif why is None and not own.settled:
        why = (f"scale unobservable: the fit has not settled (the Gauss-Newton step still to go moves the scale by "
               f"{res.step_sigmas(0):.2g} sigma)")
    if why:
        result.status, result.reason = InitStatus.UNOBSERVABLE, why
        return result
    result.scale, result.scale_sigma, result.v1 = s, rel * s, st.v[0]
    result.target = inertial.pre.corrected(st.bg, st.ba).propagate(st.g, st.v[0], T_BC)
    return result


def _paper_scale(inertial: _Inertial, T_BC: np.ndarray, options: InitOptions) -> InitResult:
    """The paper's solvers (ablations): Eq. S by total least squares ("tls") or OLS at the adopted gravity, v1 by
    Eq. v0. No error model: the scale carries no sigma, and the accelerometer bias is assumed negligible (Kaiser et
    al.); a scale is claimed whenever the visual and inertial velocity increments align (``min_alignment``)."""
    system, g = inertial.system, inertial.g
    s = system.scale(g, options.scale_solver)
    alignment = system.alignment(g)
    result = inertial.result()
    result.diagnostics["alignment"] = alignment
    why = _unobservable(inertial, options)
    if why is None and (not s > 0.0 or alignment < options.min_alignment):
        why = (f"scale unobservable: visual and inertial motion disagree (cos {alignment:.2f} < "
               f"{options.min_alignment}); the paper's fallback s = 1 is not claimed")
    if why:
        result.status, result.reason = InitStatus.UNOBSERVABLE, why
        return result
    result.scale, result.scale_sigma = float(s), float("nan")
    result.v1, result.diagnostics["v1_method"] = system.initial_velocity(s, g, options.v1_method)
    result.target = inertial.pre.propagate(g, result.v1, T_BC)
    return result


#: how the reason of a clip whose backbone rotations disagree with the gyro starts (``rotation_failure``)
GYRO_FAILURE = "backbone failure"


def rotation_failure(worst_deg: float, i: int, j: int, limit_deg: float) -> str:
    """The reason of a clip whose backbone rotations disagree with the bias-corrected gyro."""
    return (f"{GYRO_FAILURE}: its relative rotation between frames {i} and {j} disagrees with the bias-corrected "
            f"gyro by {worst_deg:.2f} deg (max_rotation_error {limit_deg} deg)")


def initialise_clip(clip, geometry: Geometry, *, options: InitOptions | None = None,
                    seeds: dict[str, np.ndarray] | None = None) -> InitResult:
    """``initialise`` on a ``Clip`` (uses its stamps, IMU, T_BC and IMU history)."""
    return initialise(geometry, clip.imu, clip.stamps, clip.T_BC, options=options, seeds=seeds,
                      imu_history=clip.imu_history)


__all__ = ["initialise", "initialise_clip", "rotation_failure", "select_gravity"]
