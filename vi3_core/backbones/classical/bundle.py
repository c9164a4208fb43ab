"""Bundle adjustment of a short clip: Levenberg-Marquardt with analytic Jacobians and a Schur complement.

Minimises the Huber-robust pixel reprojection error over the poses of frames 1..n-1 and the 3D points (frame 0
fixed as the gauge; the free scale gauge is damped by LM and normalised by the caller). A clip has few frames
and at most a few thousand points, so the reduced camera system is a dense [6(n-1)]^2 matrix and every
per-observation block is built at once with einsum.
"""

from __future__ import annotations

import numpy as np

from vi3_core import so3


def _linearise(R_cw, t_cw, X, uv, vis, K, huber_px):
    """Residuals [m,n,2], robust weights [m,n], Jacobians wrt camera [m,n,2,6] and point [m,n,2,3]."""
    Xc = np.einsum("nij,mj->mni", R_cw, X, optimize=True) + t_cw[None]
    z = np.where(vis, Xc[..., 2], 1.0)
    f = np.diag(K)[:2]
    r = np.where(vis[..., None], Xc[..., :2] / z[..., None] * f + K[:2, 2] - np.nan_to_num(uv), 0.0)
    norm = np.linalg.norm(r, axis=-1)
    w = np.where(vis, np.minimum(1.0, huber_px / np.maximum(norm, 1e-12)), 0.0)
    Jp = np.zeros(Xc.shape[:2] + (2, 3))
    Jp[..., 0, 0], Jp[..., 1, 1] = f[0] / z, f[1] / z
    Jp[..., 0, 2], Jp[..., 1, 2] = -f[0] * Xc[..., 0] / z**2, -f[1] * Xc[..., 1] / z**2
    # Left perturbation Xc' = exp(dw) R X + t + dt: dXc/d(dw) = -hat(R X) = -hat(Xc - t), dXc/d(dt) = I.
    Jc = np.concatenate([-Jp @ so3.hat(Xc - t_cw[None]), Jp], axis=-1)
    Jl = Jp @ R_cw[None]
    return r, w, Jc, Jl


def _cost(r, w, huber_px):
    """Huber cost of residuals r [m,n,2] with weights w [m,n] from ``_linearise``."""
    norm = np.linalg.norm(r, axis=-1)
    return float(np.sum(np.where(norm <= huber_px, 0.5 * norm**2, huber_px * (norm - 0.5 * huber_px)) * (w > 0)))


def bundle_adjust(R_wc: np.ndarray, t_wc: np.ndarray, points: np.ndarray, uv: np.ndarray, visible: np.ndarray,
                  K: np.ndarray, *, iterations: int = 20, huber_px: float = 1.0,
                  tol: float = 1e-6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refine camera-to-world poses R_wc [n,3,3], t_wc [n,3] and points [m,3] (NaN rows are left out) against
    the observations uv [m,n,2] (pixels, where ``visible`` [m,n]). Returns the refined (R_wc, t_wc, points)."""
    n = len(R_wc)
    pid = np.flatnonzero(np.isfinite(points[:, 0]))
    X, obs, vis = points[pid].copy(), uv[pid], visible[pid]
    R_cw = np.swapaxes(R_wc, 1, 2).copy()
    t_cw = -(R_cw @ t_wc[..., None])[..., 0]
    lam = 1e-3
    r, w, Jc, Jl = _linearise(R_cw, t_cw, X, obs, vis, K, huber_px)
    cost = _cost(r, w, huber_px)
    for _ in range(iterations):
        Jc[:, 0] = 0.0  # frame 0 is the gauge
        WJc, WJl = w[..., None, None] * Jc, w[..., None, None] * Jl
        Hcc = np.einsum("mnri,mnrj->nij", WJc, Jc, optimize=True)[1:]  # [n-1,6,6]
        Hll = np.einsum("mnri,mnrj->mij", WJl, Jl, optimize=True)  # [m,3,3]
        Hcl = np.einsum("mnri,mnrj->mnij", WJc, Jl, optimize=True)[:, 1:]  # [m,n-1,6,3]
        bc = np.einsum("mnri,mnr->ni", WJc, r, optimize=True)[1:]
        bl = np.einsum("mnri,mnr->mi", WJl, r, optimize=True)
        Hcc_d = Hcc + lam * np.eye(6) * np.diagonal(Hcc, axis1=1, axis2=2)[:, :, None]
        Hll_d = Hll + lam * np.eye(3) * np.diagonal(Hll, axis1=1, axis2=2)[:, :, None] + 1e-9 * np.eye(3)
        Hll_inv = np.linalg.inv(Hll_d)
        Y = Hcl @ Hll_inv[:, None]  # [m,n-1,6,3]
        S = -np.einsum("maij,mbkj->aibk", Y, Hcl, optimize=True)
        S[np.arange(n - 1), :, np.arange(n - 1), :] += Hcc_d
        rhs = -bc + np.einsum("maij,mj->ai", Y, bl, optimize=True)
        dc = np.linalg.solve(S.reshape(6 * (n - 1), -1), rhs.ravel()).reshape(n - 1, 6)
        dl = -np.einsum("mij,mj->mi", Hll_inv, bl + np.einsum("maji,aj->mi", Hcl, dc, optimize=True))
        R_new, t_new = R_cw.copy(), t_cw.copy()
        R_new[1:] = so3.exp(dc[:, :3]) @ R_cw[1:]
        t_new[1:] = t_cw[1:] + dc[:, 3:]
        X_new = X + dl
        lin_new = _linearise(R_new, t_new, X_new, obs, vis, K, huber_px)
        cost_new = _cost(lin_new[0], lin_new[1], huber_px)
        if cost_new < cost:
            done = cost - cost_new < tol * cost
            R_cw, t_cw, X, cost = R_new, t_new, X_new, cost_new
            r, w, Jc, Jl = lin_new
            lam = max(lam / 3.0, 1e-7)
            if done:
                break
        else:
            lam *= 5.0
    R_out = np.swapaxes(R_cw, 1, 2)
    out = np.full_like(points, np.nan)
    out[pid] = X
    return R_out, -(R_out @ t_cw[..., None])[..., 0], out
