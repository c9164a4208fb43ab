"""``GaussianPrior``: what earlier clips (or a restart's surviving estimate) say about the prior vector z
(``layout.PriorLayout``) as a linearised Gaussian, carried to a later body frame and widened by the biases' random
walk; ``sqrt_info``, the square root of an information matrix that keeps every direction."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from vi3_core import so3
from vi3_core.fit.layout import PriorLayout


@dataclass(frozen=True)
class GaussianPrior:
    """A Gaussian on the prior vector z (``PriorLayout``: g, ba, bg and v_0, clip 0's first-frame velocity, in B0),
    linearised at ``center`` [PriorLayout.n]: residual ``sqrt_info @ (z - center) + offset`` [m]. g's radial direction
    carries no information (its norm is fixed). A prior from marginalisation keeps the point it was linearised at as
    its center (its mean may lie far along directions it barely constrains)."""

    center: np.ndarray
    sqrt_info: np.ndarray
    offset: np.ndarray

    def residual(self, z: np.ndarray) -> np.ndarray:
        return self.sqrt_info @ (z - self.center) + self.offset

    def moved(self, R: np.ndarray, phi: np.ndarray) -> GaussianPrior:
        """The same prior for the body frame B0' = B(t') with R = R_B0B0' preintegrated with the center's gyro bias and
        phi [3,3] its bias Jacobian (R(bg + d) = Exp(phi d) R): g' = R^T g and v' = R^T v, linearised at the center (a
        later bias estimate also turns them, as it turns the IMU between t0 and t')."""
        Z = PriorLayout
        g, v = self.center[Z.g], self.center[Z.v]
        T = np.eye(Z.n)  # dz' / dz at the center
        T[Z.g, Z.g] = T[Z.v, Z.v] = R.T
        T[Z.g, Z.bg] = R.T @ so3.hat(g) @ phi
        T[Z.v, Z.bg] = R.T @ so3.hat(v) @ phi
        center = self.center.copy()
        center[Z.g], center[Z.v] = R.T @ g, R.T @ v
        return GaussianPrior(center, self.sqrt_info @ np.linalg.inv(T), self.offset)

    def widened(self, ba_var: float, bg_var: float, g_var: float = 0.0, v_var: float = 0.0) -> GaussianPrior:
        """The prior with ``ba_var`` ((m/s^2)^2) and ``bg_var`` ((rad/s)^2) added to the biases' variance per axis
        (their random walk over the time the prior is carried), and ``g_var`` ((m/s^2)^2), ``v_var`` ((m/s)^2) to
        gravity's and the velocity's (the attitude error of the frame it is carried into); its mean stays where it
        was.

        In square-root information form, as a square-root information filter adds process noise Q: with
        A = S Q^1/2 and L L^T = I + A A^T, S' = L^-1 S, so that S'^T S' = S^T (I + A A^T)^-1 S = ((S^T S)^-1 + Q)^-1
        (Woodbury) where S^T S is invertible, and directions S leaves free (g's radial one) stay free. Inverting the
        information to a covariance and back amplified its round-off: on a generated sequence the pseudo-inverse
        of a covariance with a 1e-18 negative eigenvalue gave an information of -1e18 and the window's fit failed."""
        q = np.zeros(PriorLayout.n)
        q[PriorLayout.ba], q[PriorLayout.bg] = ba_var, bg_var
        q[PriorLayout.g], q[PriorLayout.v] = g_var, v_var
        A = self.sqrt_info * np.sqrt(q)
        L = np.linalg.cholesky(np.eye(len(A)) + A @ A.T)
        S = scipy.linalg.solve_triangular(L, self.sqrt_info, lower=True)
        # mean - center = -S^+ offset; the widened residual there keeps the same mean: S' (center - mean).
        return GaussianPrior(self.center, S, S @ np.linalg.lstsq(self.sqrt_info, self.offset, rcond=None)[0])


def sqrt_of_info(info
: np.ndarray) -> np.ndarray:
    """S [m,m] with S^T S = info [m,m] (symmetric PSD), from the eigen-decomposition after scaling each unknown to unit
    diagonal (so that the units of the unknowns do not matter); round-off's negative eigenvalues count as zero.

    Every direction is kept, however weak: a cut-off (directions below 1e-12 of the largest dropped) made the prior
    jump wherever an eigenvalue crossed it, and on the real EuRoC IMU a 1e-13 relative change of the accelerometer
    samples then moved the window's scale by 4 % and cascaded into confident wrong scales."""
    d = unit_diagonal_scale(info)
    w, V = np.linalg.eigh(info / np.outer(d, d))
    return (V * np.sqrt(np.maximum(w, 0.0))).T * d


def unit_diagonal_scale(info: np.ndarray) -> np.ndarray:
    """d [m] such that info / outer(d, d) has a unit diagonal (info [m,m] symmetric PSD): the square roots of the
    diagonal, each at least that of 1e-24 of the largest. An unknown with no information but round-off in its row
    (1e-18 against a zero diagonal) was scaled up by 1e150 with an absolute floor (1e-300), and ``sqrt_of_info``
    returned an information of 1e131 for it."""
    diag = np.diag(info)
    return np.sqrt(np.maximum(diag, max(1e-24 * diag.max(), 1e-300)))


__all__ = ["GaussianPrior", "sqrt_of_info", "unit_diagonal_scale"]

