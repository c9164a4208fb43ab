"""Bundle adjustment of a short clip: Levenberg-Marquardt with analytic Jacobians and a Schur complement.

Minimises the Huber-robust pixel reprojection error over the poses of frames 1..n-1 and the 3D points (frame 0
fixed as the gauge; the free scale gauge is damped by LM and normalised by the caller), with the gyro's rotations,
where given, as a prior on every frame's rotation up to a correction of the gyro bias within its estimate's sigma
(``GyroRotations``). Over a short clip that mostly turns, the images alone trade translation for rotation below what
a gyro check sees (on a handheld render the trajectory's scale came out a median 18 % short of the depth's, by up to
80 %); a bias left free per clip would give it back, being a rotation that grows with time. A clip has few frames
and at most a few thousand points, so the reduced camera system is a dense [6(n-1)]^2 matrix (3 rows and columns more
with the prior, the bias correction's) and every per-observation block is built at once. The arithmetic runs in
torch (float64) so that its matrix products use torch's intra-op thread setting rather than a BLAS thread pool of
their own.
"""

from __future__ import annotations

import numpy as np
import torch

from vi3_core import so3
from vi3_core.backbones.base import GyroRotations


def _residuals(R_cw, t_cw, X, uv, vis, K):
    """Camera-frame points Xc [m,n,3], safe depths z [m,n] (1 where unseen) and residuals r [m,n,2] (0 where
    unseen) of points X [m,3] in cameras R_cw [n,3,3], t_cw [n,3] against pixels uv [m,n,2]."""
    Xc = torch.einsum("nij,mj->mni", R_cw, X) + t_cw
    z = torch.where(vis, Xc[..., 2], 1.0)
    r = torch.where(vis[..., None], Xc[..., :2] / z[..., None] * K.diagonal()[:2] + K[:2, 2] - uv, 0.0)
    return Xc, z, r


def _cost(r, vis, huber_px):
    """Huber cost of residuals r [m,n,2] over the observations ``vis`` [m,n]."""
    norm = r.norm(dim=-1)
    return float((torch.where(norm <= huber_px, 0.5 * norm**2, huber_px * (norm - 0.5 * huber_px)) * vis).sum())


class _GyroPrior:
    """The rotation prior: for frames 1..n-1 the residual e_i = Log(R_cw_i Exp(A_i d) R_wc_i^gyro) of the
    rotations against the gyro's at a bias correction d [3] rad/s, weighted by w_i = 1 / (sigma^2 + clock_sigma_i^2)
    (rad), and d itself by w_bias = 1 / bg_sigma^2."""

    def __init__(self, gyro: GyroRotations, sigma: float) -> None:
        self.R_wc, self.A = gyro.R_wc[1:], gyro.bias_jacobian[1:]
        self.w = 1.0 / (sigma**2 + gyro.clock_sigma[1:] ** 2)
        self.w_bias = 1.0 / gyro.bg_sigma**2

    def residual(self, R_cw: torch.Tensor, d: np.ndarray) -> np.ndarray:
        """e [n-1,3] rad at the rotations R_cw [n,3,3] and bias correction d [3]."""
        return so3.log(R_cw[1:].numpy() @ so3.exp(self.A @ d) @ self.R_wc)

    def cost(self, R_cw: torch.Tensor, d: np.ndarray) -> float:
        """The prior's share of the bundle adjustment's cost."""
        return 0.5 * (float(self.w @ (self.residual(R_cw, d) ** 2).sum(1)) + self.w_bias * float(d @ d))


def _inv3(A: torch.Tensor) -> torch.Tensor:
    """Inverses [...,3,3] of invertible 3x3 matrices A [...,3,3] by the adjugate (elementwise, no LAPACK call)."""
    c0 = torch.linalg.cross(A[..., 1, :], A[..., 2, :])
    c1 = torch.linalg.cross(A[..., 2, :], A[..., 0, :])
    c2 = torch.linalg.cross(A[..., 0, :], A[..., 1, :])
    det = (A[..., 0, :] * c0).sum(-1)
    return torch.stack([c0, c1, c2], -1) / det[..., None, None]


def bundle_adjust(R_wc: np.ndarray, t_wc: np.ndarray, points: np.ndarray, uv: np.ndarray, visible: np.ndarray,
                  K: np.ndarray, *, iterations: int = 20, huber_px: float = 1.0, tol: float = 1e-4,
                  gyro: GyroRotations | None = None,
                  gyro_sigma: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Refine camera-to-world poses R_wc [n,3,3], t_wc [n,3] and points [m,3] (NaN rows are left out) against
    the observations uv [m,n,2] (pixels, where ``visible`` [m,n]), with ``gyro`` (its R_wc in the same world, the first
    camera) a prior of ``gyro_sigma`` rad on each rotation where given and gyro_sigma > 0. Returns the refined
    (R_wc, t_wc, points) and the gyro bias (rad/s) the rotations fit (None without the prior)."""
    n = len(R_wc)
    pid = np.flatnonzero(np.isfinite(points[:, 0]))
    f64 = torch.float64
    X = torch.as_tensor(points[pid], dtype=f64)
    obs = torch.as_tensor(np.nan_to_num(uv[pid]), dtype=f64)
    vis = torch.as_tensor(visible[pid])
    K_t = torch.as_tensor(K, dtype=f64)
    fx, fy = float(K[0, 0]), float(K[1, 1])
    R_cw = torch.as_tensor(R_wc, dtype=f64).transpose(1, 2).contiguous()
    t_cw = -(R_cw @ torch.as_tensor(t_wc, dtype=f64)[..., None])[..., 0]
    eye6, eye3 = torch.eye(6, dtype=f64), torch.eye(3, dtype=f64)
    prior = _GyroPrior(gyro, gyro_sigma) if gyro is not None and gyro_sigma > 0 and n > 1 else None
    d = np.zeros(3)
    nb = 3 if prior is not None else 0  # the bias correction's unknowns, after the cameras'
    lam = 1e-3
    Xc, z, r = _residuals(R_cw, t_cw, X, obs, vis, K_t)
    cost = _cost(r, vis, huber_px) + (prior.cost(R_cw, d) if prior else 0.0)
    linearise = True
    for _ in range(iterations):
        if linearise:
            # Huber weights; Jacobians: Jp = d(pixel)/d(Xc) [m,n,2,3]; left perturbation Xc' = exp(dw) R X + t + dt
            # gives d/d(dw) = -Jp hat(R X) (row-wise (R X) x Jp) and d/d(dt) = Jp; d/dX = Jp R.
            w = torch.where(vis, (huber_px / r.norm(dim=-1).clamp_min(1e-12)).clamp_max(1.0), 0.0)
            Jp = torch.zeros(Xc.shape[:2] + (2, 3), dtype=f64)
            Jp[..., 0, 0], Jp[..., 1, 1] = fx / z, fy / z
            Jp[..., 0, 2], Jp[..., 1, 2] = -fx * Xc[..., 0] / z**2, -fy * Xc[..., 1] / z**2
            Jc = torch.cat([torch.linalg.cross((Xc - t_cw)[..., None, :].expand_as(Jp), Jp), Jp], -1)
            Jc[:, 0] = 0.0  # frame 0 is the gauge
            Jl = torch.einsum("mnri,nij->mnrj", Jp, R_cw)
            WJc, WJl = w[..., None, None] * Jc, w[..., None, None] * Jl
            Hcc = torch.einsum("mnri,mnrj->nij", WJc, Jc)[1:]  # [n-1,6,6]
            Hll = torch.einsum("mnri,mnrj->mij", WJl, Jl)  # [m,3,3]
            # Sums of outer products over the two residual rows, written out (batched 6x2 @ 2x3 products are slow).
            Hcl = torch.addcmul(WJc[:, 1:, 0, :, None] * Jl[:, 1:, 0, None, :], WJc[:, 1:, 1, :, None],
                                Jl[:, 1:, 1, None, :])  # [m,n-1,6,3]
            bc = torch.einsum("mnri,mnr->ni", WJc, r)[1:]
            bl = torch.einsum("mnri,mnr->mi", WJl, r)
            if prior is not None:  # d e_i / d(dw_i) = I, d e_i / d d = R_cw_i A_i (first order)
                e, wp = torch.from_numpy(prior.residual(R_cw, d)), torch.from_numpy(prior.w)
                B = R_cw[1:] @ torch.from_numpy(prior.A)
                Hcc[:, :3, :3] += wp[:, None, None] * eye3
                bc[:, :3] += wp[:, None] * e
                Hcb = torch.zeros(n - 1, 6, 3, dtype=f64)
                Hcb[:, :3] = wp[:, None, None] * B
                Hbb = torch.einsum("n,nji,njk->ik", wp, B, B) + prior.w_bias * eye3
                bb = torch.einsum("n,nji,nj->i", wp, B, e) + prior.w_bias * torch.from_numpy(d)
        diag = Hcc.diagonal(dim1=1, dim2=2)[:, :, None]
        # a camera no point constrains any more (a long clip's frame whose points were all cleaned out) stays put
        Hcc_d = Hcc + lam * eye6 * diag + eye6 * (diag == 0)
        Hll_inv = _inv3(Hll + lam * eye3 * Hll.diagonal(dim1=1, dim2=2)[:, :, None] + 1e-9 * eye3)
        Y = torch.bmm(Hcl.reshape(len(Hcl), -1, 3), Hll_inv).view(Hcl.shape)  # Hcl Hll^-1 [m,n-1,6,3]
        # Schur complement S = Hcc - sum_m Y_m Hcl_m^T as one matrix product over (point, point coordinate).
        S = -(Y.permute(1, 2, 0, 3).reshape(6 * (n - 1), -1) @ Hcl.permute(1, 2, 0, 3).reshape(6 * (n - 1), -1).T)
        S = S.view(n - 1, 6, n - 1, 6)
        S[torch.arange(n - 1), :, torch.arange(n - 1), :] += Hcc_d
        rhs = (-bc + torch.einsum("maij,mj->ai", Y, bl)).reshape(-1)
        if prior is not None:  # the bias correction joins the reduced system: no point depends on it
            M = torch.zeros(6 * (n - 1) + nb, 6 * (n - 1) + nb, dtype=f64)
            M[:-nb, :-nb] = S.reshape(6 * (n - 1), -1)
            M[:-nb, -nb:] = Hcb.reshape(-1, nb)
            M[-nb:, :-nb] = Hcb.reshape(-1, nb).T
            M[-nb:, -nb:] = Hbb + lam * torch.diag(Hbb.diagonal())
            rhs = torch.cat([rhs, -bb])
            sol = torch.linalg.solve(M, rhs)
            dc, dd = sol[:-nb].reshape(n - 1, 6), sol[-nb:].numpy()
        else:
            dc, dd = torch.linalg.solve(S.reshape(6 * (n - 1), -1), rhs).reshape(n - 1, 6), None
        dl = -torch.einsum("mij,mj->mi", Hll_inv, bl + torch.einsum("maji,aj->mi", Hcl, dc))
        R_new, t_new = R_cw.clone(), t_cw.clone()
        R_new[1:] = torch.from_numpy(so3.exp(dc[:, :3].numpy())) @ R_cw[1:]
        t_new[1:] = t_cw[1:] + dc[:, 3:]
        X_new = X + dl
        d_new = d + dd if prior is not None else d
        Xc_new, z_new, r_new = _residuals(R_new, t_new, X_new, obs, vis, K_t)
        cost_new = _cost(r_new, vis, huber_px) + (prior.cost(R_new, d_new) if prior else 0.0)
        linearise = cost_new < cost
        if linearise:
            done = cost - cost_new < tol * cost
            R_cw, t_cw, X, cost, Xc, z, r, d = R_new, t_new, X_new, cost_new, Xc_new, z_new, r_new, d_new
            lam = max(lam / 3.0, 1e-7)
            if done:
                break
        else:
            lam *= 5.0
    R_out = R_cw.transpose(1, 2)
    out = np.full_like(points, np.nan)
    out[pid] = X.numpy()
    bias = gyro.bg + d if prior is not None else None
    return R_out.numpy(), (-(R_out @ t_cw[..., None])[..., 0]).numpy(), out, bias
