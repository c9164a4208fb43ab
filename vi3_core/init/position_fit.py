"""Scale (and first-frame velocity) from positions, for a known gravity: the backbone's body positions against the
IMU-propagated ones (paper Eq. preintegrationTranslation summed from the first frame).

In the first body frame B1, the body position at frame i is, from the IMU, p_i = v1 tau_i + 0.5 g tau_i^2 + alpha_i,
and, from the backbone's camera positions t_i (first camera frame C1, up to scale s), p_i = s R_BC t_i + t_BC -
R_B1Bi t_BC = s a_i + b_i. With g known this is linear in (s, v1); with v1 known too, in s alone. Positions are
first integrals of velocity, so this is much better conditioned than the velocity increments (second differences)
the GT-free initialisation has to use when g and v1 are unknown.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vi3_core.preintegration import Preintegration


@dataclass(frozen=True)
class PositionFit:
    """scale: s (metric = s * model translation); v1: [3] body velocity at the first frame in B1, m/s;
    rms: root mean square of the position residual s a_i + b_i - p_i over the frames, m."""

    scale: float
    v1: np.ndarray
    rms: float


def fit_positions(T_wc: np.ndarray, pre: Preintegration, T_BC: np.ndarray, g: np.ndarray, *,
                  v1: np.ndarray | None = None, v1_prior: np.ndarray | None = None,
                  v1_weight_s: float = 0.0) -> PositionFit:
    """Least-squares fit of positions for gravity g [3] in B1 (m/s^2).

    T_wc: [n,4,4] backbone camera poses in C1 (up to scale); pre: the clip's preintegration at the same stamps;
    T_BC: [4,4]. With ``v1`` [3] given, v1 is held fixed and only s is fitted (s = <a, p - b> / |a|^2). Otherwise
    s and v1 are fitted jointly; ``v1_prior`` [3] with ``v1_weight_s`` > 0 (seconds: the weight of a velocity
    error against a position error) adds the prior term v1_weight_s * (v1 - v1_prior) to the least squares.
    A backbone predicting no translation gives scale NaN.
    """
    g = np.asarray(g, dtype=np.float64)
    R_BC, t_BC = T_BC[:3, :3], T_BC[:3, 3]
    a = T_wc[:, :3, 3] @ R_BC.T
    b = t_BC - pre.R @ t_BC
    tau = pre.tau[:, None]
    c = 0.5 * g * tau**2 + pre.alpha - b  # = s a_i - v1 tau_i
    if v1 is not None:
        v1 = np.asarray(v1, dtype=np.float64)
        denom = float((a * a).sum())
        s = float((a * (c + v1 * tau)).sum() / denom) if denom > 0.0 else float("nan")
    else:
        n = len(tau)
        A = np.zeros((3 * n, 4))
        A[:, 0] = a.reshape(-1)
        A[:, 1:] = -np.kron(pre.tau[:, None], np.eye(3))
        rhs = c.reshape(-1)
        if v1_prior is not None and v1_weight_s > 0.0:
            A = np.vstack([A, np.hstack([np.zeros((3, 1)), v1_weight_s * np.eye(3)])])
            rhs = np.concatenate([rhs, v1_weight_s * np.asarray(v1_prior, dtype=np.float64)])
        if not (a * a).sum() > 0.0:
            return PositionFit(float("nan"), np.full(3, np.nan), float("nan"))
        x = np.linalg.lstsq(A, rhs, rcond=None)[0]
        s, v1 = float(x[0]), x[1:]
    resid = s * a - v1 * tau - c
    return PositionFit(s, v1, float(np.sqrt((resid**2).sum(1).mean())))
