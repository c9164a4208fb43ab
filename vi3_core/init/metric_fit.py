"""Metric scale with an error model: the backbone's positions regressed on the IMU kinematics, over one clip or a
window of clips (beyond the paper; its Eq. S stays available as the ablation ``scale_solver="tls"``).

Why not Eq. S alone: s = |V| / |V^M| divides by the norm of second differences of the backbone's positions. Their
noise inflates |V^M| (regression dilution of the denominator), so at 3 mm / 0.1 deg per frame the scale of a
EuRoC-like clip comes out about 30 % low, and nothing in it says how well the clip determines s. Here the errors sit
where they are: the backbone's positions are noisy, the IMU kinematics over a second are precise, so the backbone
positions are the observations and the IMU the regressor (errors-in-variables turned the right way round):

    a_ki = lam_k (R_fk^T d_ki - b_ki) + c_k + e_ki,        lam_k = 1 / s_k,

with a_ki = R_BC t_ki clip k's backbone camera positions in body axes (model units), b_ki the metric lever-arm term
(``lever_arm_terms``), c_k an offset that absorbs the error of the clip's first frame (a 3DFM re-anchors every clip at
its own first frame), R_fk = R_B0Bf and d_ki the body displacement from the clip's first frame f, in B0 (the body
frame at the first stamp), from Eqs. preintegrationVelocity / preintegrationTranslation:

    d_ki = v_k dtau + 1/2 g dtau^2 + (alpha_i - alpha_f - beta_f dtau)(bg, ba),      dtau = tau_i - tau_f.

Consecutive clips' first-frame velocities are tied through the IMU, v_k = v_(k-1) + g dtau + beta_fk - beta_f(k-1).
Unknowns: gravity g (|g| fixed: two tangent directions), the accelerometer bias ba (a constant in the IMU frame),
the gyro bias bg (first order about the given estimate, ``BiasJacobians``), and per clip lam_k, v_k (B0), c_k;
Gaussian priors on ba and bg, and optionally on (g, ba, bg, v_0) (``GaussianPrior``: what earlier clips said).
Gauss-Newton.

Error model (``ImuNoiseModel``): e_ki ~ N(0, sigma_v,k^2) per axis, the clip's visual noise, estimated from the clip's
own residuals by restricted maximum likelihood when not given; plus lam_k^2 times the IMU's position covariance
(accelerometer noise integrated twice, and a gyro scale error that tilts gravity by kappa times the angle turned).
Velocity ties carry the accelerometer and gyro noise over their interval and the same scale-error term. The scale's
relative 1-sigma is the Gauss-Newton covariance of lam_k, inflated by the Student-t 97.5 % quantile for the residual
degrees of freedom (over 1.96) and by the a-posteriori variance factor when the residuals exceed the model, combined
with ``ImuNoiseModel.rel_floor`` for what the model leaves out.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import lapack

from vi3_core import so3
from vi3_core.init.position_fit import lever_arm_terms
from vi3_core.preintegration import Preintegration

N_SHARED = 8  # g tangent (2), ba (3), bg (3)
N_CLIP = 7  # lam, v (3), c (3)
_Z975 = 1.959964


@dataclass(frozen=True)
class ImuNoiseModel:
    """What the fit assumes about the IMU, per axis.

    accel_noise_density: m/s^2/sqrt(Hz); gyro_noise_density: rad/s/sqrt(Hz). Defaults: EuRoC's ADIS16448 datasheet
    values (``imu0/sensor.yaml``) times 10 for the accelerometer and 5 for the gyro, as VIO systems inflate them for a
    real IMU (VINS-Mono uses 40x on EuRoC): with exact camera poses and its ground-truth state, the real EuRoC V1_02
    IMU misfits the positions of a 0.7 s clip by 3-19 mm RMS where the datasheet predicts under 1 mm.
    gyro_scale_error: relative error of the integrated rotation (scale factor, misalignment; 2 %, the upper end of
    a MEMS gyro's sensitivity error, as a catch-all for what else the real IMU does in fast turns): gravity is tilted
    by this fraction of the angle turned. accel_bias_sigma: m/s^2, prior 1-sigma of the accelerometer bias (EuRoC's
    reach 0.1-0.2). gyro_bias_sigma: rad/s, floor of the gyro-bias prior's 1-sigma (a larger spread of its estimate
    is used when given). rel_floor: relative scale error the model does not see (the real IMU with exact poses: ~1 %).
    accel_bias_walk (m/s^2/sqrt(s)), gyro_bias_walk (rad/s/sqrt(s)): the biases' random walks (EuRoC's datasheet
    values): what a prior on the biases loses per second (``GaussianPrior.widened``).
    """

    accel_noise_density: float = 2.0e-2
    gyro_noise_density: float = 8.5e-4
    gyro_scale_error: float = 0.02
    accel_bias_sigma: float = 0.2
    gyro_bias_sigma: float = 5.0e-4
    rel_floor: float = 0.01
    accel_bias_walk: float = 3.0e-3
    gyro_bias_walk: float = 1.9393e-05

    def __post_init__(self) -> None:
        bad = [k for k, v in vars(self).items() if not (math.isfinite(v) and v >= 0.0)]
        bad += [k for k in ("accel_bias_sigma", "gyro_bias_sigma") if not getattr(self, k) > 0.0]
        if bad:
            raise ValueError(f"ImuNoiseModel: {', '.join(sorted(set(bad)))} must be finite and >= 0 (bias sigmas > 0)")

    def position_cov(self, dtau: np.ndarray, angle: np.ndarray, gravity_norm: float) -> np.ndarray:
        """[n,n] covariance (m^2, per axis) of the IMU displacements at dtau [n] s after the first stamp, where the body
        has turned ``angle`` [n] rad: the accelerometer's white noise integrated twice, plus the gyro scale error's
        tilt of gravity (G kappa angle_i dtau_i^2 / 6: a rotation error growing with the angle, integrated twice)."""
        ti, tj = dtau[:, None], dtau[None, :]
        m = np.minimum(ti, tj)
        cov = self.accel_noise_density**2 * (ti * tj * m - 0.5 * (ti + tj) * m**2 + m**3 / 3.0)
        f = gravity_norm * self.gyro_scale_error * angle * dtau**2 / 6.0
        return cov + np.outer(f, f)

    def velocity_sigma(self, dt: float, angle: float, gravity_norm: float) -> float:
        """1-sigma (m/s, per axis) of an IMU velocity change over dt s while turning ``angle`` rad."""
        return math.sqrt(self.accel_noise_density**2 * dt + (gravity_norm * self.gyro_noise_density)**2 * dt**3 / 3.0
                         + (0.5 * gravity_norm * self.gyro_scale_error * angle * dt)**2)


@dataclass(frozen=True)
class FitClip:
    """One clip for the fit: stamps [n] s; T_wc [n,4,4] its backbone camera poses in its first camera frame (model
    units); sigma_v: its visual noise (model units, per axis), or None to estimate it (single-clip fits only)."""

    stamps: np.ndarray
    T_wc: np.ndarray
    sigma_v: float | None = None


@dataclass
class FitState:
    """g [3] m/s^2 and v [K,3] m/s (each clip's first frame) in B0; ba [3] m/s^2 and bg [3] rad/s in the IMU frame;
    lam [K] = 1 / scale; c [K,3] model units."""

    g: np.ndarray
    ba: np.ndarray
    bg: np.ndarray
    lam: np.ndarray
    v: np.ndarray
    c: np.ndarray

    def copy(self) -> FitState:
        return FitState(*(np.array(x, dtype=np.float64) for x in (self.g, self.ba, self.bg, self.lam, self.v, self.c)))


@dataclass(frozen=True)
class GaussianPrior:
    """A Gaussian on z = (g [3], ba [3], bg [3], v_0 [3]) in B0 (v_0: clip 0's first-frame velocity), linearised at
    ``center`` [12]: residual ``sqrt_info @ (z - center) + offset`` [m]. g's radial direction carries no information
    (its norm is fixed). A prior from marginalisation keeps the point it was linearised at as its center (its mean may
    lie far along directions it barely constrains)."""

    center: np.ndarray
    sqrt_info: np.ndarray
    offset: np.ndarray

    def residual(self, z: np.ndarray) -> np.ndarray:
        return self.sqrt_info @ (z - self.center) + self.offset

    def moved(self, R: np.ndarray, phi: np.ndarray) -> GaussianPrior:
        """The same prior for the body frame B0' = B(t') with R = R_B0B0' preintegrated with the center's gyro bias and
        phi [3,3] its bias Jacobian (R(bg + d) = Exp(phi d) R): g' = R^T g and v' = R^T v, linearised at the center (a
        later bias estimate also turns them, as it turns the IMU between t0 and t')."""
        g, v = self.center[0:3], self.center[9:12]
        T = np.eye(12)  # dz' / dz at the center
        T[0:3, 0:3] = T[9:12, 9:12] = R.T
        T[0:3, 6:9] = R.T @ so3.hat(g) @ phi
        T[9:12, 6:9] = R.T @ so3.hat(v) @ phi
        center = self.center.copy()
        center[0:3], center[9:12] = R.T @ g, R.T @ v
        return GaussianPrior(center, self.sqrt_info @ np.linalg.inv(T), self.offset)

    def widened(self, ba_var: float, bg_var: float) -> GaussianPrior:
        """The prior with ``ba_var`` ((m/s^2)^2) and ``bg_var`` ((rad/s)^2) added to the biases' variance per axis
        (their random walk over the time the prior is carried); its mean stays where it was."""
        cov = np.linalg.pinv(self.sqrt_info.T @ self.sqrt_info, hermitian=True)
        cov[3:6, 3:6] += ba_var * np.eye(3)
        cov[6:9, 6:9] += bg_var * np.eye(3)
        sqrt_info = _sqrt_info(np.linalg.pinv(cov, hermitian=True))
        # mean - center = -S^+ offset; the widened residual there keeps the same mean: S' (center - mean).
        return GaussianPrior(self.center, sqrt_info, sqrt_info @ np.linalg.lstsq(self.sqrt_info, self.offset,
                                                                                rcond=None)[0])


def _sqrt_info(info: np.ndarray) -> np.ndarray:
    """S [m,m] with S^T S = info [m,m] (symmetric PSD), from the eigen-decomposition after scaling each unknown to unit
    diagonal (so that the units of the unknowns do not matter); round-off's negative eigenvalues count as zero.

    Every direction is kept, however weak: a cut-off (directions below 1e-12 of the largest dropped) made the prior
    jump wherever an eigenvalue crossed it, and on the real EuRoC IMU a 1e-13 relative change of the accelerometer
    samples then moved the window's scale by 4 % and cascaded into confident wrong scales."""
    d = np.sqrt(np.maximum(np.diag(info), 1e-300))
    w, V = np.linalg.eigh(info / np.outer(d, d))
    return (V * np.sqrt(np.maximum(w, 0.0))).T * d


@dataclass
class FitResult:
    """The fitted state, per-clip results and the error model.

    scale [K] = 1 / lam (NaN where lam <= 0); scale_rel_sigma [K]: relative 1-sigma of each scale (inf where the data
    do not determine it); sigma_v [K]: visual noise per axis, model units; chi2 [K], dof [K]: each clip's whitened
    visual residual and its degrees of freedom; variance_factor: chi2 / dof over all rows (inflates cov when > 1);
    cov: covariance of the parameters (g tangent (2), ba, bg, then lam, v, c per clip); tangent [3,2]: the basis of
    g's tangent plane that cov refers to; converged: Gauss-Newton met its tolerance; link_chi2, link_dof [K-1]: the
    velocity ties' whitened residual and degrees of freedom (tie k-1 joins clips k-1 and k).
    """

    state: FitState
    scale: np.ndarray
    scale_rel_sigma: np.ndarray
    sigma_v: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    variance_factor: float
    cov: np.ndarray
    tangent: np.ndarray
    converged: bool
    link_chi2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    link_dof: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def marginal(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(mean z [12], covariance [12,12]) of (g, ba, bg, v_k) in B0 (g's through its tangent plane)."""
        s = self.state
        J = np.zeros((12, self.cov.shape[0]))
        J[0:3, 0:2] = np.linalg.norm(s.g) * self.tangent
        J[3:9, 2:8] = np.eye(6)
        o = N_SHARED + N_CLIP * k
        J[9:12, o + 1:o + 4] = np.eye(3)
        return np.concatenate([s.g, s.ba, s.bg, s.v[k]]), J @ self.cov @ J.T

    def state_sigma(self, k: int) -> tuple[float, float]:
        """(rad, m/s): the largest 1-sigma of gravity's direction and of clip k's first-frame velocity (any axis)."""
        _, cov = self.marginal(k)
        top = [math.sqrt(max(float(np.linalg.eigvalsh(cov[a:a + 3, a:a + 3])[-1]), 0.0)) for a in (0, 9)]
        return top[0] / float(np.linalg.norm(self.state.g)), top[1]


def fit_stamps(clips: list[FitClip]) -> np.ndarray:
    """The stamps [m] s the IMU is preintegrated at for ``clips``: every clip's, sorted, each once."""
    return np.unique(np.concatenate([c.stamps for c in clips]))


class MetricFit:
    """The equations of the module docstring for ``clips`` (time-ordered).

    pre: ``preintegrate(imu, fit_stamps(clips), bg, jacobians=True)``, B0 at its first stamp; its bg is the prior's
    mean and the linearisation point of the gyro bias, and bg_sigma (rad/s, floored at ``noise.gyro_bias_sigma``)
    that estimate's 1-sigma; T_BC [4,4]."""

    def __init__(self, clips: list[FitClip], pre: Preintegration, T_BC: np.ndarray, *, noise: ImuNoiseModel,
                 gravity_norm: float, bg_sigma: float = 0.0) -> None:
        if pre.J is None or not np.array_equal(pre.stamps, fit_stamps(clips)):
            raise ValueError("MetricFit: pre must be preintegrate(imu, fit_stamps(clips), bg, jacobians=True)")
        self.clips, self.noise, self.G, self.K = clips, noise, gravity_norm, len(clips)
        self.bg0 = pre.bg
        self.bg_sigma = max(float(bg_sigma), noise.gyro_bias_sigma)
        T_BC = np.asarray(T_BC, dtype=np.float64)
        stamps = pre.stamps
        self.pre = pre
        J = pre.J
        self.n_params = N_SHARED + N_CLIP * self.K
        self.blocks = []
        row = 0
        for clip in clips:
            ii = np.searchsorted(stamps, clip.stamps)
            f = int(ii[0])
            dtau = pre.tau[ii] - pre.tau[f]
            R_f, R_rel = pre.R[f], pre.R[f].T @ pre.R[ii]
            J_ba = J.alpha_ba[ii] - J.alpha_ba[f] - J.beta_ba[f] * dtau[:, None, None]
            J_bg = J.alpha_bg[ii] - J.alpha_bg[f] - J.beta_bg[f] * dtau[:, None, None]
            D, U = np.linalg.eigh(noise.position_cov(dtau, so3.angle(R_rel), gravity_norm))
            self.blocks.append(_Block(
                first=f, row=row, dtau=dtau, half_dtau2=0.5 * dtau**2, R_f=R_f,
                a=np.asarray(clip.T_wc, np.float64)[:, :3, 3] @ T_BC[:3, :3].T, lever=lever_arm_terms(R_rel, T_BC),
                alpha=pre.alpha[ii] - pre.alpha[f] - pre.beta[f] * dtau[:, None], J_ba=J_ba,
                imu_var=np.maximum(D, 0.0), imu_modes=U.T, dtau_RfT=dtau[:, None, None] * R_f.T[None],
                RfT_J_ba=R_f.T @ J_ba, RfT_J_bg=R_f.T @ J_bg, RfT_hat_phi=(R_f.T @ _HAT_E @ J.phi_bg[f]).reshape(3, 9)))
            row += 3 * len(dtau)
        self._bias_rows = np.zeros((6, self.n_params))
        self._bias_rows[0:3, 2:5] = np.eye(3) / noise.accel_bias_sigma
        self._bias_rows[3:6, 5:8] = np.eye(3) / self.bg_sigma
        self.link_scale = 1.0  # the ties' sigma relative to the noise model (variance component, see ``solve``)
        f = np.array([b.first for b in self.blocks])
        f0, f1 = f[:-1], f[1:]
        dt = pre.tau[f1] - pre.tau[f0]
        angle = so3.angle(np.swapaxes(pre.R[f0], 1, 2) @ pre.R[f1]) if self.K > 1 else np.zeros(0)
        self.links = _Links(dt=dt, dbeta=pre.beta[f1] - pre.beta[f0], J_ba=J.beta_ba[f1] - J.beta_ba[f0],
                            J_bg=J.beta_bg[f1] - J.beta_bg[f0],
                            sigma=np.array([noise.velocity_sigma(float(t), float(a), gravity_norm)
                                            for t, a in zip(dt, angle)]), row=row)

    # ---- the model ----------------------------------------------------------------------------------------------

    def _model(self, s: FitState, priors: tuple[GaussianPrior, ...]):
        """Residual y (model minus observation) and Jacobian A [m, p] at ``s`` with every row whitened but the visual
        ones: those are projected on the modes of their clip's IMU position covariance (``_Block.imu_modes``, rows
        (mode, axis)) and left unscaled, for ``_weights`` (their noise varies with sigma_v and lam) or the noise
        estimate; the row ranges by factor ("vis k", "link k" between clips k-1 and k, "bias", "prior i") and g's
        tangent basis [3,2]."""
        G, p, K = self.G, self.n_params, self.K
        B = _tangent_basis(s.g / G)
        GB = G * B
        dbg = s.bg - self.bg0
        lk = self.links
        m = lk.row + 3 * (K - 1) + 6 + sum(prior.sqrt_info.shape[0] for prior in priors)
        y, A = np.empty(m), np.zeros((m, p))
        rows = {}
        for k, blk in enumerate(self.blocks):
            lam, n = s.lam[k], len(blk.dtau)
            d = s.v[k] * blk.dtau[:, None] + blk.half_dtau2[:, None] * s.g + blk.alpha + blk.J_ba @ s.ba  # B0, m
            # d body / d bg in the clip's first frame: the clip's frame turns with bg too (R_f^T hat(d_i) phi_f)
            RfT_J_bg = blk.RfT_J_bg + (d @ blk.RfT_hat_phi).reshape(n, 3, 3)
            body = d @ blk.R_f + RfT_J_bg @ dbg - blk.lever
            J = np.empty((n, 3, N_SHARED + N_CLIP))  # its shared unknowns, then its own
            J[:, :, 0:2] = (lam * blk.half_dtau2)[:, None, None] * (blk.R_f.T @ GB)
            J[:, :, 2:5] = lam * blk.RfT_J_ba
            J[:, :, 5:8] = lam * RfT_J_bg
            J[:, :, 8] = body
            J[:, :, 9:12] = lam * blk.dtau_RfT
            J[:, :, 12:15] = _EYE3
            r0, r1, o = blk.row, blk.row + 3 * n, N_SHARED + N_CLIP * k
            y[r0:r1] = (blk.imu_modes @ (lam * body + s.c[k] - blk.a)).reshape(-1)
            J = (blk.imu_modes @ J.reshape(n, -1)).reshape(3 * n, -1)
            A[r0:r1, 0:N_SHARED], A[r0:r1, o:o + N_CLIP] = J[:, :N_SHARED], J[:, N_SHARED:]
            rows[f"vis {k}"] = range(r0, r1)
        r0 = lk.row
        if K > 1:  # the velocity ties, one [3]-row block each
            w = 1.0 / (lk.sigma * self.link_scale)
            r = s.v[1:] - s.v[:-1] - lk.dt[:, None] * s.g - lk.dbeta - lk.J_ba @ s.ba - lk.J_bg @ dbg
            y[r0:r0 + 3 * (K - 1)] = (w[:, None] * r).reshape(-1)
            A_l = A[r0:r0 + 3 * (K - 1)].reshape(K - 1, 3, p)
            A_l[:, :, 0:2] = -(w * lk.dt)[:, None, None] * GB
            A_l[:, :, 2:5], A_l[:, :, 5:8] = -w[:, None, None] * lk.J_ba, -w[:, None, None] * lk.J_bg
            for k in range(1, K):
                o1, o0 = N_SHARED + N_CLIP * k, N_SHARED + N_CLIP * (k - 1)
                A_l[k - 1, :, o1 + 1:o1 + 4], A_l[k - 1, :, o0 + 1:o0 + 4] = w[k - 1] * _EYE3, -w[k - 1] * _EYE3
                rows[f"link {k}"] = range(r0 + 3 * (k - 1), r0 + 3 * k)
            r0 += 3 * (K - 1)
        # ba ~ N(0, accel_bias_sigma^2), bg ~ N(bg0, bg_sigma^2)
        y[r0:r0 + 3], y[r0 + 3:r0 + 6] = s.ba / self.noise.accel_bias_sigma, dbg / self.bg_sigma
        A[r0:r0 + 6] = self._bias_rows
        rows["bias"] = range(r0, r0 + 6)
        r0 += 6
        if priors:
            z = np.concatenate([s.g, s.ba, s.bg, s.v[0]])
            Jz = np.zeros((12, p))
            Jz[0:3, 0:2] = GB
            Jz[3:9, 2:8] = np.eye(6)
            Jz[9:12, N_SHARED + 1:N_SHARED + 4] = np.eye(3)
            for i, prior in enumerate(priors):
                r1 = r0 + prior.sqrt_info.shape[0]
                y[r0:r1], A[r0:r1] = prior.residual(z), prior.sqrt_info @ Jz
                rows[f"prior {i}"] = range(r0, r1)
                r0 = r1
        return y, A, rows, B

    def _weights(self, s: FitState, sigma_v: np.ndarray, m: int) -> np.ndarray:
        """[m] weights that whiten ``_model``'s rows: a visual row on mode j of clip k has variance sigma_v,k^2 +
        lam_k^2 d_j (d_j the mode's IMU position variance), the other rows are whitened already."""
        w = np.ones(m)
        for k, blk in enumerate(self.blocks):
            v = sigma_v[k] ** 2 + s.lam[k] ** 2 * blk.imu_var
            w[blk.row:blk.row + 3 * len(v)] = np.repeat(1.0 / np.sqrt(v), 3)
        return w

    def _linearise(self, s: FitState, sigma_v: np.ndarray, priors: tuple[GaussianPrior, ...]):
        """``_model`` whitened: y [m], A [m, p], the row ranges and g's tangent basis [3,2]."""
        y, A, rows, B = self._model(s, priors)
        w = self._weights(s, sigma_v, len(y))
        return w * y, w[:, None] * A, rows, B

    def _step(self, s: FitState, dx: np.ndarray, B: np.ndarray) -> FitState:
        g = s.g - self.G * B @ dx[0:2]
        per = dx[N_SHARED:].reshape(self.K, N_CLIP)
        return FitState(self.G * g / math.hypot(*g), s.ba - dx[2:5], s.bg - dx[5:8], s.lam - per[:, 0],
                        s.v - per[:, 1:4], s.c - per[:, 4:7])

    # ---- solution -----------------------------------------------------------------------------------------------

    def initial_state(self, g: np.ndarray, lam: np.ndarray | None = None) -> FitState:
        """A starting point for gravity g [3] (B0) with the biases at their priors: per clip, a_ki = lam_k body_ki(v_k
        = 0) + lam_k R_f^T v_k dtau + c_k is linear in (lam_k, lam_k v_k, c_k), solved by least squares (lam_k held at
        ``lam`` [K] where it is given and finite)."""
        K = self.K
        s = FitState(self.G * np.asarray(g, np.float64) / np.linalg.norm(g), np.zeros(3), self.bg0.copy(),
                     np.ones(K), np.zeros((K, 3)), np.zeros((K, 3)))
        for k, blk in enumerate(self.blocks):
            n = len(blk.dtau)
            X = np.empty((n, 3, 7))
            X[:, :, 0] = (blk.half_dtau2[:, None] * s.g + blk.alpha) @ blk.R_f - blk.lever
            X[:, :, 1:4] = blk.dtau_RfT
            X[:, :, 4:7] = _EYE3
            X, y = X.reshape(3 * n, 7), blk.a.reshape(-1)
            if lam is not None and np.isfinite(lam[k]):
                s.lam[k] = float(lam[k])
                coef = _lstsq(X[:, 1:], y - s.lam[k] * X[:, 0])
            else:
                coef = _lstsq(X, y)
                s.lam[k], coef = coef[0], coef[1:]
            s.v[k] = blk.R_f @ coef[0:3] / s.lam[k] if s.lam[k] != 0.0 else np.zeros(3)
            s.c[k] = coef[3:6]
        return s

    def solve(self, state: FitState, *, priors: tuple[GaussianPrior, ...] = (), iterations: int = 8,
              tol: float = 1e-4) -> FitResult:
        """Gauss-Newton from ``state`` until every scale moves by less than ``tol`` of itself (and gravity by less
        than tol / 10 rad), far below any scale's sigma. A single clip without ``sigma_v`` gets it by restricted
        maximum likelihood (``_visual_noise``) at the start."""
        sigma_v = np.array([np.nan if c.sigma_v is None else float(c.sigma_v) for c in self.clips])
        estimate = not np.isfinite(sigma_v).all()
        if estimate and self.K != 1:
            raise ValueError("MetricFit: the visual noise can be estimated only in a single-clip fit")
        s, converged = self._gauss_newton(state.copy(), sigma_v, priors, iterations, tol, estimate)
        result = self._result(s, sigma_v, priors, converged)
        # The velocity ties are the IMU's word over a second; where the real IMU is worse than its model there
        # (scale-factor errors in fast turns, a changing bias) their residuals show it: their variance component,
        # estimated from them, widens them (at most 10x) before the scales are trusted.
        for _ in range(2):
            vc = float(result.link_chi2.sum() / max(result.link_dof.sum(), 1e-9)) if self.K > 1 else 1.0
            if vc <= 1.2 or self.link_scale >= 10.0:
                break
            self.link_scale = min(self.link_scale * math.sqrt(vc), 10.0)
            s, converged = self._gauss_newton(s, sigma_v, priors, iterations, tol, False)
            result = self._result(s, sigma_v, priors, converged)
        return result

    def _gauss_newton(self, s: FitState, sigma_v: np.ndarray, priors: tuple[GaussianPrior, ...], iterations: int,
                      tol: float, estimate: bool) -> tuple[FitState, bool]:
        for it in range(iterations):
            y, A, _, B = self._model(s, priors)
            if estimate and it == 0:  # at the linear starting point: re-estimating it later changes nothing
                sigma_v[0] = self._visual_noise(s, y, A)
            w = self._weights(s, sigma_v, len(y))
            dx = _lstsq(w[:, None] * A, w * y)
            s = self._step(s, dx, B)
            if it >= 1 and np.all(np.abs(dx[N_SHARED::N_CLIP]) <= tol * np.abs(s.lam)) \
                    and np.abs(dx[:2]).max() <= 0.1 * tol:
                return s, True
        return s, False

    def _visual_noise(self, s: FitState, y: np.ndarray, A: np.ndarray, *, iterations: int = 8) -> float:
        """The single clip's visual noise sigma_v (model units, per axis) that maximises the restricted likelihood of
        its residuals at ``s`` (y, A: ``_model`` there): covariance sigma_v^2 I + lam^2 Sigma_imu per axis, the linear
        correction of every unknown profiled out (Fisher scoring on log sigma_v^2, in the eigenbasis of Sigma_imu)."""
        blk, lam = self.blocks[0], float(s.lam[0])
        n, p = len(blk.dtau), A.shape[1]
        D = lam**2 * blk.imu_var
        r_m = y[:3 * n].reshape(n, 3)  # [modes, axes]
        J_m = A[:3 * n].reshape(n, 3, p)
        J_mT = np.swapaxes(J_m, 1, 2)
        M = (J_mT @ J_m).reshape(n, p * p)  # per mode J^T J, flattened
        Jr = (J_mT @ r_m[:, :, None])[:, :, 0]
        P_A, P_y = A[3 * n:], y[3 * n:]
        H0, g0 = P_A.T @ P_A, P_A.T @ P_y
        floor = 1e-12 * max(float((blk.a**2).sum()) / n, 1e-12)  # model units: relative to the clip's extent
        theta = max(float((r_m**2).sum()) / r_m.size, floor)
        for _ in range(iterations):
            w = 1.0 / (theta + D)
            w2 = w * w
            H, M2, M3 = (np.array((w, w2, w2 * w)) @ M).reshape(3, p, p)
            H += H0
            Hi = _inv(H)
            beta = Hi @ (g0 + w @ Jr)
            e = r_m - J_m @ beta  # [modes, axes]
            HM2 = Hi @ M2
            # traces of products of symmetric matrices as dot products of their elements
            tr_P = 3.0 * float(w.sum()) - float(np.vdot(Hi, M2))
            tr_PP = 3.0 * float(w2.sum()) - 2.0 * float(np.vdot(Hi, M3)) + float(np.vdot(HM2, HM2.T))
            score = 0.5 * (float(((w[:, None] * e) ** 2).sum()) - tr_P)  # d loglik / d theta
            step = min(max(score / (0.5 * tr_PP * theta), -2.0), 2.0) if tr_PP > 0 else 0.0
            theta = max(theta * math.exp(step), floor)
            if abs(step) < 1e-2:  # sigma_v to 0.5 %: its own uncertainty (~12 dof) is 20 %
                break
        return math.sqrt(theta)

    def _result(self, s: FitState, sigma_v: np.ndarray, priors: tuple[GaussianPrior, ...],
                converged: bool) -> FitResult:
        y, A, rows, B = self._linearise(s, sigma_v, priors)
        U, sv, Vt = np.linalg.svd(A, full_matrices=False)
        keep = sv > 1e-10 * sv[0]
        cov = (Vt[keep].T / sv[keep] ** 2) @ Vt[keep]
        undetermined = (np.abs(Vt[~keep]) > 1e-6).any(0) if (~keep).any() else np.zeros(self.n_params, bool)
        leverage = (U[:, keep] ** 2).sum(1)
        vis = [rows[f"vis {k}"] for k in range(self.K)]
        links = [rows[f"link {k}"] for k in range(1, self.K)]
        chi2, link_chi2 = ([float((y[r.start:r.stop] ** 2).sum()) for r in group] for group in (vis, links))
        dof, link_dof = ([max(float(len(r) - leverage[r.start:r.stop].sum()), 1e-3) for r in group]
                         for group in (vis, links))
        dof_total = max(float(len(y) - leverage.sum()), 1.0)
        vf = max(1.0, float(y @ y) / dof_total)
        lam = s.lam
        stat = np.sqrt(np.diag(cov)[N_SHARED::N_CLIP] * vf) * (_t975(dof_total) / _Z975)
        rel = np.full(self.K, np.inf)  # undetermined, or a scale that is not positive: no relative sigma
        ok = (lam > 0) & ~undetermined[N_SHARED::N_CLIP]
        rel[ok] = np.sqrt((stat[ok] / lam[ok]) ** 2 + self.noise.rel_floor**2)
        scale = np.full(self.K, np.nan)
        scale[lam > 0] = 1.0 / lam[lam > 0]
        return FitResult(state=s, scale=scale, scale_rel_sigma=rel, sigma_v=sigma_v.copy(), chi2=np.array(chi2),
                         dof=np.array(dof), variance_factor=vf, cov=cov * vf, tangent=B, converged=converged,
                         link_chi2=np.array(link_chi2), link_dof=np.array(link_dof))

    def marginalise(self, result: FitResult, drop: int, priors: tuple[GaussianPrior, ...] = ()) -> GaussianPrior:
        """What clips 0..drop-1 say about (g, ba, bg, v_drop) once their own unknowns are eliminated: their visual
        rows, the velocity ties up to clip ``drop`` and ``priors`` (the bias priors are left out: every fit adds its
        own), linearised at ``result`` and reduced by the Schur complement, as a Gaussian prior in clip ``drop``'s
        first body frame for the window that starts there (sliding-window marginalisation)."""
        if not 0 < drop < self.K:
            raise ValueError(f"MetricFit.marginalise: drop must be in 1..{self.K - 1}, got {drop}")
        y, A, rows, B = self._linearise(result.state, result.sigma_v, priors)
        names = [f"vis {k}" for k in range(drop)] + [f"link {k}" for k in range(1, drop + 1)]
        names += [f"prior {i}" for i in range(len(priors))]
        sel = np.concatenate([np.array(rows[name], dtype=int) for name in names])
        H, b = A[sel].T @ A[sel], A[sel].T @ y[sel]  # cost 1/2 |y + A dx|^2 of the parameter change dx
        o = N_SHARED + N_CLIP * drop
        kept = np.r_[0:N_SHARED, o + 1:o + 4]
        gone = np.arange(N_SHARED, N_SHARED + N_CLIP * drop)
        # An undetermined unknown of a dropped clip (a scale its data do not fix) carries nothing over: the pseudo-
        # inverse of the column-scaled block drops it instead of dividing by round-off.
        H_dd = H[np.ix_(gone, gone)]
        d = np.sqrt(np.maximum(np.diag(H_dd), 1e-300))
        H_dd_inv = np.linalg.pinv(H_dd / np.outer(d, d), rcond=1e-10, hermitian=True) / np.outer(d, d)
        X = H_dd_inv @ H[np.ix_(gone, kept)]
        H_m = H[np.ix_(kept, kept)] - H[np.ix_(kept, gone)] @ X
        b_m = b[kept] - X.T @ b[gone]
        sqrt_H = _sqrt_info(0.5 * (H_m + H_m.T))
        P = np.zeros((11, 12))  # parameter change from z - z*: g through its tangent plane, the rest as is
        P[0:2, 0:3] = B.T / self.G
        P[2:11, 3:12] = np.eye(9)
        s = result.state
        f = self.blocks[drop].first
        dt = float(self.pre.tau[f])
        # Residual sqrt_H dx + sqrt_H^-T b_m, deflated by the fit's a-posteriori variance factor (its covariance is
        # inflated); the biases walk while the prior is carried to clip ``drop``'s first frame.
        offset = np.linalg.lstsq(sqrt_H.T, b_m, rcond=None)[0]
        vf = math.sqrt(result.variance_factor)
        prior = GaussianPrior(np.concatenate([s.g, s.ba, s.bg, s.v[drop]]), sqrt_H @ P / vf, offset / vf)
        prior = prior.widened(self.noise.accel_bias_walk**2 * dt, self.noise.gyro_bias_walk**2 * dt)
        phi = self.pre.J.phi_bg[f]
        return prior.moved(so3.exp(phi @ (s.bg - self.bg0)) @ self.pre.R[f], phi)


@dataclass(frozen=True)
class _Block:
    """Precomputed terms of one clip (see ``MetricFit._model``): first stamp index; row: its first row in the model;
    dtau, half_dtau2 = dtau^2 / 2 [n]; R_f [3,3]; a [n,3]; lever [n,3]; alpha [n,3] (bias-free displacement part, B0);
    J_ba [n,3,3]; its IMU position covariance (``ImuNoiseModel.position_cov``) as variances imu_var [n] (m^2) along
    the rows of imu_modes [n,n] (orthonormal); the constant Jacobian factors dtau_RfT, RfT_J_ba, RfT_J_bg [n,3,3]
    (R_f^T times the displacement's bias Jacobians); and RfT_hat_phi [3,9], R_f^T hat(e_a) phi_f for the axes a
    (phi_f: the first frame's rotation Jacobian), so that d @ RfT_hat_phi is R_f^T hat(d_i) phi_f, flattened."""

    first: int
    row: int
    dtau: np.ndarray
    half_dtau2: np.ndarray
    R_f: np.ndarray
    a: np.ndarray
    lever: np.ndarray
    alpha: np.ndarray
    J_ba: np.ndarray
    imu_var: np.ndarray
    imu_modes: np.ndarray
    dtau_RfT: np.ndarray
    RfT_J_ba: np.ndarray
    RfT_J_bg: np.ndarray
    RfT_hat_phi: np.ndarray


@dataclass(frozen=True)
class _Links:
    """The K-1 velocity ties between consecutive clips (tie k-1 joins clips k-1 and k): dt [K-1] s, dbeta [K-1,3] m/s,
    J_ba, J_bg [K-1,3,3], sigma [K-1] m/s; row: the first of their 3 (K-1) rows in the model."""

    dt: np.ndarray
    dbeta: np.ndarray
    J_ba: np.ndarray
    J_bg: np.ndarray
    sigma: np.ndarray
    row: int


_EYE3 = np.eye(3)
_HAT_E = so3.hat(np.eye(3))  # [3,3,3]: hat of each axis


def _lstsq(A: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The minimum-norm least-squares solution x [n] of A [m,n] x = y [m] (m >= n), the rank taken where the condition
    number reaches 1 / (eps max(m, n)), as ``np.linalg.lstsq(A, y, rcond=None)``; by LAPACK's complete orthogonal
    factorisation (gelsy), a quarter of the cost of numpy's SVD on the fit's small systems."""
    m, n = A.shape
    cond = np.finfo(np.float64).eps * max(m, n)
    x, info = lapack.dgelsy(A, y, np.zeros(n, np.int32), cond, _gelsy_lwork(m, n, cond))[1::3]
    if info != 0:
        raise np.linalg.LinAlgError(f"lstsq: LAPACK gelsy failed (info {info}) on a {m}x{n} system")
    return x[:n]


def _inv(H: np.ndarray) -> np.ndarray:
    """H^-1 [n,n] by LU (LAPACK getrf/getri, as ``np.linalg.inv`` at a third of its call cost), the pseudo-inverse
    where H is exactly singular."""
    lu, piv, info = lapack.dgetrf(H)
    if info == 0:
        Hi, info = lapack.dgetri(lu, piv)
        if info == 0:
            return Hi
    return np.linalg.pinv(H)


@functools.lru_cache(maxsize=64)
def _gelsy_lwork(m: int, n: int, cond: float) -> int:
    work, info = lapack.dgelsy_lwork(m, n, 1, cond)
    return int(work)


def _t975(dof: float) -> float:
    """Student-t 97.5 % quantile for ``dof`` degrees of freedom (Cornish-Fisher, within 1e-3 from 3 dof up)."""
    z = _Z975
    return z + (z**3 + z) / (4.0 * dof) + (5 * z**5 + 16 * z**3 + 3 * z) / (96.0 * dof**2)


def _tangent_basis(u: np.ndarray) -> np.ndarray:
    """Two unit vectors [3,2] orthogonal to the unit vector u and to each other."""
    ux, uy, uz = u.tolist()  # plain floats: numpy's per-call cost dwarfs the arithmetic here
    size = [abs(ux), abs(uy), abs(uz)]
    axis = size.index(min(size))  # the axis least aligned with u
    ex, ey, ez = (1.0 if a == axis else 0.0 for a in range(3))
    b1x, b1y, b1z = uy * ez - uz * ey, uz * ex - ux * ez, ux * ey - uy * ex
    norm = math.sqrt(b1x * b1x + b1y * b1y + b1z * b1z)
    b1x, b1y, b1z = b1x / norm, b1y / norm, b1z / norm
    return np.array([[b1x, uy * b1z - uz * b1y], [b1y, uz * b1x - ux * b1z], [b1z, ux * b1y - uy * b1x]])


__all__ = ["FitClip", "FitResult", "FitState", "GaussianPrior", "ImuNoiseModel", "MetricFit", "fit_stamps"]
