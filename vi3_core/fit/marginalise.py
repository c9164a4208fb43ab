"""Sliding-window marginalisation: what the oldest clips of a fitted window say about the unknowns the window keeps,
as a Gaussian prior on the prior vector z (``layout.PriorLayout``) for the window that starts after them."""

from __future__ import annotations

import math

import numpy as np

from vi3_core import so3
from vi3_core.fit.layout import PriorLayout
from vi3_core.fit.metric_fit import FitResult, MetricFit
from vi3_core.fit.prior import GaussianPrior, sqrt_of_info, unit_diagonal_scale


def marginalise(fit: MetricFit, result: FitResult, drop: int,
                priors: tuple[GaussianPrior, ...] = ()) -> GaussianPrior:
    """What clips 0..drop-1 of ``fit`` say about (g, ba, bg, v_drop, lam_drop) once their own unknowns are eliminated:
    their visual rows, the velocity ties and scale links up to clip ``drop`` and ``priors`` (the bias priors are left
    out: every fit adds its own), linearised at ``result`` and reduced by the Schur complement, as a Gaussian prior in
    clip ``drop``'s first body frame for the window that starts there. Clip ``drop``'s scale is in it through the scale
    link to clip drop-1 (nothing without one): the scale chain goes on past the window. That link's row carries clip
    ``drop``'s trajectory against its depth (``FitClip.traj_depth_sigma``), which the next window's link from it
    carries again: the prior does not keep their correlation, so the chain counts that term twice, on the safe side."""
    if not 0 < drop < fit.K:
        raise ValueError(f"marginalise: drop must be in 1..{fit.K - 1}, got {drop}")
    L = fit.layout
    y, A, rows, B = fit.linearise(result.state, result.sigma_v, priors)
    names = [f"vis {k}" for k in range(drop)] + [f"link {k}" for k in range(1, drop + 1)]
    names += [f"dphi {k}" for k in range(drop)]
    names += [f"scale {k}" for k in range(1, drop + 1) if f"scale {k}" in rows]
    names += [f"prior {i}" for i in range(len(priors))]
    sel = np.concatenate([np.array(rows[name], dtype=int) for name in names])
    H, b = A[sel].T @ A[sel], A[sel].T @ y[sel]  # cost 1/2 |y + A dx|^2 of the parameter change dx
    if fit.fitted_imu_level is not None:
        # the information at the covariance's floor of the IMU level, the gradient where the state was fitted
        # (``MetricFit.solve``): else the prior would pull the next window towards the floor's solution
        y_f, A_f = fit.linearise(result.state, result.sigma_v, priors, fitted=True)[:2]
        b = A_f[sel].T @ y_f[sel]
    kept = L.prior_columns(drop)
    gone = np.arange(L.clip(0).start, L.clip(drop).start)
    # An undetermined unknown of a dropped clip (a scale its data do not fix) carries nothing over: the pseudo-
    # inverse of the column-scaled block drops it instead of dividing by round-off.
    H_dd = H[np.ix_(gone, gone)]
    d = unit_diagonal_scale(H_dd)
    H_dd_inv = np.linalg.pinv(H_dd / np.outer(d, d), rcond=1e-10, hermitian=True) / np.outer(d, d)
    X = H_dd_inv @ H[np.ix_(gone, kept)]
    H_m = H[np.ix_(kept, kept)] - H[np.ix_(kept, gone)] @ X
    b_m = b[kept] - X.T @ b[gone]
    sqrt_H = sqrt_of_info(0.5 * (H_m + H_m.T))
    # The kept parameters' change from z - z*: g through its tangent plane (B^T / |g|), the rest as they are.
    P = L.prior_jacobian(drop, B / fit.G)[:, kept].T
    s = result.state
    f = fit.blocks[drop].first
    dt = float(fit.pre.tau[f])
    # Residual sqrt_H dx + sqrt_H^-T b_m, deflated by the fit's a-posteriori variance factor (its covariance is
    # inflated); the biases walk while the prior is carried to clip ``drop``'s first frame.
    offset = np.linalg.lstsq(sqrt_H.T, b_m, rcond=None)[0]
    vf = math.sqrt(result.variance_factor)
    prior = GaussianPrior(PriorLayout.vector(s.g, s.ba, s.bg, s.v[drop], s.lam[drop], s.td), sqrt_H @ P / vf,
                          offset / vf)
    # the frame it is carried into is clip ``drop``'s, whose attitude error from B0 the new window takes as zero
    turn = float(np.sum(fit.attitude_walk[1:drop + 1] ** 2))
    prior = prior.widened(fit.noise.accel_bias_walk**2 * dt, fit.noise.gyro_bias_walk**2 * dt,
                          fit.G**2 * turn, float(s.v[drop] @ s.v[drop]) * turn)
    phi = fit.pre.J.phi_bg[f]
    return prior.moved(so3.exp(phi @ (s.bg - fit.bg0)) @ fit.pre.R[f], phi)


__all__ = ["marginalise"]
