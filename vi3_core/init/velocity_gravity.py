"""Scale s, gravity g and first-frame velocity v1 from backbone positions and preintegrated IMU
(paper Eqs. S, v0, resid, gls and the fixed point s = S(g), g = g_ls(s)).

Like with like: finite differences of positions are interval-average velocities. For frame interval
i = [t_i, t_{i+1}] with length dT_i and midpoint time c_i (from t_1), body positions p = s a + b give

    s abar_i + bbar_i = v1 + g c_i + dbar_i,

where abar_i = (a_{i+1} - a_i) / dT_i comes from the backbone (a_i = R_BC p^M_i, up to scale), bbar_i from
the metric lever arm b_i = (I - R_B1Bi) t_BC (never scaled), and dbar_i = (alpha_{i+1} - alpha_i) / dT_i from
the preintegrated IMU. The half-interval gravity term (g c_i instead of g t_i) and dbar_i are exactly what
an interval-average velocity carries, so with noise-free data the solution is exact.

Differences of consecutive intervals eliminate v1 and give Eq. S's stacked increments:
    s V^M = V(g),   V^M_k = abar_{k+1} - abar_k,   V_k(g) = g (c_{k+1} - c_k) + W_k,
    W_k = (dbar_{k+1} - dbar_k) - (bbar_{k+1} - bbar_k).
All pairs i < j give Eq. resid: r_ij = s (abar_j - abar_i) + Q_ij = g (c_j - c_i). Both are reduced to a
few 3-vectors once, so each fixed-point iteration costs O(1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vi3_core.preintegration import Preintegration


@dataclass(frozen=True)
class FixedPoint:
    """Result of FP(g_seed): gravity g [3] in B1, scale s, iterations used, convergence and anti-alignment."""

    g: np.ndarray
    s: float
    iterations: int
    converged: bool
    anti_aligned: bool


class ScaleGravitySystem:
    """The linear relations above for one clip.

    a: [n,3] R_BC p^M_i (backbone camera positions rotated into the body axes, model units);
    b: [n,3] lever-arm term (I - R_B1Bi) t_BC in metres; pre: preintegration at the n stamps.
    """

    def __init__(self, a: np.ndarray, b: np.ndarray, pre: Preintegration, *, gravity_norm: float) -> None:
        dT = np.diff(pre.tau)
        self.gravity_norm = gravity_norm
        self.c = 0.5 * (pre.tau[:-1] + pre.tau[1:])
        self.abar = np.diff(a, axis=0) / dT[:, None]
        self.bbar = np.diff(b, axis=0) / dT[:, None]
        self.dbar = np.diff(pre.alpha, axis=0) / dT[:, None]
        # Eq. S increments.
        self.VM = np.diff(self.abar, axis=0)
        self.dc = np.diff(self.c)
        self.W_body = np.diff(self.dbar, axis=0)
        self.W = self.W_body - np.diff(self.bbar, axis=0)
        # The reductions are kept as Python floats and 3-tuples: the fixed point evaluates S and g_ls tens of
        # times per clip, where numpy's per-call overhead would dominate these 3-vector operations.
        self._A = float(self.dc @ self.dc)
        self._u = tuple(map(float, self.dc @ self.W))
        self._w2 = float((self.W * self.W).sum())
        self._q = tuple(map(float, self.dc @ self.VM))
        self._r = float((self.W * self.VM).sum())
        self._m2 = float((self.VM * self.VM).sum())
        # Eq. gls over all interval pairs: n(s) = s P_hat + Q_hat.
        i, j = np.triu_indices(len(self.c), k=1)
        dt = (self.c[j] - self.c[i])[:, None]
        Q = (self.bbar[j] - self.bbar[i]) - (self.dbar[j] - self.dbar[i])
        denom = float((dt**2).sum())
        self._P_hat = tuple(map(float, (dt * (self.abar[j] - self.abar[i])).sum(0) / denom))
        self._Q_hat = tuple(map(float, (dt * Q).sum(0) / denom))

    @property
    def visual_signal(self) -> float:
        """|V^M|: norm of the backbone's velocity increments (model units / s)."""
        return math.sqrt(self._m2)

    def inner(self, g) -> float:
        """<V(g), V^M> for a gravity g (any 3-sequence)."""
        return _dot(g, self._q) + self._r

    def inertial_norm(self, g) -> float:
        """|V(g)| in m/s."""
        return math.sqrt(max(_dot(g, g) * self._A + 2.0 * _dot(g, self._u) + self._w2, 0.0))

    def scale(self, g, solver: str = "tls") -> float:
        """S(g). TLS (Eq. S): sign(<V, V^M>) |V| / |V^M|; OLS: <V, V^M> / |V^M|^2 (ablation)."""
        if self._m2 <= 0.0:
            return float("nan")
        if solver == "ols":
            return self.inner(g) / self._m2
        return math.copysign(self.inertial_norm(g) / math.sqrt(self._m2), self.inner(g))

    def alignment(self, g: np.ndarray) -> float:
        """cos of the angle between V(g) and V^M (1 = visual and inertial motion agree)."""
        den = self.inertial_norm(g) * math.sqrt(self._m2)
        return self.inner(g) / den if den > 0 else 0.0

    def accel_rms(self, g: np.ndarray) -> float:
        """RMS of the body's gravity-free acceleration between interval midpoints, m/s^2 (the lever arm's
        centripetal part is excluded: a camera swinging on a rotating body does not make scale observable)."""
        V = g * self.dc[:, None] + self.W_body
        return float(np.sqrt(((V / self.dc[:, None]) ** 2).sum(1).mean()))

    def _g_ls(self, s: float) -> tuple[float, float, float]:
        P, Q = self._P_hat, self._Q_hat
        n = (s * P[0] + Q[0], s * P[1] + Q[1], s * P[2] + Q[2])
        k = self.gravity_norm / math.sqrt(_dot(n, n))
        return (n[0] * k, n[1] * k, n[2] * k)

    def gravity_ls(self, s: float) -> np.ndarray:
        """g_ls(s), Eq. gls: |g| fixed to the gravity norm, direction of sum dt_ij r_ij / sum dt_ij^2."""
        return np.array(self._g_ls(s))

    def fixed_point(self, g_seed: np.ndarray, *, solver: str, tol_deg: float, max_iters: int,
                    accelerate: bool = True) -> FixedPoint:
        """FP(g_seed): the limit of s^(k+1) = S(g^(k)), g^(k+1) = g_ls(s^(k+1)), stopped when the gravity
        moves less than ``tol_deg``; ``max_iters`` caps the evaluations of S(g_ls(.)).

        The seed enters only through s^(1) = S(g_seed), after which this is the scalar iteration s -> F(s) =
        S(g_ls(s)). It contracts slowly when the clip's acceleration is weak (factors of 0.65 to 0.999 were seen
        on EuRoC-like motion), so ``accelerate`` applies Steffensen's method to the same F: same fixed point,
        quadratic convergence. An anti-aligned S (negative) falls back to s = 1 as in the paper and is reported.
        """
        G = self.gravity_norm
        if self._m2 <= 0.0:  # the backbone predicts no change of velocity: S is undefined
            g0 = G * np.asarray(g_seed, dtype=np.float64) / np.linalg.norm(g_seed)
            return FixedPoint(g0, float("nan"), 0, False, False)
        anti = False

        def S(g: tuple) -> float:
            nonlocal anti
            val = self.scale(g, solver)
            if not val > 0.0:
                anti = True
                return 1.0
            return val

        g_ls = self._g_ls
        norm0 = math.sqrt(sum(float(x) ** 2 for x in g_seed))
        s = S(tuple(G * float(x) / norm0 for x in g_seed))
        g = g_ls(s)
        chord_tol = 2.0 * math.sin(math.radians(tol_deg) / 2.0) * G
        evals, converged = 1, False
        while evals < max_iters:
            if accelerate and evals + 2 <= max_iters:
                s1 = S(g)
                s2 = S(g_ls(s1))
                evals += 2
                d = s2 - 2.0 * s1 + s
                s_new = s - (s1 - s) ** 2 / d if d != 0.0 else s2
                if not s_new > 0.0 or not math.isfinite(s_new):
                    s_new = s2
            else:
                s_new = S(g)
                evals += 1
            g_new = g_ls(s_new)
            moved = math.dist(g, g_new)
            s, g = s_new, g_new
            if moved < chord_tol:
                converged = True
                break
        g_arr = np.array(g)
        return FixedPoint(g_arr, self.scale(g_arr, solver), evals, converged, anti)

    def v1_candidates(self, s: float, g: np.ndarray) -> np.ndarray:
        """Back-projection of every interval's velocity to the first frame: [n-1,3] in B1, m/s."""
        return s * self.abar + self.bbar - np.outer(self.c, g) - self.dbar

    def initial_velocity(self, s: float, g: np.ndarray, method: str = "all_pairs") -> tuple[np.ndarray, str]:
        """v1 (Eq. v0): direction of the gravity-free first pair, magnitude mu = median projection of all
        back-projected intervals; reverts to the first pair when mu <= 0. Returns (v1 [3], how)."""
        cand = self.v1_candidates(s, g)
        first = cand[0]
        if method == "first_pair":
            return first, "first_pair"
        norm = np.linalg.norm(first)
        if norm == 0.0:
            return first, "first_pair (zero first-pair velocity)"
        direction = first / norm
        mu = float(np.median(cand @ direction))
        if mu <= 0.0:
            return first, "first_pair (median projection <= 0)"
        return mu * direction, "all_pairs"


def _dot(a, b) -> float:
    return float(a[0]) * b[0] + float(a[1]) * b[1] + float(a[2]) * b[2]
