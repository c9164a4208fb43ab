"""IMU preintegration between arbitrary frame stamps (paper Sec. "Preintegration and state propagation").

Everything is expressed in the body frame at the first stamp, B1, with origin at that stamp. For bias
estimates ``bg``, ``ba`` the module integrates, from t_1 to every stamp t_i:

    R_i     = R_B1Bi                          (Eq. preintegrationRotation, chained from t_1)
    beta_i  = int_{t_1}^{t_i} R(t) (a(t) - ba) dt           gravity-free velocity change, in B1
    alpha_i = int_{t_1}^{t_i} beta(t) dt                    gravity-free position change, in B1

so that, given gravity g and the velocity v1 (both in B1), the states are (Eqs. preintegrationVelocity /
preintegrationTranslation summed from the first frame):

    v_i = v1 + g tau_i + beta_i,     p_i = v1 tau_i + 0.5 g tau_i^2 + alpha_i,     tau_i = t_i - t_1.

Integration scheme: the IMU stream is linearly interpolated at the frame stamps (which fall between
samples) and merged with the samples strictly inside [t_1, t_n]. On each sub-interval the rotation uses
the midpoint rate ((w_k + w_{k+1}) / 2 - bg) and the specific force rotated into B1 is treated as linear in
time (trapezoidal velocity, exact double integral of the linear force for position). This is second order
in the sample period, so noise-free preintegration reproduces analytic motion to ~1e-6 relative. The
rotation chain is a parallel prefix product (log2(M) batched matmuls), so nothing loops per sample.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from vi3_core import so3
from vi3_core.types import ImuSamples, ImuTrajectory


def cumulative_rotations(dR: np.ndarray) -> np.ndarray:
    """[K,3,3] increments -> [K+1,3,3] prefix products R_0 = I, R_k = dR_0 @ ... @ dR_{k-1}."""
    out = np.empty((len(dR) + 1, 3, 3))
    out[0], out[1:] = np.eye(3), dR
    P = out[1:]
    shift = 1
    while shift < len(P):
        P[shift:] = P[:-shift] @ P[shift:]  # right side is evaluated first: a Hillis-Steele scan step
        shift *= 2
    return out


@dataclass(frozen=True)
class Grid:
    """The integration grid: t [K] s, gyro [K,3], accel [K,3] on it, frame_idx [n] positions of the stamps; what
    does not depend on a bias estimate is computed once per grid (the properties)."""

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    frame_idx: np.ndarray

    @cached_property
    def dt(self) -> np.ndarray:
        """[K-1] s, the grid intervals."""
        return np.diff(self.t)

    @cached_property
    def mid_gyro(self) -> np.ndarray:
        """[K-1,3] rad/s, the raw gyro at each interval's midpoint (w_k + w_{k+1}) / 2."""
        return 0.5 * (self.gyro[:-1] + self.gyro[1:])

    @cached_property
    def gyro_mean(self) -> np.ndarray:
        """[n-1,3] rad/s, the time average of the raw gyro over each frame interval (trapezoidal)."""
        w_int = np.concatenate([np.zeros((1, 3)), np.cumsum(self.mid_gyro * self.dt[:, None], 0)])
        fi = self.frame_idx
        return np.diff(w_int[fi], axis=0) / np.diff(self.t[fi])[:, None]

    @cached_property
    def frame_steps(self) -> tuple[np.ndarray, np.ndarray]:
        """Each frame interval's steps padded to a power-of-two width w: (index [n-1,w] into the K-1 steps, pad
        [n-1,w] True where an identity fills in), for ``frame_rotations``."""
        fi = self.frame_idx
        count = np.diff(fi)
        k = np.arange(1 << int(count.max() - 1).bit_length())
        return np.minimum(fi[:-1, None] + k, len(self.t) - 2), k >= count[:, None]


def merged_grid(imu: ImuSamples, stamps: np.ndarray) -> Grid:
    """Frame stamps merged with the IMU stamps strictly between them, and the IMU interpolated on that grid."""
    stamps = np.asarray(stamps, dtype=np.float64)
    inside = imu.t[(imu.t > stamps[0]) & (imu.t < stamps[-1])]
    inside = inside[stamps[np.searchsorted(stamps, inside)] != inside]  # not a stamp itself (stamps are sorted)
    t = np.sort(np.concatenate([stamps, inside]), kind="stable")
    gyro = np.stack([np.interp(t, imu.t, imu.gyro[:, a]) for a in range(3)], -1)
    accel = np.stack([np.interp(t, imu.t, imu.accel[:, a]) for a in range(3)], -1)
    return Grid(t, gyro, accel, np.searchsorted(t, stamps))


@dataclass(frozen=True)
class BiasJacobians:
    """First-order effect of bias changes on the preintegration at the n stamps, each [n,3,3].

    phi_bg: rad per rad/s, R_B1Bi(bg + d) = Exp(phi_bg d) R_B1Bi(bg) (a rotation in B1); beta_bg, alpha_bg: m/s and m
    per rad/s (the specific force turned by that rotation, integrated once and twice); beta_ba, alpha_ba: s and s^2,
    exact for any ba (the force is R (a - ba), linear in ba).
    """

    phi_bg: np.ndarray
    beta_bg: np.ndarray
    alpha_bg: np.ndarray
    beta_ba: np.ndarray
    alpha_ba: np.ndarray


@dataclass(frozen=True)
class Preintegration:
    """Preintegrated IMU at n stamps, in B1 (see the module docstring).

    stamps, tau: [n] s; R: [n,3,3] R_B1Bi; beta: [n,3] m/s; alpha: [n,3] m; gyro_mean: [n-1,3] rad/s time
    average of the raw gyro over each frame interval; bg, ba: [3] the biases used; J: the bias Jacobians when asked.
    """

    stamps: np.ndarray
    tau: np.ndarray
    R: np.ndarray
    beta: np.ndarray
    alpha: np.ndarray
    gyro_mean: np.ndarray
    bg: np.ndarray
    ba: np.ndarray
    J: BiasJacobians | None = None

    def corrected(self, bg: np.ndarray, ba: np.ndarray) -> Preintegration:
        """The preintegration for biases (bg, ba) near the ones used, to first order through ``J`` (Forster et al.'s
        bias update; exact in ba, error O(|bg - self.bg|^2) in bg); requires ``jacobians=True``."""
        if self.J is None:
            raise ValueError("Preintegration.corrected needs the bias Jacobians (preintegrate(..., jacobians=True))")
        J, dbg, dba = self.J, np.asarray(bg, np.float64) - self.bg, np.asarray(ba, np.float64) - self.ba
        return Preintegration(stamps=self.stamps, tau=self.tau, R=so3.exp(J.phi_bg @ dbg) @ self.R,
                              beta=self.beta + J.beta_bg @ dbg + J.beta_ba @ dba,
                              alpha=self.alpha + J.alpha_bg @ dbg + J.alpha_ba @ dba, gyro_mean=self.gyro_mean,
                              bg=self.bg + dbg, ba=self.ba + dba, J=J)

    def propagate(self, g: np.ndarray, v1: np.ndarray, T_BC: np.ndarray | None = None) -> ImuTrajectory:
        """Metric states at the stamps for gravity g [3] and first-frame velocity v1 [3], both in B1.

        Camera poses are T_C1Ci = T_CB T_B1Bi T_BC (DESIGN.md): the lever arm of T_BC is metric.
        """
        g, v1 = np.asarray(g, dtype=np.float64), np.asarray(v1, dtype=np.float64)
        tau = self.tau[:, None]
        p = v1 * tau + 0.5 * g * tau**2 + self.alpha
        v = v1 + g * tau + self.beta
        T_B = so3.make_T(self.R, p)
        T_BC = np.eye(4) if T_BC is None else np.asarray(T_BC, dtype=np.float64)
        T_wc = so3.inv_T(T_BC) @ T_B @ T_BC
        return ImuTrajectory(R=self.R, p=p, v=v, T_wc=T_wc)


def _rotation_steps(grid: Grid, bg: np.ndarray) -> np.ndarray:
    """[K-1,3,3] the rotation over each grid interval with the midpoint rate (w_k + w_{k+1}) / 2 - bg."""
    return so3.exp((grid.mid_gyro - bg) * grid.dt[:, None])


def integrate_rotations(grid: Grid, bg: np.ndarray) -> np.ndarray:
    """R_B1B(t) [K,3,3] on the grid with the midpoint rate (w_k + w_{k+1}) / 2 - bg."""
    return cumulative_rotations(_rotation_steps(grid, bg))


def frame_rotations(grid: Grid, bg: np.ndarray) -> np.ndarray:
    """R_B1Bi [n,3,3] at the frames only: ``integrate_rotations(grid, bg)[grid.frame_idx]`` up to round-off, at a
    fraction of its cost. Each frame interval's steps are multiplied pairwise in a tree (padded with identities to a
    power of two), then the n-1 interval rotations are chained."""
    index, pad = grid.frame_steps
    P = _rotation_steps(grid, bg)[index]  # [n-1, width, 3, 3]
    P[pad] = np.eye(3)
    while P.shape[1] > 1:
        P = P[:, 0::2] @ P[:, 1::2]
    return cumulative_rotations(P[:, 0])


def preintegrate(imu: ImuSamples, stamps: np.ndarray, bg: np.ndarray, ba: np.ndarray | None = None, *,
                 grid: Grid | None = None, jacobians: bool = False) -> Preintegration:
    """Preintegrate ``imu`` from stamps[0] to every stamp (see the module docstring for the scheme).

    imu must cover [stamps[0], stamps[-1]] (validated by the caller); stamps [n] strictly increasing, s.
    ``grid`` (from ``merged_grid(imu, stamps)``) may be passed to reuse it across bias estimates; ``jacobians`` adds
    the bias Jacobians (``BiasJacobians``) from the same pass.
    """
    stamps = np.asarray(stamps, dtype=np.float64)
    bg = np.asarray(bg, dtype=np.float64)
    ba = np.zeros(3) if ba is None else np.asarray(ba, dtype=np.float64)
    grid = grid or merged_grid(imu, stamps)
    dt = grid.dt
    R = integrate_rotations(grid, bg)
    force = np.einsum("kij,kj->ki", R, grid.accel - ba)
    beta, alpha = _integrate_force(force, dt)
    fi = grid.frame_idx
    J = None
    if jacobians:
        # A bias change d turns every step by -d dt in its own frame, i.e. by about -R d dt in B1 (R at the step's
        # midpoint): the rotations gain Exp(phi_k d) on the left, phi_k = -sum_(j<k) (R_j + R_(j+1)) / 2 dt_j, and the
        # force f_k gains -hat(f_k) phi_k d.
        phi = np.concatenate([np.zeros((1, 3, 3)), np.cumsum(-0.5 * (R[:-1] + R[1:]) * dt[:, None, None], axis=0)])
        beta_bg, alpha_bg = _integrate_force(-so3.hat(force) @ phi, dt)
        beta_ba, alpha_ba = _integrate_force(-R, dt)
        J = BiasJacobians(phi[fi], beta_bg[fi], alpha_bg[fi], beta_ba[fi], alpha_ba[fi])
    return Preintegration(stamps=stamps, tau=stamps - stamps[0], R=R[fi], beta=beta[fi], alpha=alpha[fi],
                          gyro_mean=grid.gyro_mean, bg=bg, ba=ba, J=J)


def _integrate_force(f: np.ndarray, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """beta, alpha [K,...] on the grid from the force in B1, f [K,...] (linear in time on each of the K-1
    intervals dt): trapezoidal velocity, exact double integral for position."""
    dt = dt.reshape(-1, *([1] * (f.ndim - 1)))
    dbeta = 0.5 * (f[:-1] + f[1:]) * dt
    beta = np.concatenate([np.zeros_like(f[:1]), np.cumsum(dbeta, axis=0)])
    dalpha = beta[:-1] * dt + (2.0 * f[:-1] + f[1:]) * (dt**2 / 6.0)
    return beta, np.concatenate([np.zeros_like(f[:1]), np.cumsum(dalpha, axis=0)])
