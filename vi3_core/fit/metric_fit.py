"""Metric scale with an error model: the backbone's positions regressed on the IMU kinematics, over one clip or a
window of clips (beyond the paper; its Eq. S stays available as the ablation ``scale_solver="tls"``).

Why not Eq. S alone: s = |V| / |V^M| divides by the norm of second differences of the backbone's positions. Their
noise inflates |V^M| (regression dilution of the denominator), so at 3 mm / 0.1 deg per frame the scale of a
EuRoC-like clip comes out at about half the true scale, and nothing in it says how well the clip determines s. Here
the errors sit where they are: the backbone's positions are noisy, the IMU kinematics over a second are precise, so
the backbone positions are the observations and the IMU the regressor (errors-in-variables turned the right way
round):

    a_ki = lam_k (R_fk^T d_ki - b_ki) + c_k + e_ki,        lam_k = 1 / s_k,

with a_ki = R_BC t_ki clip k's backbone camera positions in body axes (model units), b_ki the metric lever-arm term
(``lever_arm_terms``), c_k an offset that absorbs the error of the clip's first frame (a 3DFM re-anchors every clip at
its own first frame), R_fk = R_B0Bf and d_ki the body displacement from the clip's first frame f, in B0 (the body
frame at the first stamp), from Eqs. preintegrationVelocity / preintegrationTranslation:

    d_ki = v_k dtau + 1/2 g dtau^2 + (alpha_i - alpha_f - beta_f dtau)(bg, ba),      dtau = tau_i - tau_f.

Consecutive clips' first-frame velocities are tied through the IMU, v_k = v_(k-1) + g dtau + beta_fk - beta_f(k-1).
Unknowns: gravity g (|g| fixed: two tangent directions), the accelerometer bias ba (a constant in the IMU frame),
the gyro bias bg (first order about the given estimate, ``BiasJacobians``), and per clip lam_k, v_k (B0), c_k;
Gaussian priors on ba and bg, and optionally on (g, ba, bg, v_0) (``GaussianPrior``: what earlier clips said); the
unknowns and their columns: ``layout.StateLayout``.
Gauss-Newton.

Error model (``ImuNoiseModel``): e_ki ~ N(0, sigma_v,k^2) per axis, the clip's visual noise, estimated from the clip's
own residuals by restricted maximum likelihood when not given; plus lam_k^2 times the IMU's position covariance
(accelerometer noise integrated twice, and a gyro scale error that tilts gravity by kappa times the angle turned),
each optionally times a level the online window estimates (``MetricFit``'s estimate_levels): a real IMU is rarely at
its model's level, and where the IMU's part matters a wrong level biases the scale (below, and ``_whiten``).
Velocity ties carry the accelerometer and gyro noise over their interval and the same scale-error term. The scale's
relative 1-sigma is the Gauss-Newton covariance of lam_k, inflated by the Student-t 97.5 % quantile for the residual
degrees of freedom (over 1.96) and by the a-posteriori variance factor when the residuals exceed the model, combined
with ``ImuNoiseModel.rel_floor`` for what the model leaves out.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import solve_triangular

from vi3_core import so3
from vi3_core.fit.layout import PriorLayout, StateLayout
from vi3_core.fit.linalg import Z975, inv, lstsq, t975, tangent_basis
from vi3_core.fit.noise import ImuNoiseModel
from vi3_core.fit.position import lever_arm_terms
from vi3_core.fit.prior import GaussianPrior
from vi3_core.preintegration import Preintegration


@dataclass(frozen=True)
class FitClip:
    """One clip for the fit: stamps [n] s; T_wc [n,4,4] its backbone camera poses in its first camera frame (model
    units); sigma_v: its visual noise (model units, per axis), or None to estimate it (single-clip fits only);
    traj_depth_sigma: the 1-sigma of the log of its trajectory's scale against its depth's (``Geometry``'s; 0: the
    same scale), what the scale links (depth) and its visual rows (trajectory) may disagree by."""

    stamps: np.ndarray
    T_wc: np.ndarray
    sigma_v: float | None = None
    traj_depth_sigma: float = 0.0


@dataclass(frozen=True)
class ScaleLink:
    """What two consecutive clips' predictions of their shared frames say about their model scales: log_ratio =
    log(lam_k / lam_(k-1)) (the later clip's over the earlier's) and its 1-sigma (``vi3_core.online.link``)."""

    log_ratio: float
    sigma: float


@dataclass
class FitState:
    """g [3] m/s^2 and v [K,3] m/s (each clip's first frame) in B0; ba [3] m/s^2 and bg [3] rad/s in the IMU frame;
    lam [K] = 1 / scale; c [K,3] model units; td: s, the camera-IMU time offset left over (a frame at t shows the
    body at t + td)."""

    g: np.ndarray
    ba: np.ndarray
    bg: np.ndarray
    lam: np.ndarray
    v: np.ndarray
    c: np.ndarray
    dphi: np.ndarray
    td: float = 0.0

    def copy(self) -> FitState:
        return FitState(*(np.array(x, dtype=np.float64)
                          for x in (self.g, self.ba, self.bg, self.lam, self.v, self.c, self.dphi)), float(self.td))


@dataclass
class FitResult:
    """The fitted state, per-clip results and the error model.

    scale [K] = 1 / lam (NaN where lam <= 0); scale_rel_sigma [K]: relative 1-sigma of each scale (inf where the data
    do not determine it); sigma_v [K]: visual noise per axis, model units; chi2 [K], dof [K]: each clip's whitened
    visual residual and its degrees of freedom; variance_factor: chi2 / dof over all rows (inflates cov when > 1);
    cov: covariance of the parameters (``StateLayout(K)``'s columns); tangent [3,2]: the basis of
    g's tangent plane that cov refers to; converged: Gauss-Newton met its tolerance; next_step: the full Gauss-Newton
    step still to go from ``state`` (cov's columns, subtracted; of the objective the state was fitted to, where cov is
    at the model's IMU level; ``settled``); link_chi2, link_dof [K-1]: the
    velocity ties' whitened residual and degrees of freedom (tie k-1 joins clips k-1 and k); scale_chi2, scale_dof
    [K-1]: the same of the scale links (NaN where clips k-1 and k have none); level_score [2], level_info [2,2]:
    with ``estimate_levels``, the restricted likelihood's score and information in the logarithms of the IMU's and the
    visual noise's levels at the solution (what the window says about them, ``vi3_core.online.window``; else empty).
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
    next_step: np.ndarray = field(default_factory=lambda: np.zeros(0))
    link_chi2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    link_dof: np.ndarray = field(default_factory=lambda: np.zeros(0))
    scale_chi2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    scale_dof: np.ndarray = field(default_factory=lambda: np.zeros(0))
    level_score: np.ndarray = field(default_factory=lambda: np.zeros(0))
    level_info: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    @property
    def layout(self) -> StateLayout:
        return StateLayout(len(self.scale))

    def step_sigmas(self, k: int) -> float:
        """How far the fit still is from its solution in clip k's scale: the change that ``next_step`` makes to lam_k,
        in lam_k's linearised 1-sigma (before the variance factor, which the residual an unconverged fit still holds
        would inflate; inf where the step or the sigma is not known)."""
        if len(self.next_step) != self.layout.n:
            return math.inf
        col = self.layout.lam(k)
        var = float(self.cov[col, col]) / self.variance_factor
        return abs(float(self.next_step[col])) / math.sqrt(var) if var > 0 else math.inf

    def settled(self, k: int) -> bool:
        """Whether the scale a claim of clip k publishes has settled: the Gauss-Newton step still to go moves it by at
        most ``SETTLED_SIGMAS`` of its sigma (``step_sigmas``). The fit's own tolerance is relative to each lam, so a
        member whose scale the window cannot fix (a clip at rest at the start of a flight) swings from step to step
        and keeps the whole fit from meeting it, while the newest clip's scale moves by less than 1e-4 of itself.
        Gravity and the velocity, which a claim publishes with their own sigmas, are not held to it: on V1_02's
        take-off the step still to go moved gravity by up to 0.6 of its sigma where it moved the scale by 0.04."""
        return self.step_sigmas(k) <= SETTLED_SIGMAS

    def marginal(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(mean z, covariance) of the prior vector z (``PriorLayout``) at clip k: g, ba, bg, v_k in B0 (g's
        covariance through its tangent plane)."""
        s = self.state
        J = self.layout.prior_jacobian(k, np.linalg.norm(s.g) * self.tangent)
        return PriorLayout.vector(s.g, s.ba, s.bg, s.v[k], s.lam[k], s.td), J @ self.cov @ J.T

    @property
    def time_offset_sigma(self) -> float:
        """s: the 1-sigma of the time offset td."""
        return math.sqrt(max(float(self.cov[self.layout.td, self.layout.td]), 0.0))

    def state_sigma(self, k: int) -> tuple[float, float]:
        """(rad, m/s): the largest 1-sigma of gravity's direction and of clip k's first-frame velocity (any axis)."""
        _, cov = self.marginal(k)
        top = [math.sqrt(max(float(np.linalg.eigvalsh(cov[a, a])[-1]), 0.0)) for a in (PriorLayout.g, PriorLayout.v)]
        return top[0] / float(np.linalg.norm(self.state.g)), top[1]



def fit_stamps(clips: list[FitClip]) -> np.ndarray:
    """The stamps [m] s the IMU is preintegrated at for ``clips``: every clip's, sorted, each once."""
    return np.unique(np.concatenate([c.stamps for c in clips]))


class MetricFit:
    """The equations of the module docstring for ``clips`` (time-ordered).

    pre: ``preintegrate(imu, fit_stamps(clips), bg, jacobians=True)``, B0 at its first stamp; its bg is the prior's
    mean and the linearisation point of the gyro bias, and bg_sigma (rad/s, floored at ``noise.gyro_bias_sigma``)
    that estimate's 1-sigma; T_BC [4,4]; scale_links [K-1]: the ``ScaleLink`` between clips k-1 and k at k-1, or
    None where they have none (empty: none at all); estimate_walk: estimate a random walk of the backbone's positions
    (``solve``); estimate_levels: the noise levels ``imu_level`` and ``visual_level`` (factors on the IMU's position
    covariance and on every clip's sigma_v^2, set by the caller: an online estimate of the sensors') are the data's,
    so the objective is the errors-in-variables one (``_whiten``) and ``solve`` reports what the fit says about them
    (``FitResult.level_score``); the covariance takes the IMU's level at no less than the model's (``solve``)."""

    def __init__(self, clips: list[FitClip], pre: Preintegration, T_BC: np.ndarray, *, noise: ImuNoiseModel,
                 gravity_norm: float, bg_sigma: float = 0.0, scale_links: Sequence[ScaleLink | None] = (),
                 estimate_walk: bool = False, estimate_levels: bool = False) -> None:
        if pre.J is None or not np.array_equal(pre.stamps, fit_stamps(clips)):
            raise ValueError("MetricFit: pre must be preintegrate(imu, fit_stamps(clips), bg, jacobians=True)")
        if scale_links and len(scale_links) != len(clips) - 1:
            raise ValueError(f"MetricFit: {len(scale_links)} scale links for {len(clips)} clips (need one per pair)")
        self.clips, self.noise, self.G, self.K = clips, noise, gravity_norm, len(clips)
        # the scale links as (k, log ratio, sigma): residuals log lam_k - log lam_(k-1) - log ratio, whitened together
        # (``_links_whitener``: their own sigmas and the clips' trajectories against their depth)
        self.scale_links = [(k, link.log_ratio, link.sigma) for k, link in enumerate(scale_links, start=1)
                            if link is not None]
        self._links_whitener = _links_whitener(self.scale_links, [c.traj_depth_sigma for c in clips])
        self.bg0 = pre.bg
        self.bg_sigma = max(float(bg_sigma), noise.gyro_bias_sigma)
        T_BC = np.asarray(T_BC, dtype=np.float64)
        stamps = pre.stamps
        self.pre = pre
        J = pre.J
        self.layout = L = StateLayout(self.K)
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
            walk = U.T @ np.minimum(dtau[:, None], dtau[None, :]) @ U  # a random walk's kernel on the modes, s
            self.blocks.append(_Block(
                first=f, row=row, dtau=dtau, half_dtau2=0.5 * dtau**2, R_f=R_f,
                a=np.asarray(clip.T_wc, np.float64)[:, :3, 3] @ T_BC[:3, :3].T, lever=lever_arm_terms(R_rel, T_BC),
                alpha=pre.alpha[ii] - pre.alpha[f] - pre.beta[f] * dtau[:, None], dbeta=pre.beta[ii] - pre.beta[f],
                J_ba=J_ba,
                imu_var=np.maximum(D, 0.0), imu_modes=U.T, walk_modes=walk, dtau_RfT=dtau[:, None, None] * R_f.T[None],
                RfT_J_ba=R_f.T @ J_ba, RfT_J_bg=R_f.T @ J_bg, RfT_hat_phi=(R_f.T @ _HAT_E @ J.phi_bg[f]).reshape(3, 9)))
            row += 3 * len(dtau)
        self._bias_rows = np.zeros((7, L.n))
        self._bias_rows[0:3, L.ba] = np.eye(3) / noise.accel_bias_sigma
        self._bias_rows[3:6, L.bg] = np.eye(3) / self.bg_sigma
        self._bias_rows[6, L.td] = 1.0 / noise.time_offset_sigma
        self.link_scale = 1.0  # the ties' sigma relative to the noise model (variance component, see ``solve``)
        self.walk = 0.0  # m^2/s: the variance rate of a random walk of the backbone's positions (``solve``)
        self.imu_level = self.visual_level = 1.0  # the noise levels (see above)
        self.fitted_imu_level: float | None = None  # the IMU level the state was fitted at, where ``solve`` floored it
        self.estimate_walk, self.estimate_levels = estimate_walk, estimate_levels
        f = np.array([b.first for b in self.blocks])
        f0, f1 = f[:-1], f[1:]
        dt = pre.tau[f1] - pre.tau[f0]
        angle = so3.angle(np.swapaxes(pre.R[f0], 1, 2) @ pre.R[f1]) if self.K > 1 else np.zeros(0)
        # rad: the attitude's walk over each tie (``ImuNoiseModel.attitude_walk``); the first clip's frame is B0
        self.attitude_walk = np.maximum(np.concatenate([[0.0], noise.attitude_walk(dt, angle)]), ATTITUDE_ANCHOR)
        self.links = _Links(dt=dt, dbeta=pre.beta[f1] - pre.beta[f0], J_ba=J.beta_ba[f1] - J.beta_ba[f0],
                            J_bg=J.beta_bg[f1] - J.beta_bg[f0],
                            sigma=np.array([noise.velocity_sigma(float(t), float(a), gravity_norm)
                                            for t, a in zip(dt, angle)]), row=row)

    # ---- the model ----------------------------------------------------------------------------------------------

    def _model(self, s: FitState, priors: tuple[GaussianPrior, ...]):
        """Residual y (model minus observation) and Jacobian A [m, p] at ``s`` with every row whitened but the visual
        ones: those are projected on the modes of their clip's IMU position covariance (``_Block.imu_modes``, rows
        (mode, axis)) and left unscaled, for ``_whiten`` (their noise varies with sigma_v and lam) or the noise
        estimate; the row ranges by factor ("vis k", "link k" between clips k-1 and k, "bias", "prior i") and g's
        tangent basis [3,2]."""
        G, L, K = self.G, self.layout, self.K
        B = tangent_basis(s.g / G)
        GB = G * B
        dbg = s.bg - self.bg0
        lk = self.links
        m = lk.row + 3 * (K - 1) + len(self.scale_links) + 7 + 3 * K + sum(p.sqrt_info.shape[0] for p in priors)
        y, A = np.empty(m), np.zeros((m, L.n))
        rows = {}
        own = StateLayout(1)  # a clip's Jacobian block: the shared unknowns, then its own
        for k, blk in enumerate(self.blocks):
            lam, n = s.lam[k], len(blk.dtau)
            d = s.v[k] * blk.dtau[:, None] + blk.half_dtau2[:, None] * s.g + blk.alpha + blk.J_ba @ s.ba  # B0, m
            # d body / d bg in the clip's first frame: the clip's frame turns with bg too (R_f^T hat(d_i) phi_f)
            RfT_J_bg = blk.RfT_J_bg + (d @ blk.RfT_hat_phi).reshape(n, 3, 3)
            # the body velocity at the frames (clip's first body frame): a time offset td shows the body td later
            vel = (s.v[k] + blk.dtau[:, None] * s.g + blk.dbeta) @ blk.R_f
            # the clip's attitude error dphi_k (B0) tilts the gravity it sees: R_f^T hat(g tau^2 / 2) dphi_k
            RfT_hat_g = blk.R_f.T[None] @ so3.hat(blk.half_dtau2[:, None] * s.g)
            body = d @ blk.R_f + RfT_J_bg @ dbg - blk.lever + s.td * vel + RfT_hat_g @ s.dphi[k]
            J = np.empty((n, 3, own.n))
            J[:, :, own.g] = ((lam * (blk.half_dtau2 + s.td * blk.dtau))[:, None, None] * (blk.R_f.T @ GB))
            J[:, :, own.ba] = lam * blk.RfT_J_ba
            J[:, :, own.bg] = lam * RfT_J_bg
            J[:, :, own.td] = lam * vel
            J[:, :, own.lam(0)] = body
            J[:, :, own.v(0)] = lam * (blk.dtau_RfT + s.td * blk.R_f.T[None])
            J[:, :, own.c(0)] = _EYE3
            J[:, :, own.dphi(0)] = lam * RfT_hat_g
            r0, r1 = blk.row, blk.row + 3 * n
            y[r0:r1] = (blk.imu_modes @ (lam * body + s.c[k] - blk.a)).reshape(-1)
            J = (blk.imu_modes @ J.reshape(n, -1)).reshape(3 * n, -1)
            A[r0:r1, L.shared], A[r0:r1, L.clip(k)] = J[:, own.shared], J[:, own.clip(0)]
            rows[f"vis {k}"] = range(r0, r1)
        r0 = lk.row
        if K > 1:  # the velocity ties, one [3]-row block each
            w = 1.0 / (lk.sigma * self.link_scale)
            # the tie's force integral turned by the attitude error of the clip it spans: + hat(dbeta) dphi_(k-1)
            hat_dbeta = so3.hat(lk.dbeta)
            r = s.v[1:] - s.v[:-1] - lk.dt[:, None] * s.g - lk.dbeta - lk.J_ba @ s.ba - lk.J_bg @ dbg \
                + (hat_dbeta @ s.dphi[:-1, :, None])[:, :, 0]
            y[r0:r0 + 3 * (K - 1)] = (w[:, None] * r).reshape(-1)
            A_l = A[r0:r0 + 3 * (K - 1)].reshape(K - 1, 3, L.n)
            A_l[:, :, L.g] = -(w * lk.dt)[:, None, None] * GB
            A_l[:, :, L.ba], A_l[:, :, L.bg] = -w[:, None, None] * lk.J_ba, -w[:, None, None] * lk.J_bg
            for k in range(1, K):
                A_l[k - 1, :, L.v(k)], A_l[k - 1, :, L.v(k - 1)] = w[k - 1] * _EYE3, -w[k - 1] * _EYE3
                A_l[k - 1, :, L.dphi(k - 1)] = w[k - 1] * hat_dbeta[k - 1]
                rows[f"link {k}"] = range(r0 + 3 * (k - 1), r0 + 3 * k)
            r0 += 3 * (K - 1)
        first_scale = r0
        for k, log_ratio, _ in self.scale_links:  # the scale chain through shared frames
            lam1, lam0 = abs(s.lam[k]), abs(s.lam[k - 1])
            y[r0] = math.log(lam1) - math.log(lam0) - log_ratio
            A[r0, L.lam(k)], A[r0, L.lam(k - 1)] = 1.0 / lam1, -1.0 / lam0
            rows[f"scale {k}"] = range(r0, r0 + 1)
            r0 += 1
        if self.scale_links:  # lower triangular: link j's row is its innovation given the links before it
            y[first_scale:r0] = self._links_whitener @ y[first_scale:r0]
            A[first_scale:r0] = self._links_whitener @ A[first_scale:r0]
        # ba ~ N(0, accel_bias_sigma^2), bg ~ N(bg0, bg_sigma^2), td ~ N(0, time_offset_sigma^2)
        y[r0:r0 + 3], y[r0 + 3:r0 + 6] = s.ba / self.noise.accel_bias_sigma, dbg / self.bg_sigma
        y[r0 + 6] = s.td / self.noise.time_offset_sigma
        A[r0:r0 + 7] = self._bias_rows
        rows["bias"] = range(r0, r0 + 7)
        r0 += 7
        # the attitude walks from the window's first frame: dphi_0 = 0, dphi_k - dphi_(k-1) ~ N(0, walk_k^2)
        for k in range(K):
            sd = self.attitude_walk[k]
            y[r0:r0 + 3] = (s.dphi[k] - (s.dphi[k - 1] if k else 0.0)) / sd
            A[r0:r0 + 3, L.dphi(k)] = _EYE3 / sd
            if k:
                A[r0:r0 + 3, L.dphi(k - 1)] = -_EYE3 / sd
            rows[f"dphi {k}"] = range(r0, r0 + 3)
            r0 += 3
        if priors:
            z = PriorLayout.vector(s.g, s.ba, s.bg, s.v[0], s.lam[0], s.td)
            Jz = L.prior_jacobian(0, GB)
            for i, prior in enumerate(priors):
                r1 = r0 + prior.sqrt_info.shape[0]
                y[r0:r1], A[r0:r1] = prior.residual(z), prior.sqrt_info @ Jz
                rows[f"prior {i}"] = range(r0, r1)
                r0 = r1
        return y, A, rows, B

    def _whitener(self, s: FitState, sigma_v: np.ndarray, k: int, imu_level: float | None = None) -> np.ndarray:
        """[n] weights, or [n,n] matrix W, that whiten clip k's visual rows (on the modes of its IMU position
        covariance, per axis): their covariance is C = visual_level sigma_v,k^2 I + lam_k^2 (imu_level D + walk M),
        D the modes' IMU position variances, M the random walk's kernel on them; W W^T = C^-1 (W = L^-1, L its
        Cholesky factor); imu_level: in place of ``self.imu_level``."""
        blk = self.blocks[k]
        level = self.imu_level if imu_level is None else imu_level
        var = self.visual_level * sigma_v[k] ** 2 + s.lam[k] ** 2 * level * blk.imu_var
        if self.walk == 0.0:
            return 1.0 / np.sqrt(var)
        C = np.diag(var) + (s.lam[k] ** 2 * self.walk) * blk.walk_modes
        return solve_triangular(np.linalg.cholesky(C), np.eye(len(var)), lower=True)

    def _whiten(self, s: FitState, sigma_v: np.ndarray, y: np.ndarray, A: np.ndarray, eiv: bool,
                imu_level: float | None = None) -> None:
        """Whiten ``_model``'s visual rows of y [m] and A [m, p] in place (``_whitener``); the others are already.
        With ``eiv`` the objective is the errors-in-variables one: the whitening's own dependence on
        lam_k (its IMU terms grow with lam_k^2) joins lam_k's column, d(W y)/d lam_k = W dy/d lam_k - Phi(W C' W^T) W y
        with C' = dC/d lam_k = 2 lam_k (imu_level D + walk M) and Phi(X) X's lower triangle with half its diagonal
        (the derivative of a Cholesky factor). Holding the weights fixed instead (iterated reweighting) ignores that
        a larger lam_k also widens the rows' noise, and attenuates lam_k (the scale comes out high: a regression on a
        noisy regressor) wherever the IMU's part of C is not small."""
        level = self.imu_level if imu_level is None else imu_level
        for k, blk in enumerate(self.blocks):
            n, W = len(blk.dtau), self._whitener(s, sigma_v, k, level)
            r = slice(blk.row, blk.row + 3 * n)
            if W.ndim == 1:
                w = np.repeat(W, 3)
                y[r] *= w
                A[r] *= w[:, None]
            else:
                y[r] = (W @ y[r].reshape(n, 3)).reshape(-1)
                A[r] = (W @ A[r].reshape(n, -1)).reshape(3 * n, -1)
            if not eiv:
                continue
            lam, col = s.lam[k], self.layout.lam(k)
            if W.ndim == 1:
                A[r, col] -= np.repeat(lam * level * blk.imu_var * W**2, 3) * y[r]
            else:
                X = 2.0 * lam * (W @ (level * np.diag(blk.imu_var) + self.walk * blk.walk_modes) @ W.T)
                Phi = np.tril(X, -1) + 0.5 * np.diag(np.diag(X))
                A[r, col] -= (Phi @ y[r].reshape(n, 3)).reshape(-1)

    def linearise(self, s: FitState, sigma_v: np.ndarray, priors: tuple[GaussianPrior, ...], *, fitted: bool = False):
        """``_model`` whitened: y [m], A [m, p], the row ranges and g's tangent basis [3,2] (with estimate_levels, of
        the errors-in-variables objective); ``fitted``: at the IMU level the state was fitted at, where ``solve``
        floored the covariance's (there the cost's gradient is zero; at the floor it is not)."""
        y, A, rows, B = self._model(s, priors)
        self._whiten(s, sigma_v, y, A, self.estimate_levels, self.fitted_imu_level if fitted else None)
        return y, A, rows, B

    def _decomposed(self, s: FitState, sigma_v: np.ndarray, priors: tuple[GaussianPrior, ...]) -> _Linear:
        """``linearise`` at ``s`` with the thin SVD of its A, columns scaled to unit norm first: what counts as
        undetermined then does not depend on the units of the unknowns. At a scale lam_k near 0 with a velocity v_k
        near infinity (the clip's motion fitted as lam_k v_k, a constant velocity in model units, where its IMU says
        nothing of it) lam_k's column is 1e7 times the others' and, unscaled, the cut-off dropped gravity's and the
        biases' directions: lam_k then read as known to 3 % of itself (a clip of the real recording of
        docs/accuracy.md, fitted alone, at a scale of 9e7)."""
        y, A, rows, B = self.linearise(s, sigma_v, priors)
        norm = np.linalg.norm(A, axis=0)
        norm[norm == 0.0] = 1.0
        U, sv, Vt = np.linalg.svd(A / norm, full_matrices=False)
        return _Linear(y, rows, B, U, sv, Vt, norm)

    def _step(self, s: FitState, dx: np.ndarray, B: np.ndarray) -> FitState:
        L = self.layout
        g = s.g - self.G * B @ dx[L.g]
        return FitState(self.G * g / math.hypot(*g), s.ba - dx[L.ba], s.bg - dx[L.bg], s.lam - dx[L.lams],
                        s.v - dx[L.vs], s.c - dx[L.cs], s.dphi - dx[L.dphis], s.td - float(dx[L.td]))

    # ---- solution -----------------------------------------------------------------------------------------------

    def initial_state(self, g: np.ndarray, lam: np.ndarray | None = None) -> FitState:
        """A starting point for gravity g [3] (B0) with the biases at their priors: per clip, a_ki = lam_k body_ki(v_k
        = 0) + lam_k R_f^T v_k dtau + c_k is linear in (lam_k, lam_k v_k, c_k), solved by least squares (lam_k held at
        ``lam`` [K] where it is given and finite)."""
        K = self.K
        s = FitState(self.G * np.asarray(g, np.float64) / np.linalg.norm(g), np.zeros(3), self.bg0.copy(),
                     np.ones(K), np.zeros((K, 3)), np.zeros((K, 3)), np.zeros((K, 3)))
        for k, blk in enumerate(self.blocks):
            n = len(blk.dtau)
            X = np.empty((n, 3, 7))  # columns: lam, lam v (solved for in place of v), c
            X[:, :, 0] = (blk.half_dtau2[:, None] * s.g + blk.alpha) @ blk.R_f - blk.lever
            X[:, :, 1:4] = blk.dtau_RfT
            X[:, :, 4:7] = _EYE3
            X, y = X.reshape(3 * n, 7), blk.a.reshape(-1)
            if lam is not None and np.isfinite(lam[k]):
                s.lam[k] = float(lam[k])
                coef = np.empty(7)
                coef[1:] = lstsq(X[:, 1:], y - s.lam[k] * X[:, 0])
            else:
                coef = lstsq(X, y)
                s.lam[k] = coef[0]
            s.v[k] = blk.R_f @ coef[1:4] / s.lam[k] if s.lam[k] != 0.0 else np.zeros(3)
            s.c[k] = coef[4:7]
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
        if self.estimate_levels:
            # from the fixed-weights solution: from a start far off (a clip started at its neighbour's scale) the
            # errors-in-variables objective's descent can lead off to |lam| -> inf (``_damped``)
            s, converged = self._gauss_newton(s, sigma_v, priors, iterations, tol, False, eiv=True)
        lin = self._decomposed(s, sigma_v, priors)
        result = self._result(s, lin, sigma_v, converged)
        # The velocity ties are the IMU's word over a second; where the real IMU is worse than its model there
        # (scale-factor errors in fast turns, a changing bias) their residuals show it: their variance component,
        # estimated from them, widens them (at most 10x) before the scales are trusted.
        for _ in range(2):
            vc = float(result.link_chi2.sum() / max(result.link_dof.sum(), 1e-9)) if self.K > 1 else 1.0
            if vc <= 1.2 or self.link_scale >= 10.0:
                break
            self.link_scale = min(self.link_scale * math.sqrt(vc), 10.0)
            s, converged = self._gauss_newton(s, sigma_v, priors, iterations, tol, False, eiv=self.estimate_levels)
            lin = self._decomposed(s, sigma_v, priors)
            result = self._result(s, lin, sigma_v, converged)
        # A 3DFM's errors are correlated in time (a scale drifting inside the clip, a depth-dependent bias): where the
        # window's visual residuals show a random walk of the positions beyond each clip's white noise, its variance
        # (restricted maximum likelihood over every clip, metric units) joins the error model before the scales are.
        if self.estimate_walk and self.K > 1:
            walk = self._walk_reml(s, sigma_v, priors, lin)
            if walk > 0.0:
                self.walk = walk
                s, converged = self._gauss_newton(s, sigma_v, priors, iterations, tol, False, eiv=self.estimate_levels)
                lin = self._decomposed(s, sigma_v, priors)
                result = self._result(s, lin, sigma_v, converged)
        if self.estimate_levels:
            score, info = self._reml_terms(s, sigma_v, lin, LEVELS)
            # The residuals can show the IMU worse than its model, never better: the part of its error that looks like
            # a change of scale (a scale factor, a tilt growing with the motion) is taken up by the scales and leaves
            # no trace in them, and the model's level covers it (at the level the residuals give, the real V2_03 IMU's
            # claims at 1 mm of pose noise were beyond 3 sigma six times as often). The scales are fitted at the
            # estimated levels; their covariance, and what ``marginalise`` keeps of them, at no less than the model's.
            if self.imu_level < 1.0:
                self.fitted_imu_level, self.imu_level = self.imu_level, 1.0
                # the step still to go is the objective's the state was fitted to
                result = self._result(s, self._decomposed(s, sigma_v, priors), sigma_v, converged,
                                      next_step=result.next_step)
            result.level_score, result.level_info = score, info
        return result

    def _kernels(self, s: FitState, sigma_v: np.ndarray, k: int, names: Sequence[str]) -> np.ndarray:
        """[c,n,n]: clip k's derivatives (per axis, in its whitened rows) of the visual rows' covariance by each
        variance component in ``names``: "walk" lam^2 W M W^T; "imu_level" lam^2 imu_level W D W^T and "visual_level"
        visual_level sigma_v^2 W W^T (the two levels by their logarithms)."""
        blk, W = self.blocks[k], self._whitener(s, sigma_v, k)
        lam2, full = s.lam[k] ** 2, W.ndim == 2
        kernel = {"walk": lambda: lam2 * (W @ blk.walk_modes @ W.T if full else np.outer(W, W) * blk.walk_modes),
                  "imu_level": lambda: lam2 * self.imu_level * ((W * blk.imu_var) @ W.T if full
                                                                else np.diag(W**2 * blk.imu_var)),
                  "visual_level": lambda: self.visual_level * sigma_v[k] ** 2 * (W @ W.T if full else np.diag(W**2))}
        return np.stack([kernel[name]() for name in names])

    def _reml_terms(self, s: FitState, sigma_v: np.ndarray, lin: _Linear,
                    names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """The score [c] and Fisher information [c,c] of the restricted likelihood of the residuals at ``s`` (``lin``:
        ``_decomposed`` there: its projector is onto the whitened Jacobian, with estimate_levels the errors-in-variables
        one) in the variance components ``names`` (``_kernels``), the other rows' models held. In the
        coordinates whitened at the current values, with G_i the covariance's derivative by component i
        (block-diagonal by clip and axis) and P the residual projector, the score is (r^T G_i r - tr(P G_i)) / 2 and
        the information tr(P G_i P G_j) / 2."""
        Q = lin.U[:, lin.sv > 1e-10 * lin.sv[0]]  # P = I - Q Q^T
        r = lin.y - Q @ (Q.T @ lin.y)
        c = len(names)
        rGr, trG = np.zeros(c), np.zeros(c)
        trGG, trQGGQ = np.zeros((c, c)), np.zeros((c, c))
        QGQ = np.zeros((c, Q.shape[1], Q.shape[1]))
        for k, blk in enumerate(self.blocks):
            n = len(blk.dtau)
            G = self._kernels(s, sigma_v, k, names)
            rows = slice(blk.row, blk.row + 3 * n)
            rk, Qk = r[rows].reshape(n, 3), Q[rows].reshape(n, -1)  # Qk rows: frame, columns: (axis, q)
            GQ = G @ Qk
            rGr += np.einsum("ia,cij,ja->c", rk, G, rk)
            trG += 3.0 * np.trace(G, axis1=1, axis2=2)
            trGG += 3.0 * np.einsum("aij,bij->ab", G, G)
            trQGGQ += np.einsum("aij,bij->ab", GQ, GQ)
            QGQ += np.einsum("ij,cik->cjk", Qk.reshape(3 * n, -1), GQ.reshape(c, 3 * n, -1))
        score = 0.5 * (rGr - (trG - np.trace(QGQ, axis1=1, axis2=2)))
        info = 0.5 * (trGG - 2.0 * trQGGQ + np.einsum("ajk,bkj->ab", QGQ, QGQ))
        return score, info

    def _walk_reml(self, s: FitState, sigma_v: np.ndarray, priors: tuple[GaussianPrior, ...], start: _Linear, *,
                   iterations: int = 6) -> float:
        """The random walk's variance rate (m^2/s of metric position, shared by the clips) that maximises the
        restricted likelihood of the residuals at ``s`` (``_reml_terms``), each clip's white noise and the other rows'
        models held: Fisher scoring, 0 where the residuals show none. ``start``: ``_decomposed`` at ``s`` with the
        current walk (the solution's own, where the scoring starts)."""
        walk = self.walk
        for it in range(iterations):
            self.walk = walk
            lin = start if it == 0 else self._decomposed(s, sigma_v, priors)
            score, info = self._reml_terms(s, sigma_v, lin, ("walk",))
            new = max(walk + float(score[0] / info[0, 0]), 0.0) if info[0, 0] > 0 else walk
            if abs(new - walk) <= 1e-3 * max(new, 1e-12):
                walk = new
                break
            walk = new
        self.walk = 0.0
        return walk

    def _gauss_newton(self, s: FitState, sigma_v: np.ndarray, priors: tuple[GaussianPrior, ...], iterations: int,
                      tol: float, estimate: bool, *, eiv: bool = False) -> tuple[FitState, bool]:
        """Gauss-Newton from ``s`` (``solve``), of the errors-in-variables objective where ``eiv`` (``_whiten``, its
        steps ``_damped``); ``estimate``: the single clip's visual noise first (``_visual_noise``)."""
        for it in range(iterations):
            y, A, _, B = self._model(s, priors)
            if estimate and it == 0:  # at the linear starting point: re-estimating it later changes nothing
                sigma_v[0] = self._visual_noise(s, y, A)
            self._whiten(s, sigma_v, y, A, eiv)
            dx = lstsq(A, y)
            if eiv:
                dx = self._damped(s, dx, B, float(y @ y), sigma_v, priors)
            s = self._step(s, dx, B)
            if it >= 1 and np.all(np.abs(dx[self.layout.lams]) <= tol * np.abs(s.lam)) \
                    and np.abs(dx[self.layout.g]).max() <= 0.1 * tol:
                return s, True
        return s, False

    def _damped(self, s: FitState, dx: np.ndarray, B: np.ndarray, cost: float, sigma_v: np.ndarray,
                priors: tuple[GaussianPrior, ...]) -> np.ndarray:
        """The Gauss-Newton step dx from ``s`` halved (at most 5 times, the last untested) while it raises the whitened
        cost above ``cost``: the errors-in-variables objective flattens out as |lam_k| grows (the clip's weights fall
        with lam_k^2), and a full step can overshoot onto that slope, where the fit would run off to infinity. A step
        that moves no scale by more than a tenth is taken as it is (near the solution, where every step is)."""
        if np.all(np.abs(dx[self.layout.lams]) <= 0.1 * np.abs(s.lam)):
            return dx
        for _ in range(5):
            y = self.linearise(self._step(s, dx, B), sigma_v, priors)[0]
            if float(y @ y) <= cost:
                break
            dx = 0.5 * dx
        return dx

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
            Hi = inv(H)
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

    def _result(self, s: FitState, lin: _Linear, sigma_v: np.ndarray, converged: bool,
                next_step: np.ndarray | None = None) -> FitResult:
        """The solution at ``s`` from ``lin`` (``_decomposed`` there); ``next_step``: ``FitResult.next_step`` where it
        is not ``lin``'s Gauss-Newton step."""
        y, rows, B, U, sv, Vt = lin.y, lin.rows, lin.B, lin.U, lin.sv, lin.Vt
        keep = sv > 1e-10 * sv[0]
        if next_step is None:
            next_step = (Vt[keep].T / sv[keep]) @ (U[:, keep].T @ y) / lin.norm
        cov = (Vt[keep].T / sv[keep] ** 2) @ Vt[keep] / np.outer(lin.norm, lin.norm)
        undetermined = (np.abs(Vt[~keep]) > 1e-6).any(0) if (~keep).any() else np.zeros(self.layout.n, bool)
        leverage = (U[:, keep] ** 2).sum(1)
        vis = [rows[f"vis {k}"] for k in range(self.K)]
        links = [rows[f"link {k}"] for k in range(1, self.K)]
        chi2, link_chi2 = ([float((y[r.start:r.stop] ** 2).sum()) for r in group] for group in (vis, links))
        dof, link_dof = ([max(float(len(r) - leverage[r.start:r.stop].sum()), 1e-3) for r in group]
                         for group in (vis, links))
        scale_chi2, scale_dof = np.full(max(self.K - 1, 0), np.nan), np.full(max(self.K - 1, 0), np.nan)
        for k, _, _ in self.scale_links:
            r = rows[f"scale {k}"].start
            scale_chi2[k - 1], scale_dof[k - 1] = y[r] ** 2, max(1.0 - leverage[r], 1e-3)
        dof_total = max(float(len(y) - leverage.sum()), 1.0)
        vf = max(1.0, float(y @ y) / dof_total)
        lam = s.lam
        stat = np.sqrt(np.diag(cov)[self.layout.lams] * vf) * (t975(dof_total) / Z975)
        rel = np.full(self.K, np.inf)  # undetermined, or a scale that is not positive: no relative sigma
        ok = (lam > 0) & ~undetermined[self.layout.lams]
        rel[ok] = np.sqrt((stat[ok] / lam[ok]) ** 2 + self.noise.rel_floor**2)
        scale = np.full(self.K, np.nan)
        scale[lam > 0] = 1.0 / lam[lam > 0]
        return FitResult(state=s, scale=scale, scale_rel_sigma=rel, sigma_v=sigma_v.copy(), chi2=np.array(chi2),
                         dof=np.array(dof), variance_factor=vf, cov=cov * vf, tangent=B, converged=converged,
                         next_step=next_step, link_chi2=np.array(link_chi2), link_dof=np.array(link_dof),
                         scale_chi2=scale_chi2, scale_dof=scale_dof)


def _links_whitener(scale_links: list[tuple[int, float, float]], traj_depth_sigma: Sequence[float]) -> np.ndarray:
    """W [l,l] lower triangular with W C W^T = I for the covariance C of the scale links' residuals
    log lam_k - log lam_(k-1) - log_ratio (``MetricFit._model``): lam is what each clip's trajectory says, the links
    measure depth, and clip k's trajectory is at its depth's scale times exp(u_k), u_k ~ N(0, tau_k^2) (tau:
    ``traj_depth_sigma``), so link k carries u_k - u_(k-1) beside its own sigma: var sigma_k^2 + tau_k^2 +
    tau_(k-1)^2, and -tau_k^2 with link k+1, which shares clip k (a random effect per clip: consecutive links'
    errors cancel along a chain, a clip's own trajectory scale keeps its u_k)."""
    k = np.array([j for j, _, _ in scale_links], dtype=int)
    tau2 = np.asarray(traj_depth_sigma, np.float64) ** 2
    C = np.diag(np.array([sigma for _, _, sigma in scale_links]) ** 2 + tau2[k] + tau2[k - 1])
    i = np.flatnonzero(k[1:] == k[:-1] + 1)  # links i and i + 1 share clip k[i]
    C[i, i + 1] = C[i + 1, i] = -tau2[k[i]]
    return solve_triangular(np.linalg.cholesky(C), np.eye(len(k)), lower=True)


@dataclass(frozen=True)
class _Block:
    """Precomputed terms of one clip (see ``MetricFit._model``): first stamp index; row: its first row in the model;
    dtau, half_dtau2 = dtau^2 / 2 [n]; R_f [3,3]; a [n,3]; lever [n,3]; alpha [n,3] (bias-free displacement part, B0);
    dbeta [n,3] (bias-free velocity change from the first frame, B0);
    J_ba [n,3,3]; its IMU position covariance (``ImuNoiseModel.position_cov``) as variances imu_var [n] (m^2) along
    the rows of imu_modes [n,n] (orthonormal); walk_modes [n,n] s, the kernel min(dtau_i, dtau_j) of a random walk of
    the positions on those modes; the constant Jacobian factors dtau_RfT, RfT_J_ba, RfT_J_bg [n,3,3]
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
    dbeta: np.ndarray
    J_ba: np.ndarray
    imu_var: np.ndarray
    imu_modes: np.ndarray
    walk_modes: np.ndarray
    dtau_RfT: np.ndarray
    RfT_J_ba: np.ndarray
    RfT_J_bg: np.ndarray
    RfT_hat_phi: np.ndarray


@dataclass(frozen=True)
class _Linear:
    """The whitened model at a state (``MetricFit.linearise``): y [m], the row ranges, g's tangent basis B [3,2], and
    the thin SVD of its A [m,p] with each column divided by its norm [p]: U [m,r], sv [r], Vt [r,p] (r = min(m,
    p)), A = U diag(sv) Vt diag(norm)."""

    y: np.ndarray
    rows: dict[str, range]
    B: np.ndarray
    U: np.ndarray
    sv: np.ndarray
    Vt: np.ndarray
    norm: np.ndarray


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
LEVELS = ("imu_level", "visual_level")  # the noise levels' variance components (``MetricFit.solve``)
SETTLED_SIGMAS = 0.25  # a scale has settled where the step still to go moves it by at most this many of its 1-sigma
ATTITUDE_ANCHOR = 1e-6  # rad: the window's first frame is B0 itself (its attitude error is zero)
_HAT_E = so3.hat(np.eye(3))  # [3,3,3]: hat of each axis


__all__ = ["FitClip", "FitResult", "FitState", "MetricFit", "ScaleLink", "fit_stamps"]
