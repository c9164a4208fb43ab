"""A metric reference for a recording without ground truth: an offline reconstruction's camera poses (up to one
unknown scale, in any world frame, e.g. COLMAP's structure from motion of the frames) given its metric scale, gravity
and the camera-IMU time offset by a batch visual-inertial fit of the whole IMU record.

The fit (beyond the paper, whose scale is per clip): keyframes at the reconstruction's stamps t_k, body poses from its
cameras (R_WB_k = R_WC_k R_CB, p_k = s c_k + R_WC_k t_CB: the scale s multiplies the reconstruction's camera centres
c_k, the lever arm is metric), the IMU preintegrated between consecutive keyframes (``preintegration``; its stamps
moved by the time offset). Per interval, in the body frame at its start (Eqs. preintegrationVelocity /
preintegrationTranslation between two keyframes):

    r_v = R_WB_k^T (v_k+1 - v_k - g dt) - dbeta_k(ba_k)
    r_p = R_WB_k^T (p_k+1 - p_k - v_k dt - g dt^2 / 2) - dalpha_k(ba_k)
    r_b = ba_k+1 - ba_k                                   (the accelerometer bias's random walk)

linear in the unknowns s, g (|g| fixed by a tangent-plane refinement), every interval's accelerometer bias ba_k and
every keyframe's velocity v_k: one sparse weighted least squares. Where asked, the accelerometer's matrix A joins
them (the specific force is A times the reading: an uncalibrated consumer IMU's scale factors and cross-axis terms,
5 % on a RealSense's, turn gravity into acceleration as the camera tilts), in dbeta and dalpha, with a prior about
the identity. The gyro bias comes first, from the
reconstruction's rotations against the gyro, and the time offset from the profile of that rotation fit over a grid of
offsets. Weights: the IMU's noise (``ImuNoiseModel``, the velocity change's sigma per interval and the position's,
both with the gyro scale error of the angle turned), the bias walk's (``accel_bias_walk``) and the reconstruction's
own position noise, each group scaled by a variance component estimated from the residuals (restricted maximum
likelihood), so that the weighting is the data's, not an assumed one: on gentle motion the scale depends on how the
IMU's errors are weighted against the reconstruction's (on a handheld recording a 3x larger assumed accelerometer
noise moved a fit with assumed weights by a quarter). The scale's sigma is the least squares' own, times
sqrt(chi^2 / dof) where that exceeds one. ``fit_halves`` fits each half of the record alone: a sigma that is right
has the halves agree within their combined sigmas.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.optimize import least_squares

from vi3_core import so3
from vi3_core.errors import DataError
from vi3_core.fit.linalg import tangent_basis
from vi3_core.fit.noise import ImuNoiseModel
from vi3_core.online.chain import gravity_align
from vi3_core.preintegration import Preintegration, frame_rotations, merged_grid, preintegrate
from vi3_core.types import ImuSamples

GRAVITY = 9.81
PROBES = 24  # Hutchinson probes per variance component and iteration
MAX_INTERVAL_S = 1.0  # keyframes further apart than this are not tied (a reconstruction that lost the camera)
MIN_KEYFRAMES = 10
# prior 1-sigma of the accelerometer matrix's elements about the identity, row-major: scale factors (the diagonal)
# of a consumer IMU are good to 1-3 %, its cross-axis terms reach several percent
ACCEL_MATRIX_SIGMA = np.where(np.eye(3, dtype=bool), 0.02, 0.1).ravel()


@dataclass(frozen=True)
class ReferenceFit:
    """The batch fit. scale: metres per reconstruction unit, scale_sigma its 1-sigma (m per unit); g [3]: gravity
    in the reconstruction's world, m/s^2; bg [3] rad/s: the gyro bias (constant over the record); ba [3] m/s^2: the
    accelerometer bias's mean over the record, ba_spread (m/s^2) the largest distance of its walk from that mean;
    time_offset: s, the IMU's stamps plus this are the camera's (t_cam = t_imu + time_offset); sigma_ref: the
    reconstruction's position noise, m; imu_noise_factor: the IMU noise model's sigmas are this times the given ones;
    accel_bias_walk: m/s^2/sqrt(s), the bias's random walk (the three estimated); accel_matrix [3,3]: the specific
    force is this times the accelerometer's reading (its scale factors and cross-axis terms; the identity unless
    fitted, ``fit_reference(accel_intrinsics=True)``), accel_matrix_sigma [3,3] its elements' 1-sigma; chi2_dof: the
    weighted residual per degree of freedom (about 1 once the variance components are estimated); keyframes,
    intervals: what was fitted; span: (first, last) keyframe stamp, s."""

    scale: float
    scale_sigma: float
    g: np.ndarray
    bg: np.ndarray
    ba: np.ndarray
    time_offset: float
    sigma_ref: float
    chi2_dof: float
    keyframes: int
    intervals: int
    span: tuple[float, float]
    imu_noise_factor: float
    accel_bias_walk: float
    ba_spread: float
    accel_matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    accel_matrix_sigma: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))

    @property
    def rel_sigma(self) -> float:
        return self.scale_sigma / self.scale

    def as_dict(self) -> dict:
        return {"scale": self.scale, "scale_sigma": self.scale_sigma, "rel_sigma": self.rel_sigma,
                "gravity": self.g.tolist(), "bg": self.bg.tolist(), "ba": self.ba.tolist(),
                "time_offset_s": self.time_offset, "sigma_ref_m": self.sigma_ref, "chi2_dof": self.chi2_dof,
                "keyframes": self.keyframes, "intervals": self.intervals, "span_s": list(self.span),
                "imu_noise_factor": self.imu_noise_factor, "accel_bias_walk": self.accel_bias_walk,
                "ba_spread": self.ba_spread, "accel_matrix": self.accel_matrix.tolist(),
                "accel_matrix_sigma": self.accel_matrix_sigma.tolist()}

    def body_track(self, stamps: np.ndarray, T_WC: np.ndarray, T_BC: np.ndarray) -> np.ndarray:
        """The metric IMU body poses [n,4,4] of the reconstruction's cameras ``T_WC`` [n,4,4] (its units) at
        ``stamps`` [n] (camera clock, kept: ``vi3 eval`` looks a frame's ground truth up at the frame's stamp), in a
        gravity-aligned world (z up, its origin at the first body position)."""
        R_align = gravity_align(np.eye(3), self.g)
        T_CB = so3.inv_T(np.asarray(T_BC, np.float64))
        T = np.array(T_WC, np.float64)
        T[:, :3, 3] *= self.scale
        T_WB = T @ T_CB
        T_WB[:, :3, :3] = R_align @ T_WB[:, :3, :3]
        T_WB[:, :3, 3] = (T_WB[:, :3, 3] - T_WB[0, :3, 3]) @ R_align.T
        return T_WB


def fit_reference(stamps: np.ndarray, T_WC: np.ndarray, imu: ImuSamples, T_BC: np.ndarray, *,
                  noise: ImuNoiseModel | None = None, offsets: np.ndarray | None = None,
                  time_offset: float | None = None, accel_intrinsics: bool = False) -> ReferenceFit:
    """The batch fit (see the module docstring) of a reconstruction's camera poses ``T_WC`` [n,4,4] (camera to its
    world, its units) at ``stamps`` [n] s (camera clock, increasing) to ``imu`` (body frame, IMU clock), camera mount
    ``T_BC`` [4,4]. ``time_offset``: s, known (skips the search), else the best of ``offsets`` (s; default -0.2 to
    0.2 s in 2 ms steps) refined to a fraction of a step. ``accel_intrinsics``: also fit the accelerometer's matrix
    (``ReferenceFit.accel_matrix``). DataError naming what is missing."""
    noise = noise or ImuNoiseModel()
    stamps, T_WC = _checked(stamps, T_WC, imu)
    R_WB = T_WC[:, :3, :3] @ np.asarray(T_BC, np.float64)[:3, :3].T
    if time_offset is None:
        grid = np.arange(-0.2, 0.2 + 1e-9, 0.002) if offsets is None else np.asarray(offsets, np.float64)
        time_offset = _best_offset(stamps, R_WB, imu, grid)
    keep = (stamps - time_offset > imu.t[0]) & (stamps - time_offset < imu.t[-1])
    if keep.sum() < MIN_KEYFRAMES:
        raise DataError(f"the IMU covers {int(keep.sum())} of the reference's {len(stamps)} poses at a time offset of "
                        f"{1e3 * time_offset:.1f} ms (need {MIN_KEYFRAMES})")
    stamps, T_WC, R_WB = stamps[keep], T_WC[keep], R_WB[keep]
    bg = _gyro_bias(stamps - time_offset, R_WB, imu)
    pre = preintegrate(imu, stamps - time_offset, bg, jacobians=True)
    # the specific force is linear in the reading: the preintegration of reading axis q put on axis j is the
    # derivative of the deltas by the matrix's element (j, q)
    parts = []
    for j, q in np.ndindex(3, 3) if accel_intrinsics else ():
        accel = np.zeros_like(imu.accel)
        accel[:, j] = imu.accel[:, q]
        parts.append(preintegrate(replace(imu, accel=accel), stamps - time_offset, bg))
    return _solve(stamps, T_WC, R_WB, np.asarray(T_BC, np.float64), pre, noise, time_offset, bg, parts)


def fit_halves(stamps: np.ndarray, T_WC: np.ndarray, imu: ImuSamples, T_BC: np.ndarray, *,
               noise: ImuNoiseModel | None = None, time_offset: float,
               accel_intrinsics: bool = False) -> tuple[ReferenceFit, ReferenceFit]:
    """``fit_reference`` of the first and the second half of the keyframes (by time) on their own, at the whole
    record's ``time_offset``."""
    stamps = np.asarray(stamps, np.float64)
    mid = 0.5 * (stamps[0] + stamps[-1])
    return tuple(fit_reference(stamps[m], np.asarray(T_WC)[m], imu, T_BC, noise=noise, time_offset=time_offset,
                               accel_intrinsics=accel_intrinsics) for m in (stamps <= mid, stamps > mid))


def _checked(stamps: np.ndarray, T_WC: np.ndarray, imu: ImuSamples) -> tuple[np.ndarray, np.ndarray]:
    stamps, T_WC = np.asarray(stamps, np.float64), np.asarray(T_WC, np.float64)
    if stamps.ndim != 1 or T_WC.shape != (len(stamps), 4, 4):
        raise DataError(f"a reference needs stamps [n] and poses [n,4,4], got {stamps.shape} and {T_WC.shape}")
    if len(stamps) < MIN_KEYFRAMES or not (np.isfinite(stamps).all() and np.isfinite(T_WC).all()):
        raise DataError(f"a reference needs >= {MIN_KEYFRAMES} finite poses, got {len(stamps)}")
    if np.any(np.diff(stamps) <= 0):
        raise DataError("the reference's stamps must increase")
    if len(imu.t) < 2:
        raise DataError("no IMU samples to fit the reference to")
    return stamps, T_WC


def _intervals(stamps: np.ndarray) -> np.ndarray:
    """[k] the keyframes k whose interval to k+1 is tied (not longer than MAX_INTERVAL_S)."""
    return np.flatnonzero(np.diff(stamps) <= MAX_INTERVAL_S)


def _rotation_residual(pre_R: np.ndarray, R_WB: np.ndarray, k: np.ndarray) -> np.ndarray:
    """[len(k),3] rad: the gyro's rotation over each tied interval against the reconstruction's."""
    dR_imu = np.swapaxes(pre_R[k], 1, 2) @ pre_R[k + 1]
    dR_ref = np.swapaxes(R_WB[k], 1, 2) @ R_WB[k + 1]
    return so3.log(np.swapaxes(dR_imu, 1, 2) @ dR_ref)


def _gyro_bias(t_imu: np.ndarray, R_WB: np.ndarray, imu: ImuSamples) -> np.ndarray:
    """The constant gyro bias [3] that best turns the gyro into the reconstruction's rotations (keyframes at
    ``t_imu``, IMU clock)."""
    grid, k = merged_grid(imu, t_imu), _intervals(t_imu)

    def residual(bg: np.ndarray) -> np.ndarray:
        return _rotation_residual(frame_rotations(grid, bg), R_WB, k).ravel()

    return least_squares(residual, np.zeros(3), method="lm", x_scale=1e-3).x


def _best_offset(stamps: np.ndarray, R_WB: np.ndarray, imu: ImuSamples, grid: np.ndarray) -> float:
    """The time offset (s) of ``grid`` whose rotation fit (the gyro bias of the whole record fitted at the grid's
    middle, the rotations compared over every tied interval) is best, refined by a parabola through its
    neighbours."""

    bg = _gyro_bias(stamps - float(np.median(grid)), R_WB, imu)
    cost = np.full(len(grid), np.inf)
    for i, dt in enumerate(grid):
        t = stamps - dt
        inside = (t > imu.t[0]) & (t < imu.t[-1])
        if inside.sum() < MIN_KEYFRAMES:
            continue
        k = _intervals(t[inside])
        r = _rotation_residual(frame_rotations(merged_grid(imu, t[inside]), bg), R_WB[inside], k)
        cost[i] = float(np.mean(r**2))
    if not np.isfinite(cost).any():
        raise DataError("the IMU does not cover the reference's poses at any time offset searched")
    i = int(np.argmin(cost))
    if 0 < i < len(grid) - 1 and np.isfinite(cost[i - 1:i + 2]).all():
        a, b, c = cost[i - 1:i + 2]
        step = grid[i + 1] - grid[i]
        den = a - 2 * b + c
        if den > 0:
            return float(grid[i] + 0.5 * step * (a - c) / den)
    return float(grid[i])


def _solve(stamps: np.ndarray, T_WC: np.ndarray, R_WB: np.ndarray, T_BC: np.ndarray, pre: Preintegration,
           noise: ImuNoiseModel, time_offset: float, bg: np.ndarray, parts: list[Preintegration]) -> ReferenceFit:
    """The fit of s, g (|g| = GRAVITY), ba_k, v_k (module docstring) by Gauss-Newton, with the reconstruction's true
    camera centres as unknowns too (c_k measured with noise sigma_ref): the scale multiplies the noisy side, and a
    least squares that took the measured centres as exact would shrink it (errors in variables: with a velocity per
    keyframe the positions enter twice differenced, their noise as large as gentle motion's acceleration); between
    Gauss-Newton solutions, the three groups' variances (IMU, bias walk, centres) by a Fisher-scoring step of their
    restricted likelihood. ``parts``: the accelerometer matrix's nine derivatives (``fit_reference``), or empty."""
    n = len(stamps)
    k = _intervals(stamps)
    m = len(k)
    if m < MIN_KEYFRAMES:
        raise DataError(f"{m} keyframe intervals of at most {MAX_INTERVAL_S} s (need {MIN_KEYFRAMES})")
    dt = np.diff(stamps)[k]
    RkT = np.swapaxes(pre.R[k], 1, 2)  # the preintegration's deltas into B_k
    J = pre.J
    dbeta = np.einsum("kij,kj->ki", RkT, pre.beta[k + 1] - pre.beta[k])
    dalpha = np.einsum("kij,kj->ki", RkT, pre.alpha[k + 1] - pre.alpha[k] - pre.beta[k] * dt[:, None])
    Jb = RkT @ (J.beta_ba[k + 1] - J.beta_ba[k])  # d dbeta / d ba [m,3,3]
    Ja = RkT @ (J.alpha_ba[k + 1] - J.alpha_ba[k] - J.beta_ba[k] * dt[:, None, None])
    c = T_WC[:, :3, 3]
    lever = np.einsum("nij,j->ni", T_WC[:, :3, :3], so3.inv_T(T_BC)[:3, 3])  # metric, world
    dlever = lever[k + 1] - lever[k]
    RbT = np.swapaxes(R_WB[k], 1, 2)  # world -> B_k (the reconstruction's rotations)
    angle = np.linalg.norm(_rotation_residual(np.tile(np.eye(3), (n, 1, 1)), R_WB, k), axis=1)
    w_v = 1.0 / np.array([noise.velocity_sigma(float(a), float(b), GRAVITY) for a, b in zip(dt, angle)])
    w_p = 1.0 / np.sqrt(noise.accel_noise_density**2 * dt**3 / 3.0
                        + (GRAVITY * noise.gyro_scale_error * angle * dt**2 / 6.0) ** 2)
    # the accelerometer bias walks (a consumer IMU's drifts by several hundredths of m/s^2 over a minute): one bias per
    # interval, consecutive ones tied over the time between their starts
    w_b = 1.0 / (max(noise.accel_bias_walk, 1e-9) * np.sqrt(np.diff(stamps[k])))
    # unknowns: s | dg (2, tangent at the current g) | ba (3m, one per interval) | v (3n) | c_hat (3n)
    iS, iG, iA = 0, 1, 3
    iV = iA + 3 * m
    iC = iV + 3 * n
    iM = iC + 3 * n
    nM = len(parts)  # dA: the accelerometer matrix less the identity, row-major, with a prior of ACCEL_MATRIX_SIGMA
    nx = iM + nM
    Dv = np.stack([np.einsum("kij,kj->ki", RkT, P.beta[k + 1] - P.beta[k]) for P in parts], 2) if nM else None
    Dp = (np.stack([np.einsum("kij,kj->ki", RkT, P.alpha[k + 1] - P.alpha[k] - P.beta[k] * dt[:, None])
                    for P in parts], 2) if nM else None)
    rv, rp, rc, rb = (r0 + 3 * np.arange(q) for r0, q in ((0, m), (3 * m, m), (6 * m, n), (6 * m + 3 * n, m - 1)))
    n_rows = 6 * m + 3 * n + 3 * (m - 1) + nM
    groups = {"imu": np.arange(6 * m), "walk": np.arange(6 * m + 3 * n, n_rows - nM),
              "centres": np.arange(6 * m, 6 * m + 3 * n)}

    def jacobian(s_: float, g: np.ndarray, basis: np.ndarray, c_hat: np.ndarray) -> sp.csc_matrix:
        rows, cols, vals = [], [], []

        def put(r0, c0, M):  # M [len(r0),3,q] at rows r0..r0+3, columns c0..c0+q
            q = M.shape[2]
            r0 = np.broadcast_to(np.asarray(r0), (len(M),))
            c0 = np.broadcast_to(np.asarray(c0), (len(M),))
            rows.append((r0[:, None, None] + np.arange(3)[None, :, None]).repeat(q, 2).ravel())
            cols.append((c0[:, None, None] + np.arange(q)[None, None, :]).repeat(3, 1).ravel())
            vals.append(M.ravel())

        eye = np.tile(np.eye(3), (m - 1, 1, 1))
        put(rv, iV + 3 * (k + 1), RbT)
        put(rv, iV + 3 * k, -RbT)
        put(rv, iG, -(RbT * dt[:, None, None]) @ basis)
        put(rv, iA + 3 * np.arange(m), -Jb)
        put(rp, iS, np.einsum("kij,kj->ki", RbT, c_hat[k + 1] - c_hat[k])[:, :, None])
        put(rp, iC + 3 * (k + 1), s_ * RbT)
        put(rp, iC + 3 * k, -s_ * RbT)
        put(rp, iV + 3 * k, -RbT * dt[:, None, None])
        put(rp, iG, -(RbT * (0.5 * dt**2)[:, None, None]) @ basis)
        put(rp, iA + 3 * np.arange(m), -Ja)
        put(rc, iC + 3 * np.arange(n), np.tile(np.eye(3), (n, 1, 1)))
        put(rb, iA + 3 * np.arange(1, m), eye)
        put(rb, iA + 3 * np.arange(m - 1), -eye)
        if nM:
            put(rv, iM, -Dv)
            put(rp, iM, -Dp)
            rows.append(n_rows - nM + np.arange(nM))
            cols.append(iM + np.arange(nM))
            vals.append(np.ones(nM))
        return sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(n_rows, nx))

    def residual(s_: float, g: np.ndarray, ba: np.ndarray, v: np.ndarray, c_hat: np.ndarray,
                 dA: np.ndarray) -> np.ndarray:
        r_v = (np.einsum("kij,kj->ki", RbT, v[k + 1] - v[k] - g * dt[:, None]) - dbeta
               - np.einsum("kij,kj->ki", Jb, ba))
        r_p = (np.einsum("kij,kj->ki", RbT, s_ * (c_hat[k + 1] - c_hat[k]) + dlever - v[k] * dt[:, None]
                         - 0.5 * g * dt[:, None] ** 2) - dalpha - np.einsum("kij,kj->ki", Ja, ba))
        if nM:
            r_v, r_p = r_v - Dv @ dA, r_p - Dp @ dA
        return np.concatenate([r_v.ravel(), r_p.ravel(), (c_hat - c).ravel(), (ba[1:] - ba[:-1]).ravel(), dA])

    # start: gravity as minus the mean specific force, the scale from the sizes of the accelerations (the
    # reconstruction's twice-differenced centres against the IMU's): only a starting point for Gauss-Newton
    g = GRAVITY * _initial_gravity(R_WB, k, dbeta)
    s_ = _initial_scale(c, stamps, R_WB, k, dt, dbeta, g)
    ba = np.zeros((m, 3))
    v = np.gradient(s_ * c, stamps, axis=0)
    c_hat = c.copy()
    dA = np.zeros(nM)
    step = float(np.median(np.linalg.norm(np.diff(c, axis=0), axis=1)))
    # the variance components: the IMU's (a factor on the noise model's densities), the bias walk's (a factor on its
    # accel_bias_walk) and the centres' (sigma_ref^2, reconstruction units); floored, so that a group the data do not
    # need keeps a finite weight
    var = {"imu": 1.0, "walk": 1.0, "centres": max(0.01 * step, 1e-9) ** 2}
    floor = {"imu": 1e-4, "walk": 1e-4, "centres": max(1e-4 * step, 1e-9) ** 2}

    def weights() -> np.ndarray:
        imu = np.repeat(np.concatenate([w_v, w_p]), 3) / math.sqrt(var["imu"])
        return np.concatenate([imu, np.full(3 * n, 1.0 / math.sqrt(var["centres"])),
                               np.repeat(w_b, 3) / math.sqrt(var["walk"]), 1.0 / ACCEL_MATRIX_SIGMA[:nM]])

    def linearised():
        """(tangent basis of g, whitened Jacobian, whitened residual, the normal matrix's LU) at the current
        unknowns and variance components."""
        basis = tangent_basis(g / GRAVITY) * GRAVITY
        w = weights()
        Jm = sp.diags(w) @ jacobian(s_, g, basis, c_hat)
        # the normal matrix is symmetric positive definite: a symmetric ordering keeps its factor sparse (COLAMD's
        # made it 50x slower on 400 keyframes)
        N = (Jm.T @ Jm).tocsc()
        return basis, Jm, w * residual(s_, g, ba, v, c_hat, dA), spla.splu(
            N, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})

    for _ in range(30):
        for _ in range(12):
            basis, Jm, r, lu = linearised()
            dx = -lu.solve(Jm.T @ r)
            s_ += dx[iS]
            g = g + basis @ dx[iG:iA]
            g = GRAVITY * g / np.linalg.norm(g)
            ba = ba + dx[iA:iV].reshape(m, 3)
            v = v + dx[iV:iC].reshape(n, 3)
            c_hat = c_hat + dx[iC:iM].reshape(n, 3)
            dA = dA + dx[iM:]
            if abs(dx[iS]) <= 1e-10 * abs(s_):
                break
        # restricted maximum likelihood of the three variances by Fisher scoring in their logarithms (Helmert's
        # one-at-a-time update crawls where they trade off, as the IMU's and the centres' do on gentle motion): in
        # whitened rows, with H the hat matrix and E_i group i's rows, the score is (r_i^T r_i - n_i + tr H_ii) / 2 and
        # the information (delta_ij (n_i - 2 tr H_ii) + |H_ij|_F^2) / 2, the traces by Hutchinson's estimator
        names = list(groups)
        tr_H = np.zeros(len(names))
        H2 = np.zeros((len(names), len(names)))
        rng = np.random.default_rng(0)
        Jr = Jm.tocsr()
        for j, name in enumerate(names):
            Jg = Jr[groups[name]]
            for z in rng.choice([-1.0, 1.0], size=(PROBES, len(groups[name]))):
                u = Jg.T @ z
                x = lu.solve(u)
                tr_H[j] += float(u @ x) / PROBES
                y = Jr @ x
                H2[:, j] += [float(y[groups[i]] @ y[groups[i]]) / PROBES for i in names]
        n_g = np.array([len(groups[i]) for i in names], np.float64)
        score = 0.5 * (np.array([float(r[groups[i]] @ r[groups[i]]) for i in names]) - n_g + tr_H)
        info = 0.5 * (np.diag(n_g - 2.0 * tr_H) + 0.5 * (H2 + H2.T))
        step_ = np.clip(np.linalg.solve(info, score), -2.0, 2.0)
        pinned = np.array([var[i] <= floor[i] for i in names]) & (step_ < 0)  # the data want less than the floor
        for name, d in zip(names, step_):
            var[name] = max(var[name] * math.exp(d), floor[name])
        if np.all((np.abs(step_) < 0.01) | pinned):
            break
    _, _, r, lu = linearised()
    dof = max(len(r) - (nx - 1), 1)
    chi2 = float(r @ r / dof)
    e0 = np.zeros(nx)
    e0[iS] = 1.0
    var_s = float(lu.solve(e0)[iS]) * max(chi2, 1.0)
    A, A_sigma = np.eye(3), np.zeros((3, 3))
    if nM:
        A = A + dA.reshape(3, 3)
        E = np.zeros((nx, nM))
        E[iM + np.arange(nM), np.arange(nM)] = 1.0
        A_sigma = np.sqrt(np.maximum(np.diag(lu.solve(E)[iM:]), 0.0) * max(chi2, 1.0)).reshape(3, 3)
    return ReferenceFit(scale=float(s_), scale_sigma=math.sqrt(max(var_s, 0.0)), g=g, bg=np.asarray(bg, np.float64),
                        ba=ba.mean(0), time_offset=float(time_offset), sigma_ref=float(s_ * math.sqrt(var["centres"])),
                        chi2_dof=chi2, keyframes=n, intervals=m, span=(float(stamps[0]), float(stamps[-1])),
                        imu_noise_factor=math.sqrt(var["imu"]),
                        accel_bias_walk=noise.accel_bias_walk * math.sqrt(var["walk"]),
                        ba_spread=float(np.linalg.norm(ba - ba.mean(0), axis=1).max()), accel_matrix=A,
                        accel_matrix_sigma=A_sigma)


def _initial_scale(c: np.ndarray, stamps: np.ndarray, R_WB: np.ndarray, k: np.ndarray, dt: np.ndarray,
                   dbeta: np.ndarray, g: np.ndarray) -> float:
    """Metres per unit from the median size of the world accelerations: the IMU's (R_WB dbeta / dt + g) over the
    reconstruction's (second differences of its centres)."""
    a_imu = np.einsum("kij,kj->ki", R_WB[k], dbeta) / dt[:, None] + g
    vel = np.diff(c, axis=0) / np.diff(stamps)[:, None]
    a_rec = np.diff(vel, axis=0) / (0.5 * (stamps[2:] - stamps[:-2]))[:, None]
    ratio = np.median(np.linalg.norm(a_imu, axis=1)) / max(float(np.median(np.linalg.norm(a_rec, axis=1))), 1e-12)
    return float(ratio) if np.isfinite(ratio) and ratio > 0 else 1.0


def _initial_gravity(R_WB: np.ndarray, k: np.ndarray, dbeta: np.ndarray) -> np.ndarray:
    """Unit gravity direction in the reconstruction's world: minus the mean specific force (the accelerometer reads
    -g on average over any flight that ends about as fast as it began), each interval's velocity change rotated into
    the world."""
    f = np.einsum("kij,kj->ki", R_WB[k], dbeta).sum(0)
    return -f / np.linalg.norm(f)


__all__ = ["ReferenceFit", "fit_halves", "fit_reference"]
