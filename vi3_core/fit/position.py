"""Scale from positions for a known gravity and first-frame velocity: the backbone's body positions against the
IMU-propagated ones (paper Eq. preintegrationTranslation summed from the first frame), as the oracle
initialisation uses it.

In the first body frame B1, the body position at frame i is, from the IMU, p_i = v1 tau_i + 0.5 g tau_i^2 + alpha_i,
and, from the backbone's camera positions t_i (first camera frame C1, up to scale s), p_i = s R_BC t_i + t_BC -
R_B1Bi t_BC = s a_i + b_i (``body_position_terms``, shared by the GT-free initialisation and the online window).
With g and v1 known this is linear in s alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vi3_core.preintegration import Preintegration


def body_position_terms(T_wc: np.ndarray, R_B1B: np.ndarray, T_BC: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(a, b), each [n,3]: body position at frame i in B1 = s a_i + b_i for backbone camera poses T_wc [n,4,4]
    (first camera frame, up to scale s), body rotations R_B1B [n,3,3] and T_BC [4,4]. a_i = R_BC t_i (model units);
    b_i = t_BC - R_B1Bi t_BC, the lever arm in metres (never scaled)."""
    return T_wc[:, :3, 3] @ T_BC[:3, :3].T, lever_arm_terms(R_B1B, T_BC)


def lever_arm_terms(R_B1B: np.ndarray, T_BC: np.ndarray) -> np.ndarray:
    """b [n,3] = t_BC - R_B1Bi t_BC, metres: where the camera's lever arm puts body positions relative to camera
    positions for body rotations R_B1B [n,3,3] (never scaled)."""
    t_BC = T_BC[:3, 3]
    return t_BC - R_B1B @ t_BC


@dataclass(frozen=True)
class PositionFit:
    """scale: s (metric = s * model translation); rms: root mean square of the position residual
    s a_i + b_i - p_i over the frames, m."""

    scale: float
    rms: float


def fit_positions(T_wc: np.ndarray, pre: Preintegration, T_BC: np.ndarray, g: np.ndarray,
                  v1: np.ndarray) -> PositionFit:
    """Least-squares scale s = <a, p - b> / |a|^2 for gravity g [3] (m/s^2) and velocity v1 [3] (m/s) in B1.

    T_wc: [n,4,4] backbone camera poses in C1 (up to scale); pre: the clip's preintegration at the same stamps;
    T_BC: [4,4]. A backbone predicting no translation gives scale NaN.
    """
    a, b = body_position_terms(T_wc, pre.R, T_BC)
    p = pre.propagate(g, v1).p
    denom = float((a * a).sum())
    s = float((a * (p - b)).sum() / denom) if denom > 0.0 else float("nan")
    resid = s * a + b - p
    return PositionFit(s, float(np.sqrt((resid**2).sum(1).mean())))
