"""Joint metric fit of the last few clips of a stream (beyond the paper, which fits each clip on its own).

Over one 0.75 s clip a constant acceleration is nearly indistinguishable from a gravity tilt, so the paper's
per-clip scale rests on a weakly observed gravity and v1. Over a window of several clips linked by continuous IMU,
gravity, the velocities and the accelerometer bias are much better observed, and every clip keeps its own scale (a
3DFM normalises each clip differently).

Unknowns live in B0, the body frame at the window's first stamp; the IMU is preintegrated over the whole window
(paper Eqs. preintegrationRotation / Velocity / Translation, gyro bias bg; alpha and beta from B0, linear in the
accelerometer bias ba, a constant in the IMU frame, through J_alpha, J_beta). For clip k with first frame f and
velocity v_k there (in B0), the body displacement to its frame i is, with dtau = tau_i - tau_f,
    p_i - p_f = v_k dtau + 0.5 g dtau^2 + (alpha_i - alpha_f - beta_f dtau)
                + (J_alpha_i - J_alpha_f - J_beta_f dtau) ba,
and from its backbone camera positions t_ki (its first camera frame, model units) R_B0Bf (s_k a_ki + b_ki), with
a_ki = R_BC t_ki and the metric lever-arm term b_ki = t_BC - R_BfBi t_BC (``body_position_terms``). Consecutive
clips' velocities are tied by the IMU between their first frames, v_k = v_(k-1) + g dtau_k + dbeta_k + dJ_beta_k ba
(Eq. preintegrationVelocity), as soft rows: the gyro's random walk tilts the integrated attitude over seconds, and
a hard tie turns that tilt into velocity errors of several per cent at walking speed. One linear least-squares
problem in x = [g (3), ba (3), v_1..v_K (3K), s_1..s_K], |g| fixed by Gauss-Newton steps on its tangent plane.
Positions (first integrals) rather than velocity increments keep it well conditioned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vi3_core.init.position_fit import body_position_terms
from vi3_core.preintegration import accel_bias_jacobians, merged_grid, preintegrate
from vi3_core.types import ImuSamples

G_COLS, BA_COLS = slice(0, 3), slice(3, 6)
LINK_NOMINAL_S = 0.8  # s: consecutive clips of 8 frames at stride 2 from a 20 Hz camera


@dataclass(frozen=True)
class WindowClip:
    """One clip as the window sees it: stamps [n] s; T_wc [n,4,4] backbone camera poses in its first camera frame
    (T_wc[0] = I, model units)."""

    stamps: np.ndarray
    T_wc: np.ndarray


@dataclass(frozen=True)
class Prior:
    """Extra least-squares rows on x (see the module docstring): A [r, 6 + 4K], y [r]."""

    A: np.ndarray
    y: np.ndarray


@dataclass(frozen=True)
class WindowFit:
    """g [3] m/s^2 and v [K,3] m/s (each clip's first frame) in B0, ba [3] m/s^2 (IMU frame); scales [K];
    scale_rel_sigma [K] (inf where the window cannot determine the scale):
    1-sigma of each scale over the scale (from the position residual); rms [K]: position residual per clip, m."""

    g: np.ndarray
    ba: np.ndarray
    v: np.ndarray
    scales: np.ndarray
    scale_rel_sigma: np.ndarray
    rms: np.ndarray


class WindowSystem:
    """The position and velocity-link equations of ``clips`` (time-ordered, IMU over their whole span).

    imu: samples covering clips[0].stamps[0] .. clips[-1].stamps[-1]; bg [3] rad/s; T_BC [4,4]; ba_weight: weight
    of the zero-bias prior row (m per m/s^2); link_weight_s: weight of the velocity tie between first frames
    LINK_NOMINAL_S apart (m per m/s), scaled by sqrt(LINK_NOMINAL_S / dt) for other spacings (the IMU's velocity
    uncertainty grows with the time it integrates, e.g. over a gap left by dropped clips)."""

    def __init__(self, clips: list[WindowClip], imu: ImuSamples, bg: np.ndarray, T_BC: np.ndarray, *,
                 gravity_norm: float, ba_weight: float, link_weight_s: float) -> None:
        self.gravity_norm = gravity_norm
        K = self.K = len(clips)
        stamps = np.unique(np.concatenate([c.stamps for c in clips]))
        grid = merged_grid(imu, stamps)
        pre = self.pre = preintegrate(imu, stamps, bg, grid=grid)
        self.J_beta, J_alpha = accel_bias_jacobians(imu, stamps, bg, grid=grid)
        self.first = [int(np.searchsorted(stamps, c.stamps[0])) for c in clips]
        n_x = 6 + 4 * K
        blocks_A, blocks_y = [], []
        for k, clip in enumerate(clips):
            idx = np.searchsorted(stamps, clip.stamps)
            f, rest = idx[0], idx[1:]
            R_f = pre.R[f]
            a, b = body_position_terms(clip.T_wc[1:], np.einsum("ji,njk->nik", R_f, pre.R[rest]), T_BC)
            dtau = pre.tau[rest] - pre.tau[f]
            A = np.zeros((len(rest), 3, n_x))
            A[:, :, G_COLS] = -0.5 * dtau[:, None, None] ** 2 * np.eye(3)
            A[:, :, BA_COLS] = -(J_alpha[rest] - J_alpha[f] - dtau[:, None, None] * self.J_beta[f])
            A[:, :, self._v(k)] = -dtau[:, None, None] * np.eye(3)
            A[:, :, 6 + 3 * K + k] = a @ R_f.T
            blocks_A.append(A.reshape(-1, n_x))
            blocks_y.append((pre.alpha[rest] - pre.alpha[f] - dtau[:, None] * pre.beta[f] - b @ R_f.T).reshape(-1))
        self.rows = np.cumsum([0] + [len(y) for y in blocks_y])
        for k in range(1, K):  # v_k - v_(k-1) - g dtau - dJ_beta ba = dbeta
            f0, f1 = self.first[k - 1], self.first[k]
            A = np.zeros((3, n_x))
            A[:, self._v(k)], A[:, self._v(k - 1)] = np.eye(3), -np.eye(3)
            A[:, G_COLS] = -(pre.tau[f1] - pre.tau[f0]) * np.eye(3)
            A[:, BA_COLS] = -(self.J_beta[f1] - self.J_beta[f0])
            w = link_weight_s * np.sqrt(LINK_NOMINAL_S / (pre.tau[f1] - pre.tau[f0]))
            blocks_A.append(w * A)
            blocks_y.append(w * (pre.beta[f1] - pre.beta[f0]))
        ba_rows = np.zeros((3, n_x))
        ba_rows[:, BA_COLS] = ba_weight * np.eye(3)
        self.A = np.vstack([*blocks_A, ba_rows])
        self.y = np.concatenate([*blocks_y, np.zeros(3)])

    def _v(self, k: int) -> slice:
        return slice(6 + 3 * k, 9 + 3 * k)

    # ---- priors on the state at clip k's first frame ----------------------------------------------------------

    def velocity_prior(self, k: int, v_Bk: np.ndarray, weight_s: float) -> Prior:
        """Velocity [3] m/s at clip k's first frame, in that body frame."""
        A = np.zeros((3, self.A.shape[1]))
        A[:, self._v(k)] = np.eye(3)
        return Prior(weight_s * A, weight_s * (self.pre.R[self.first[k]] @ v_Bk))

    def gravity_prior(self, k: int, g_Bk: np.ndarray, weight_s2: float) -> Prior:
        """Gravity [3] m/s^2 in clip k's first body frame."""
        A = np.zeros((3, self.A.shape[1]))
        A[:, G_COLS] = np.eye(3)
        return Prior(weight_s2 * A, weight_s2 * (self.pre.R[self.first[k]] @ g_Bk))

    # ---- solution --------------------------------------------------------------------------------------------

    def solve(self, priors: tuple[Prior, ...] = (), *, iterations: int = 3) -> WindowFit:
        """Least squares with |g| = gravity_norm (tangent-plane Gauss-Newton, ``iterations`` >= 1 steps from the
        unconstrained solution)."""
        A = np.vstack([self.A, *(p.A for p in priors)])
        y = np.concatenate([self.y, *(p.y for p in priors)])
        x = np.linalg.lstsq(A, y, rcond=None)[0]
        G = self.gravity_norm
        g = G * x[G_COLS] / np.linalg.norm(x[G_COLS])
        for _ in range(max(iterations, 1)):
            B = G * _tangent_basis(g / G)
            A_t = np.hstack([A[:, G_COLS] @ B, A[:, 3:]])
            z = np.linalg.lstsq(A_t, y - A[:, G_COLS] @ g, rcond=None)[0]
            g = G * (g + B @ z[:2]) / np.linalg.norm(g + B @ z[:2])
            x = np.concatenate([g, z[2:]])
        r = (self.A @ x - self.y)[: self.rows[-1]]
        rms = np.array([np.sqrt(3.0 * np.mean(r[a:b] ** 2)) for a, b in zip(self.rows[:-1], self.rows[1:])])
        sigma2 = float(r @ r) / max(self.rows[-1] - A_t.shape[1], 1)
        s = x[-self.K:]
        sigma = np.sqrt(sigma2 * _variances(A_t)[-self.K:])
        rel = np.divide(sigma, np.abs(s), out=np.full(self.K, np.inf), where=np.abs(s) > 0)  # no scale: infinite
        return WindowFit(g=g, ba=x[BA_COLS], v=x[6:6 + 3 * self.K].reshape(-1, 3), scales=s, scale_rel_sigma=rel,
                         rms=rms)

    def state_at(self, k: int, fit: WindowFit) -> tuple[np.ndarray, np.ndarray]:
        """(g [3], v [3]) at clip k's first frame, in that body frame."""
        R_f = self.pre.R[self.first[k]]
        return R_f.T @ fit.g, R_f.T @ fit.v[k]


def _variances(A: np.ndarray, *, rcond: float = 1e-10) -> np.ndarray:
    """Diagonal of (A^T A)^-1 [m] for unit residual variance, from the SVD of A with unit-norm columns (so the
    units of the unknowns do not matter); an unknown that a truncated (unobservable) direction touches gets inf."""
    norms = np.linalg.norm(A, axis=0)
    scaled = A / np.where(norms > 0, norms, 1.0)
    _, sv, Vt = np.linalg.svd(scaled, full_matrices=False)
    keep = sv > rcond * sv[0]
    var = ((Vt[keep] / sv[keep, None]) ** 2).sum(0) / np.where(norms > 0, norms, 1.0) ** 2
    touched = (np.abs(Vt[~keep]) > 1e-6).any(0) | (norms == 0)
    return np.where(touched, np.inf, var)


def _tangent_basis(u: np.ndarray) -> np.ndarray:
    """Two unit vectors [3,2] orthogonal to the unit vector u and to each other."""
    e = np.eye(3)[int(np.argmin(np.abs(u)))]
    b1 = np.cross(u, e)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, np.cross(u, b1)])


__all__ = ["Prior", "WindowClip", "WindowFit", "WindowSystem"]
