"""Bundle adjustment of a short clip: Levenberg-Marquardt with analytic Jacobians and a Schur complement.

Minimises the Huber-robust pixel reprojection error over the poses of frames 1..n-1 and the 3D points (frame 0
fixed as the gauge; the free scale gauge is damped by LM and normalised by the caller), and says how well the result
fixes its trajectory's scale against its depth's (``_trajectory_depth_sigma``), with the gyro's rotations,
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

import math
from typing import NamedTuple

import numpy as np
import torch

from vi3_core import so3
from vi3_core.backbones.base import GyroRotations


class Adjusted(NamedTuple):
    """``bundle_adjust``'s result: R_wc [n,3,3], t_wc [n,3] camera-to-world, points [m,3] (NaN: left out), the gyro
    bias [3] rad/s the rotations fit (None without the prior), ``traj_depth_sigma``, the 1-sigma of the log of
    the trajectory's scale against the depth's (``_trajectory_depth_sigma``; NaN: not computed) and, with held
    cameras, ``held_scale_sigma``, the 1-sigma of the log of the clip's scale against theirs (``_held_scale_sigma``;
    NaN: none held, or not computed) and ``held_observations``, their observations kept."""

    R_wc: np.ndarray
    t_wc: np.ndarray
    points: np.ndarray
    bias: np.ndarray | None
    traj_depth_sigma: float
    held_scale_sigma: float
    held_observations: int


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

    def normal(self, R_cw: torch.Tensor, d: np.ndarray):
        """The prior's share of the normal equations: Hcc [n-1,6,6] and bc [n-1,6] to add to the cameras' (its
        rotation blocks), and the bias correction's Hcb [n-1,6,3], Hbb [3,3], bb [3] (d e_i / d(dw_i) = I,
        d e_i / d d = R_cw_i A_i to first order)."""
        f64 = R_cw.dtype
        e, wp = torch.from_numpy(self.residual(R_cw, d)), torch.from_numpy(self.w)
        B = R_cw[1:] @ torch.from_numpy(self.A)
        Hcc, bc = torch.zeros(len(wp), 6, 6, dtype=f64), torch.zeros(len(wp), 6, dtype=f64)
        Hcc[:, :3, :3] = wp[:, None, None] * torch.eye(3, dtype=f64)
        bc[:, :3] = wp[:, None] * e
        Hcb = torch.zeros(len(wp), 6, 3, dtype=f64)
        Hcb[:, :3] = wp[:, None, None] * B
        Hbb = torch.einsum("n,nji,njk->ik", wp, B, B) + self.w_bias * torch.eye(3, dtype=f64)
        bb = torch.einsum("n,nji,nj->i", wp, B, e) + self.w_bias * torch.from_numpy(d)
        return Hcc, bc, Hcb, Hbb, bb


def _pixel_normal(R_cw, t_cw, Xc, z, r, vis, K, huber_px, nc):
    """The reprojection error's Gauss-Newton normal equations at cameras R_cw [n,3,3], t_cw [n,3] with camera-frame
    points Xc [m,n,3], depths z and residuals r (``_residuals``), Huber-weighted at ``huber_px`` (1 px: unit weight):
    the weights w [m,n] and the blocks Hcc [nc-1,6,6], Hll [m,3,3], Hcl [m,nc-1,6,3], bc [nc-1,6], bl [m,3] of cameras
    1..nc-1 (rotation, then translation: left perturbations) and points (frame 0 is the gauge; cameras nc.. are held,
    their observations constrain the points only)."""
    # Jp = d(pixel)/d(Xc) [m,n,2,3]; the left perturbation Xc' = exp(dw) R X + t + dt gives d/d(dw) = -Jp hat(R X)
    # (row-wise (R X) x Jp) and d/d(dt) = Jp; d/dX = Jp R.
    fx, fy = K[0, 0], K[1, 1]
    w = torch.where(vis, (huber_px / r.norm(dim=-1).clamp_min(1e-12)).clamp_max(1.0), 0.0)
    Jp = torch.zeros(Xc.shape[:2] + (2, 3), dtype=Xc.dtype)
    Jp[..., 0, 0], Jp[..., 1, 1] = fx / z, fy / z
    Jp[..., 0, 2], Jp[..., 1, 2] = -fx * Xc[..., 0] / z**2, -fy * Xc[..., 1] / z**2
    Jpc = Jp[:, 1:nc]  # the cameras solved for
    Jc = torch.cat([torch.linalg.cross((Xc[:, 1:nc] - t_cw[1:nc])[..., None, :].expand_as(Jpc), Jpc), Jpc], -1)
    Jl = torch.einsum("mnri,nij->mnrj", Jp, R_cw)
    WJc, WJl = w[:, 1:nc, None, None] * Jc, w[..., None, None] * Jl
    Hcc = torch.einsum("mnri,mnrj->nij", WJc, Jc)  # [nc-1,6,6]
    Hll = torch.einsum("mnri,mnrj->mij", WJl, Jl)  # [m,3,3]
    # Sums of outer products over the two residual rows, written out (batched 6x2 @ 2x3 products are slow).
    Hcl = torch.addcmul(WJc[..., 0, :, None] * Jl[:, 1:nc, 0, None, :], WJc[..., 1, :, None],
                        Jl[:, 1:nc, 1, None, :])  # [m,nc-1,6,3]
    bc = torch.einsum("mnri,mnr->ni", WJc, r[:, 1:nc])
    bl = torch.einsum("mnri,mnr->mi", WJl, r)
    return w, Hcc, Hll, Hcl, bc, bl


def _reduced(Hcc: torch.Tensor, Hll_inv: torch.Tensor, Hcl: torch.Tensor,
             bias: tuple[torch.Tensor, torch.Tensor] | None) -> tuple[torch.Tensor, torch.Tensor]:
    """The reduced camera system M [6(n-1)+nb]^2 once the points are eliminated (their inverse blocks Hll_inv
    [m,3,3]), with the bias correction's unknowns last where ``bias`` = (Hcb [n-1,6,3], Hbb [3,3]) is given (no point
    depends on them), and Y = Hcl Hll^-1 [m,n-1,6,3] (for the right-hand side and the points' back-substitution)."""
    c = Hcc.shape[0]
    Y = torch.bmm(Hcl.reshape(len(Hcl), -1, 3), Hll_inv).view(Hcl.shape)
    # Schur complement S = Hcc - sum_m Y_m Hcl_m^T as one matrix product over (point, point coordinate).
    S = -(Y.permute(1, 2, 0, 3).reshape(6 * c, -1) @ Hcl.permute(1, 2, 0, 3).reshape(6 * c, -1).T)
    S = S.view(c, 6, c, 6)
    S[torch.arange(c), :, torch.arange(c), :] += Hcc
    if bias is None:
        return S.reshape(6 * c, 6 * c), Y
    Hcb, Hbb = bias
    M = torch.zeros(6 * c + 3, 6 * c + 3, dtype=Hcc.dtype)
    M[:-3, :-3] = S.reshape(6 * c, -1)
    M[:-3, -3:] = Hcb.reshape(-1, 3)
    M[-3:, :-3] = Hcb.reshape(-1, 3).T
    M[-3:, -3:] = Hbb
    return M, Y


def _information(pixel: tuple, r: torch.Tensor, vis: torch.Tensor, prior: tuple | None, n: int, *,
                 cameras_only: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, tuple | None] | None:
    """The Gauss-Newton information of an adjustment of n cameras (the first the gauge) at the pixel noise its
    residuals r [m,N,2] show (Huber-weighted, dof-corrected): ``pixel``'s Hcc, Hcl (w, Hcc, Hll, Hcl of
    ``_pixel_normal``) divided by that variance, the prior's (``_GyroPrior.normal``'s Hcc, Hcb, Hbb, or None) added,
    the points' inverse blocks Hll^-1 [m,3,3] at that variance, and the bias blocks (Hcb, Hbb) or None; None where no
    degrees of freedom are left or a camera's centre is free. ``cameras_only``: a quantity of the cameras alone, whose
    variance a point's unseen depth should not reach through round-off: the blocks as ``_pinv_points`` (else exactly,
    since a quantity of the points' depths has those depths' real variance in it)."""
    w, Hcc, Hll, Hcl = pixel
    dof = 2 * int(vis.sum()) - 6 * (n - 1) - 3 * Hll.shape[0]
    if dof <= 0 or bool((Hcc.diagonal(dim1=1, dim2=2)[:, 3:] <= 0).any()):
        return None
    var_px = float((w * (r**2).sum(-1)).sum()) / dof
    Hcc, Hcl = Hcc / var_px, Hcl / var_px
    Hll_inv = _pinv_points(Hll / var_px) if cameras_only else _inv3(Hll / var_px + 1e-9 * torch.eye(3, dtype=Hll.dtype))
    if prior is None:
        return Hcc, Hll_inv, Hcl, None
    Hp, Hcb, Hbb = prior
    return Hcc + Hp, Hll_inv, Hcl, (Hcb, Hbb)


def _trajectory_depth_sigma(R_cw: torch.Tensor, t_cw: torch.Tensor, Xc: torch.Tensor, z: torch.Tensor,
                            r: torch.Tensor, vis: torch.Tensor, pixel: tuple, prior: tuple | None) -> float:
    """The 1-sigma of log(trajectory scale / depth scale) of the adjusted clip (cameras R_cw [n,3,3], t_cw [n,3],
    camera-frame points Xc [m,n,3], depths z, residuals r, ``_residuals``'), from the normal equations of the last
    linearisation (``pixel``: w, Hcc, Hll, Hcl of ``_pixel_normal``; ``prior``: Hcc, Hcb, Hbb of
    ``_GyroPrior.normal``, or None; a step before the end at most, where the step was within the tolerance).

    q = q_t - q_d, q_t the least-squares scale change of the camera centres about their mean and q_d the mean relative
    change of the observed depths. Both move alike with the scale gauge, so q is defined by the images (and the gyro)
    alone, and its variance g^T H^+ g comes from the Gauss-Newton information H at the pixel noise the residuals show
    (Huber-weighted, dof-corrected) plus the prior's. A clip that mostly turns has it large: its images cannot say how
    far the camera moved against how far the scene is, and the metric fit (which reads the trajectory) and the scale
    links (which read the depth) then see different scales. NaN where it cannot be computed: fewer than 3 frames, no
    degrees of freedom left, or a frame that no point constrains (its centre is free)."""
    n = R_cw.shape[0]
    f64 = Xc.dtype
    info = _information(pixel, r, vis, prior, n, cameras_only=False) if n >= 3 else None
    if info is None:
        return float("nan")
    Hcc, Hll_inv, Hcl, bias = info
    # q's gradient: centres c_i = -R_i^T t_i about their mean p_i move by -R_i^T (dt_i - dw_i x t_i); depths by
    # e_z . (dw_i x P + dt_i + R_i dX_m) with P = R_i X_m.
    c = -(R_cw.transpose(1, 2) @ t_cw[..., None])[..., 0]
    p = c - c.mean(0)
    Rp = (R_cw @ p[..., None])[..., 0][1:]
    spread = float((p**2).sum())
    inv_z = torch.where(vis, 1.0 / z, 0.0) / int(vis.sum())  # [m,n]
    e_z = torch.tensor([0.0, 0.0, 1.0], dtype=f64)
    P = Xc - t_cw
    gc = torch.zeros(n - 1, 6, dtype=f64)
    gc[:, :3] = torch.linalg.cross(t_cw[1:], Rp) / spread - torch.einsum(
        "mn,mni->ni", inv_z, torch.linalg.cross(P, e_z.expand_as(P)))[1:]
    gc[:, 3:] = -Rp / spread - inv_z.sum(0)[1:, None] * e_z
    gl = -torch.einsum("mn,ni->mi", inv_z, R_cw[:, 2, :])
    # the scale gauge: a rank-one term on a camera's translation along itself (q is blind to the gauge)
    j = int(torch.argmax(t_cw[1:].norm(dim=-1)))
    u = torch.zeros(n - 1, 6, dtype=f64)
    u[j, 3:] = t_cw[1 + j] / t_cw[1 + j].norm()
    M, Y = _reduced(Hcc, Hll_inv, Hcl, bias)
    u = u.reshape(-1)
    M[:len(u), :len(u)] += float(M.diagonal().abs().mean()) * torch.outer(u, u)
    rhs = (gc - torch.einsum("maij,mj->ai", Y, gl)).reshape(-1)
    if bias is not None:
        rhs = torch.cat([rhs, torch.zeros(3, dtype=f64)])
    var = float(torch.einsum("mi,mij,mj->", gl, Hll_inv, gl)) + float(rhs @ torch.linalg.solve(M, rhs))
    return math.sqrt(var) if var >= 0 and math.isfinite(var) else float("nan")


def _held_scale_sigma(R_cw: torch.Tensor, t_cw: torch.Tensor, r: torch.Tensor, vis: torch.Tensor, pixel: tuple,
                      prior: tuple | None, n: int) -> float:
    """The 1-sigma of the log of the scale of the clip's trajectory (its first ``n`` cameras, the first held as the
    gauge) where held cameras fix the scale gauge, from the Gauss-Newton information of the last linearisation at the
    pixel noise the residuals r [m,N,2] show (``pixel``: w, Hcc, Hll, Hcl of ``_pixel_normal`` over all N cameras;
    ``prior``: ``_GyroPrior.normal``'s Hcc, Hcb, Hbb, or None). The scale is q_t, the least-squares scale change of
    the clip's camera centres about the first's, c_i = -R_i^T t_i moving by -R_i^T (dt_i - dw_i x t_i); it depends on
    no point, so its variance is g^T M^-1 g with M the reduced camera system. NaN where it cannot be computed."""
    f64 = t_cw.dtype
    info = _information(pixel, r, vis, prior, n, cameras_only=True) if n >= 2 else None
    if info is None:
        return float("nan")
    Hcc, Hll_inv, Hcl, bias = info
    c = -(R_cw[:n].transpose(1, 2) @ t_cw[:n, :, None])[..., 0]
    p = c - c[0]
    spread = float((p**2).sum())
    if spread <= 0:
        return float("nan")
    Rp = (R_cw[1:n] @ p[1:, :, None])[..., 0]
    g = torch.cat([torch.linalg.cross(t_cw[1:n], Rp), -Rp], 1).reshape(-1) / spread
    M, _ = _reduced(Hcc, Hll_inv, Hcl, bias)
    if bias is not None:
        g = torch.cat([g, torch.zeros(3, dtype=f64)])
    var = float(g @ torch.linalg.solve(M, g))
    return math.sqrt(var) if var >= 0 and math.isfinite(var) else float("nan")


def _adjugate(A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The adjugates [...,3,3] and determinants [...] of 3x3 matrices A [...,3,3] (elementwise, no LAPACK call)."""
    c0 = torch.linalg.cross(A[..., 1, :], A[..., 2, :])
    c1 = torch.linalg.cross(A[..., 2, :], A[..., 0, :])
    c2 = torch.linalg.cross(A[..., 0, :], A[..., 1, :])
    return torch.stack([c0, c1, c2], -1), (A[..., 0, :] * c0).sum(-1)


def _inv3(A: torch.Tensor) -> torch.Tensor:
    """Inverses [...,3,3] of invertible 3x3 matrices A [...,3,3] by the adjugate."""
    adj, det = _adjugate(A)
    return adj / det[..., None, None]


# A point's direction with less information than this share of its block's largest eigenvalue (a depth seen at a
# parallax near zero, its 1-sigma over a thousand times the lateral one) is left out of the points' inverse.
POINT_RTOL = 1e-6


def _pinv_points(Hll: torch.Tensor) -> torch.Tensor:
    """The points' inverse information blocks [m,3,3] from Hll [m,3,3] (symmetric, positive semi-definite), with
    each block's directions under ``POINT_RTOL`` of its largest eigenvalue left out (a pseudo-inverse). Inverted
    exactly, a block with a condition of 1e9 (a point on one ray from cameras that turn) enters the Schur complement
    as terms that cancel to a part in 1e9 of themselves: a camera quantity's sigma (the held scale's) then swings by
    tens of percent with the last bits of the input, or comes out negative. Left out, such a direction is held rather
    than eliminated, as if the point's depth were known: optimistic by at most that point's own share of the
    cameras' information (such points are few: 1.5 % of the blocks of the test clip in
    tests/core/test_frame_tracker.py, 0.2 % on a real handheld recording; on that test clip the held sigma is within
    3 % of its value computed exactly in extended precision). Well-conditioned blocks keep their adjugate inverse;
    the others go through an eigendecomposition (every block with a direction under the tolerance has a determinant
    of at most 4 * POINT_RTOL times the cube of its mean eigenvalue; a NaN block stays NaN)."""
    adj, det = _adjugate(Hll)
    inv = adj / det[..., None, None]
    mean = Hll.diagonal(dim1=-2, dim2=-1).sum(-1) / 3
    weak = det <= 4 * POINT_RTOL * mean**3
    if bool(weak.any()):
        lam, V = torch.linalg.eigh(Hll[weak])
        keep = lam > POINT_RTOL * lam[:, -1:]
        inv[weak] = (V * torch.where(keep, 1.0 / torch.where(keep, lam, 1.0), 0.0)[:, None, :]) @ V.transpose(1, 2)
    return inv


class _Solved(NamedTuple):
    """``_levenberg_marquardt``'s end: cameras R_cw [N,3,3], t_cw [N,3], points X [m,3], the gyro bias correction d
    [3] rad/s, ``_residuals``' Xc, z, r there, the last linearisation's blocks (``pixel``: w, Hcc, Hll, Hcl of
    ``_pixel_normal``; ``prior``: Hcc, Hcb, Hbb of ``_GyroPrior.normal``; None: none made, or no prior) and the
    damping ``lam`` reached."""

    R_cw: torch.Tensor
    t_cw: torch.Tensor
    X: torch.Tensor
    d: np.ndarray
    Xc: torch.Tensor
    z: torch.Tensor
    r: torch.Tensor
    pixel: tuple | None
    prior: tuple | None
    lam: float


def _levenberg_marquardt(R_cw: torch.Tensor, t_cw: torch.Tensor, X: torch.Tensor, obs: torch.Tensor,
                         vis: torch.Tensor, K: torch.Tensor, n: int, prior: _GyroPrior | None, *, iterations: int,
                         huber_px: float, tol: float, d: np.ndarray | None = None, lam: float = 1e-3) -> _Solved:
    """At most ``iterations`` Levenberg-Marquardt steps of cameras 1..n-1 and the points from R_cw, t_cw, X against
    the pixels obs [m,N,2] where ``vis`` [m,N] (cameras n.. held), with the gyro ``prior`` on the clip's rotations,
    its bias correction starting at ``d`` [3] rad/s (None: zero) and the damping at ``lam`` (a pass that continues
    another starts from its end, both); stops where a step lowers the cost by less than ``tol`` of it."""
    f64 = X.dtype
    eye6, eye3 = torch.eye(6, dtype=f64), torch.eye(3, dtype=f64)
    clip = slice(0, n)
    d = np.zeros(3) if d is None else d
    Xc, z, r = _residuals(R_cw, t_cw, X, obs, vis, K)
    cost = _cost(r, vis, huber_px) + (prior.cost(R_cw[clip], d) if prior else 0.0)
    linearise = True
    pixel = prior_blocks = None
    for _ in range(iterations):
        if linearise:
            w, Hcc, Hll, Hcl, bc, bl = _pixel_normal(R_cw, t_cw, Xc, z, r, vis, K, huber_px, n)
            pixel, prior_blocks = (w, Hcc, Hll, Hcl), None
            if prior is not None:
                Hp, bp, Hcb, Hbb, bb = prior.normal(R_cw[clip], d)
                Hcc, bc, prior_blocks = Hcc + Hp, bc + bp, (Hp, Hcb, Hbb)
        diag = Hcc.diagonal(dim1=1, dim2=2)[:, :, None]
        # a camera no point constrains any more (a long clip's frame whose points were all cleaned out) stays put
        Hcc_d = Hcc + lam * eye6 * diag + eye6 * (diag == 0)
        Hll_inv = _inv3(Hll + lam * eye3 * Hll.diagonal(dim1=1, dim2=2)[:, :, None] + 1e-9 * eye3)
        M, Y = _reduced(Hcc_d, Hll_inv, Hcl, None if prior is None else
                        (Hcb, Hbb + lam * torch.diag(Hbb.diagonal())))
        rhs = (-bc + torch.einsum("maij,mj->ai", Y, bl)).reshape(-1)
        sol = torch.linalg.solve(M, rhs if prior is None else torch.cat([rhs, -bb]))
        dc = sol[:6 * (n - 1)].reshape(n - 1, 6)
        dd = sol[6 * (n - 1):].numpy()
        dl = -torch.einsum("mij,mj->mi", Hll_inv, bl + torch.einsum("maji,aj->mi", Hcl, dc))
        R_new, t_new = R_cw.clone(), t_cw.clone()
        R_new[1:n] = torch.from_numpy(so3.exp(dc[:, :3].numpy())) @ R_cw[1:n]
        t_new[1:n] = t_cw[1:n] + dc[:, 3:]
        X_new = X + dl
        d_new = d + dd if prior is not None else d
        Xc_new, z_new, r_new = _residuals(R_new, t_new, X_new, obs, vis, K)
        cost_new = _cost(r_new, vis, huber_px) + (prior.cost(R_new[clip], d_new) if prior else 0.0)
        linearise = cost_new < cost
        if linearise:
            done = cost - cost_new < tol * cost
            R_cw, t_cw, X, cost, Xc, z, r, d = R_new, t_new, X_new, cost_new, Xc_new, z_new, r_new, d_new
            lam = max(lam / 3.0, 1e-7)
            if done:
                break
        else:
            lam *= 5.0
    return _Solved(R_cw, t_cw, X, d, Xc, z, r, pixel, prior_blocks, lam)


@torch.inference_mode()
def bundle_adjust(R_wc: np.ndarray, t_wc: np.ndarray, points: np.ndarray, uv: np.ndarray, visible: np.ndarray,
                  K: np.ndarray, *, iterations: int = 20, huber_px: float = 1.0, tol: float = 1e-4,
                  gyro: GyroRotations | None = None, gyro_sigma: float = 0.0, held: int = 0,
                  held_max_px: float = math.inf) -> Adjusted:
    """Refine camera-to-world poses R_wc [n,3,3], t_wc [n,3] and points [m,3] (NaN rows are left out) against
    the observations uv [m,n,2] (pixels, where ``visible`` [m,n]), with ``gyro`` (its R_wc in the same world, the first
    camera) a prior of ``gyro_sigma`` rad on each rotation where given and gyro_sigma > 0 (``Adjusted``). The last
    ``held`` cameras (keyframes of earlier clips) stay where they are: their observations hold the points, and with
    them the scale gauge, to the keyframes'; those that miss by more than ``held_max_px`` after a first pass are
    dropped before a second, shorter one (``iterations // 4``) that goes on from the first's end (its state, bias
    correction and damping: restarted at the initial damping, it was still far from its optimum when its steps ran
    out), and the sigmas are computed once, at the end. The trajectory's sigma against the depth is the clip's own
    (its first n - held cameras)."""
    n = len(R_wc) - held
    pid = np.flatnonzero(np.isfinite(points[:, 0]))
    f64 = torch.float64
    X = torch.as_tensor(points[pid], dtype=f64)
    obs = torch.as_tensor(np.nan_to_num(uv[pid]), dtype=f64)
    vis = torch.as_tensor(visible[pid])
    K_t = torch.as_tensor(K, dtype=f64)
    R_cw = torch.as_tensor(R_wc, dtype=f64).transpose(1, 2).contiguous()
    t_cw = -(R_cw @ torch.as_tensor(t_wc, dtype=f64)[..., None])[..., 0]
    prior = _GyroPrior(gyro, gyro_sigma) if gyro is not None and gyro_sigma > 0 and n > 1 else None
    lm = dict(iterations=iterations, huber_px=huber_px, tol=tol)
    s = _levenberg_marquardt(R_cw, t_cw, X, obs, vis, K_t, n, prior, **lm)
    if held:
        miss = vis[:, n:] & ~(s.r[:, n:].norm(dim=-1) <= held_max_px)
        if bool(miss.any()):
            vis = vis.clone()
            vis[:, n:] &= ~miss
            s = _levenberg_marquardt(s.R_cw, s.t_cw, s.X, obs, vis, K_t, n, prior,
                                     **{**lm, "iterations": max(iterations // 4, 1)}, d=s.d, lam=s.lam)
    R_cw, t_cw, Xc, z, r, pixel = s.R_cw, s.t_cw, s.Xc, s.z, s.r, s.pixel
    clip = slice(0, n)
    held_sigma = float("nan")
    if held and pixel is not None:  # both at the final state: the scale against the keyframes with their observations,
        # the trajectory against the depth from the clip's own (the keyframes' observations left out)
        held_sigma = _held_scale_sigma(R_cw, t_cw, r, vis, _pixel_normal(R_cw, t_cw, Xc, z, r, vis, K_t, huber_px,
                                                                          n)[:4], s.prior, n)
        pixel = _pixel_normal(R_cw[clip], t_cw[clip], Xc[:, clip], z[:, clip], r[:, clip], vis[:, clip], K_t,
                              huber_px, n)[:4]
    R_out = R_cw.transpose(1, 2)
    out = np.full_like(points, np.nan)
    out[pid] = s.X.numpy()
    return Adjusted(R_out.numpy(), (-(R_out @ t_cw[..., None])[..., 0]).numpy(), out,
                    gyro.bg + s.d if prior is not None else None,
                    _trajectory_depth_sigma(R_cw[clip], t_cw[clip], Xc[:, clip], z[:, clip], r[:, clip], vis[:, clip],
                                            pixel, s.prior) if pixel is not None else float("nan"), held_sigma,
                    int(vis[:, n:].sum()))
