"""Up-to-scale camera poses and sparse points of a clip from feature tracks (structure from motion).

Steps: an essential matrix (RANSAC) between frame 0 and the frame with the most parallax fixes the first
up-to-scale baseline; its inlier tracks are triangulated; every other frame is registered in order by PnP (RANSAC)
against the points so far, each adding the points of the tracks it is the second posed view of (incremental, so a
camera that turns away from frame 0's view keeps points to register on); all tracks are then triangulated from
every view that sees them (linear DLT) and poses and points are refined together by a small bundle adjustment
(``bundle.py``). A clip that continues the tracks of the clip before it starts from that clip's points instead
(``known``: the structure its shared first frame saw, in this clip's world; no essential matrix), and falls back to
the two-view start where those points do not carry its frames.

World = first camera (OpenCV axes), poses camera-to-world. The scale is whatever the first baseline gave; the
caller normalises it. Degenerate clips are reported, never forced: no common tracks -> ``few_features``; image
motion below ``stationary_px`` -> ``stationary`` (identity poses); motion explained by a rotation alone ->
``no_parallax`` (rotations estimated, translations zero).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from vi3_core.backbones.base import GyroRotations
from vi3_core.backbones.classical.bundle import Adjusted
from vi3_core.backbones.classical.bundle import bundle_adjust as refine
from vi3_core.backbones.classical.keyframes import Anchors
from vi3_core.backbones.classical.tracks import Tracks

OK = "ok"
STATIONARY = "stationary"
NO_PARALLAX = "no_parallax"
FEW_FEATURES = "few_features"


@dataclass
class SfmResult:
    """R_wc [n,3,3], t_wc [n,3] camera-to-world in the first camera's frame (arbitrary scale);
    points [m,3] per track in that frame, NaN where not triangulated; status one of ok | stationary |
    no_parallax | few_features, with a human-readable reason; diagnostics: counts and errors."""

    R_wc: np.ndarray
    t_wc: np.ndarray
    points: np.ndarray
    status: str
    reason: str
    diagnostics: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == OK


def _bearings(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels [...,2] -> normalised image coordinates [...,2] (z = 1)."""
    return (uv - K[:2, 2]) / np.diag(K)[:2]


def project(points: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points [m,3] into n cameras -> pixels [m,n,2] and z-depths [m,n]."""
    Xc = np.einsum("nji,mnj->mni", R_wc, points[:, None, :] - t_wc[None])  # R_wc^T (X - t)
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = Xc[..., :2] / z[..., None] * np.diag(K)[:2] + K[:2, 2]
    return uv, z


def triangulate(uv: np.ndarray, visible: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray,
                K: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of m tracks from all the views that see them.

    uv [m,n,2] pixels, visible [m,n] bool, poses camera-to-world [n,3,3], [n,3] -> points [m,3] in the world.
    """
    R_cw = np.swapaxes(R_wc, 1, 2)
    P = np.concatenate([R_cw, -(R_cw @ t_wc[..., None])], axis=2)  # [n,3,4] world -> camera
    x = np.where(visible[..., None], _bearings(np.nan_to_num(uv), K), 0.0)
    rows = np.concatenate([x[..., 0:1, None] * P[None, :, 2:3] - P[None, :, 0:1],
                           x[..., 1:2, None] * P[None, :, 2:3] - P[None, :, 1:2]], axis=2)  # [m,n,2,4]
    A = (rows * visible[..., None, None]).reshape(len(uv), -1, 4)
    _, _, Vt = np.linalg.svd(A, full_matrices=False)
    Xh = Vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return Xh[:, :3] / Xh[:, 3:]


def _clean_points(points: np.ndarray, uv: np.ndarray, visible: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray,
                  K: np.ndarray, *, max_reproj_px: float, min_angle_deg: float | np.ndarray) -> np.ndarray:
    """NaN out points seen in < 2 views, behind a camera, with a reprojection error above ``max_reproj_px``
    in any view, or whose rays meet at less than ``min_angle_deg`` (depth poorly constrained; one for all, or per
    point [m])."""
    proj, z = project(points, R_wc, t_wc, K)
    err = np.where(visible, np.linalg.norm(proj - uv, axis=-1), 0.0)
    rays = points[:, None, :] - t_wc[None]
    with np.errstate(invalid="ignore"):
        rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    # Largest angle between any viewing ray and the ray of the first view that sees the point.
    first = np.take_along_axis(rays, np.argmax(visible, axis=1)[:, None, None], axis=1)
    cosang = np.where(visible, np.sum(rays * first, axis=-1), 1.0)
    angle = np.degrees(np.arccos(np.clip(cosang.min(axis=1), -1.0, 1.0)))
    good = (visible.sum(1) >= 2) & np.all(np.where(visible, z > 0, True), axis=1)
    good &= np.nan_to_num(err, nan=np.inf).max(axis=1) <= max_reproj_px
    good &= angle >= min_angle_deg
    return np.where(good[:, None], points, np.nan)


def _rotation_only(uv: np.ndarray, visible: np.ndarray, K: np.ndarray) -> np.ndarray:
    """R_wc [n,3,3] of a purely rotating camera: Kabsch fit of each frame's bearings to frame 0's."""
    n = uv.shape[1]
    f = np.concatenate([_bearings(np.nan_to_num(uv), K), np.ones(uv.shape[:2] + (1,))], -1)
    f /= np.linalg.norm(f, axis=-1, keepdims=True)
    both = visible & visible[:, :1]  # [m,n]
    H = np.einsum("mn,mni,mj->nij", both.astype(float), f, f[:, 0])  # sum f_i f_0^T: R_0i f_i ~ f_0
    U, _, Vt = np.linalg.svd(H)
    D = np.ones((n, 3))
    D[:, 2] = np.sign(np.linalg.det(Vt.transpose(0, 2, 1) @ U.transpose(0, 2, 1)))
    return np.einsum("nji,nj,nkj->nik", Vt, D, U)


def _two_view(uv: np.ndarray, visible: np.ndarray, K: np.ndarray, j: int, R_wc: np.ndarray, t_wc: np.ndarray, *,
              ransac_px: float, max_reproj_px: float, min_angle_deg: float) -> np.ndarray | None:
    """The first baseline: frame j's pose from the essential matrix (RANSAC) against frame 0, written into R_wc[j],
    t_wc[j]; returns its inlier tracks triangulated and cleaned [m,3] (NaN elsewhere), None when E fails."""
    pair = visible[:, 0] & visible[:, j]
    E, mask = cv2.findEssentialMat(uv[pair, 0], uv[pair, j], K, method=cv2.RANSAC, prob=0.999, threshold=ransac_px)
    if E is None or E.shape != (3, 3):
        return None
    _, R_cw, t_cw, mask = cv2.recoverPose(E, uv[pair, 0], uv[pair, j], K, mask=mask)
    R_wc[j], t_wc[j] = R_cw.T, -(R_cw.T @ t_cw).ravel()
    inliers = np.flatnonzero(pair)[mask.ravel() > 0]
    init_vis = np.zeros_like(visible)
    init_vis[inliers, 0] = init_vis[inliers, j] = True
    return _clean_points(triangulate(uv, init_vis, R_wc, t_wc, K), uv, init_vis, R_wc, t_wc, K,
                         max_reproj_px=max_reproj_px, min_angle_deg=min_angle_deg)


def _register(uv: np.ndarray, visible: np.ndarray, K: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray,
              points: np.ndarray, posed: list[int], *, ransac_px: float, clean: dict) -> str | None:
    """Every frame not in ``posed`` registered in order by PnP (RANSAC) against ``points`` [m,3] (NaN: none yet),
    its pose written into R_wc, t_wc [n,...]; after each, the tracks seen by two posed frames that have no point yet
    are triangulated into ``points`` (incremental: a frame whose view has turned away from the first frame's still
    sees the points its neighbours made). Returns why it failed, or None."""
    is_posed = np.zeros(uv.shape[1], bool)
    is_posed[posed] = True
    for i in np.flatnonzero(~is_posed):
        sel = visible[:, i] & np.isfinite(points[:, 0])
        if sel.sum() < 6:
            return f"frame {i} sees only {sel.sum()} triangulated points (need 6)"
        ok, rvec, tvec, _ = cv2.solvePnPRansac(points[sel], uv[sel, i], K, None, reprojectionError=2 * ransac_px,
                                               iterationsCount=200, flags=cv2.SOLVEPNP_EPNP)
        if not ok:
            return f"PnP failed for frame {i}"
        R_i = cv2.Rodrigues(rvec)[0]
        R_wc[i], t_wc[i] = R_i.T, -(R_i.T @ tvec).ravel()
        is_posed[i] = True
        seen = visible & is_posed
        new = ~np.isfinite(points[:, 0]) & (seen.sum(1) >= 2) & seen[:, i]
        if new.any():
            points[new] = _clean_points(triangulate(uv[new], seen[new], R_wc, t_wc, K), uv[new], seen[new], R_wc,
                                        t_wc, K, **clean)
    return None


def _anchored(R_wc: np.ndarray, t_wc: np.ndarray, points: np.ndarray, uv: np.ndarray, K: np.ndarray,
              found: Anchors, *, iterations: int, gyro: GyroRotations | None, gyro_sigma: float,
              max_reproj_px: float) -> tuple[Adjusted, int]:
    """The bundle adjustment of the clip (R_wc [n,3,3], t_wc [n,3], points [m,3], uv [m,n,2], NaN where unseen)
    with the keyframes of ``found`` held, its keyframe observations that miss by more than ``max_reproj_px`` after
    a first pass dropped before a second, shorter one (``bundle.bundle_adjust``'s ``held_max_px``); returns it (the
    clip's cameras only) and the keyframe observations kept."""
    n = len(R_wc)
    uv_all = np.concatenate([uv, found.uv], 1)
    adjusted = refine(np.concatenate([R_wc, found.R_wc]), np.concatenate([t_wc, found.t_wc]), points, uv_all,
                      np.isfinite(uv_all[..., 0]), K, iterations=iterations, gyro=gyro, gyro_sigma=gyro_sigma,
                      held=len(found.R_wc), held_max_px=max_reproj_px)
    return adjusted._replace(R_wc=adjusted.R_wc[:n], t_wc=adjusted.t_wc[:n]), adjusted.held_observations


def estimate_poses(tracks: Tracks, K: np.ndarray, *, known: np.ndarray | None = None, stationary_px: float = 0.5,
                   min_parallax_px: float = 1.0, min_tracks: int = 30, ransac_px: float = 1.0,
                   max_reproj_px: float = 3.0, min_angle_deg: float = 0.3, bundle_adjust: bool = True,
                   ba_iterations: int = 20, gyro: GyroRotations | None = None, gyro_sigma: float = 0.0,
                   anchor: Callable[[np.ndarray], Anchors | None] | None = None) -> SfmResult:
    """Structure from motion over the clip (see the module docstring). ``K`` [3,3] of the tracked images; ``known``
    [m,3]: points of the tracks (NaN where unknown) from the clip before, in this clip's world, used in place of a
    two-view start when at least ``min_tracks`` of them are seen in the first frame; ``gyro``, ``gyro_sigma``: the
    bundle adjustment's rotation prior (``bundle.bundle_adjust``; the gyro bias it fits is in the diagnostics,
    ``gyro_bias``); ``anchor``: the keyframes' observations of the clip's points [m,3] before the bundle adjustment
    (``keyframes.KeyframeMap.anchors``), which then holds the keyframes where at least ``min_tracks`` are found
    (``anchored``: how many it kept)."""
    uv, visible = tracks.uv, tracks.visible
    n = uv.shape[1]
    eye, zero = np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))
    nan_points = np.full((len(uv), 3), np.nan)
    common = (visible & visible[:, :1]).sum(0)
    if n < 2 or common[1:].max(initial=0) < min_tracks:
        return SfmResult(eye, zero, nan_points, FEW_FEATURES,
                         f"too few feature tracks shared with frame 0 (best {common[1:].max(initial=0)}, "
                         f"need {min_tracks})", {"tracks": len(uv)})
    flow = np.linalg.norm(uv - uv[:, :1], axis=-1)
    med_flow = np.array([np.median(flow[visible[:, j] & visible[:, 0], j]) if common[j] else 0.0
                         for j in range(n)])
    if med_flow.max() < stationary_px:
        return SfmResult(eye, zero, nan_points, STATIONARY,
                         f"no image motion (median feature flow {med_flow.max():.2f} px < {stationary_px} px)",
                         {"tracks": len(uv), "median_flow_px": float(med_flow.max())})
    # Rotation-compensated parallax of every frame against frame 0 decides the initial pair.
    R_rot = _rotation_only(uv, visible, K)
    derot = np.einsum("ij,njk,kl->nil", K, np.swapaxes(R_rot, 1, 2), np.linalg.inv(K))  # pixel homography 0 -> j
    p0 = np.concatenate([np.nan_to_num(uv[:, 0]), np.ones((len(uv), 1))], 1)
    pred = np.einsum("nij,mj->mni", derot, p0)
    parallax = np.linalg.norm(pred[..., :2] / pred[..., 2:] - uv, axis=-1)
    med_par = np.array([np.median(parallax[visible[:, j] & visible[:, 0], j]) if common[j] >= min_tracks else 0.0
                        for j in range(n)])
    j = int(np.argmax(med_par))
    diag = {"tracks": len(uv), "median_flow_px": float(med_flow.max()), "parallax_px": float(med_par[j])}
    clean = dict(max_reproj_px=max_reproj_px, min_angle_deg=min_angle_deg)
    failed = "no structure from the clip before"
    carried = np.full((len(uv), 3), np.nan)
    if known is not None and int((np.isfinite(known[:, 0]) & visible[:, 0]).sum()) >= min_tracks:
        # the clip before's points already have depth: PnP needs no parallax of this clip's own
        R_wc, t_wc = eye.copy(), zero.copy()
        carried = np.where(visible[:, :1], known, np.nan)
        points = carried.copy()
        diag["initial_points"] = int(np.isfinite(points[:, 0]).sum())
        failed = _register(uv, visible, K, R_wc, t_wc, points, [0], ransac_px=ransac_px, clean=clean)
    diag["warm_start"] = failed is None
    if failed is not None and med_par[j] < min_parallax_px:
        return SfmResult(R_rot, zero, nan_points, NO_PARALLAX,
                         f"image motion is a rotation only (median parallax {med_par[j]:.2f} px < "
                         f"{min_parallax_px} px): translation and depth unobservable", diag)
    if failed is not None:  # no warm start, or it lost the structure: the two-view start of the clip's own
        R_wc, t_wc = eye.copy(), zero.copy()
        points = _two_view(uv, visible, K, j, R_wc, t_wc, ransac_px=ransac_px, **clean)
        if points is None:
            return SfmResult(R_rot, zero, nan_points, NO_PARALLAX, "essential matrix estimation failed", diag)
        diag["initial_points"] = int(np.isfinite(points[:, 0]).sum())
        if diag["initial_points"] < min_tracks:
            return SfmResult(R_rot, zero, nan_points, NO_PARALLAX,
                             f"two-view reconstruction of frames 0 and {j} too weak: {diag['initial_points']} points "
                             f"triangulated with rays >= {min_angle_deg} deg apart (need {min_tracks}; median "
                             f"parallax {med_par[j]:.2f} px): translation and depth unobservable", diag)
        failed = _register(uv, visible, K, R_wc, t_wc, points, [0, j], ransac_px=ransac_px, clean=clean)
        if failed is not None:
            return SfmResult(R_rot, zero, nan_points, FEW_FEATURES, failed, diag)
    # a carried point needs no angle between its rays in this clip: its depth came from the clip before
    was_carried = np.isfinite(carried[:, 0]) if diag["warm_start"] else np.zeros(len(uv), bool)
    final = dict(max_reproj_px=max_reproj_px, min_angle_deg=np.where(was_carried, 0.0, min_angle_deg))
    points = triangulate(uv, visible, R_wc, t_wc, K)
    points = _clean_points(np.where(np.isfinite(points[:, :1]), points, carried), uv, visible, R_wc, t_wc, K, **final)
    if bundle_adjust:
        found = anchor(points) if anchor is not None else None
        if found is not None and found.count >= min_tracks:
            adjusted, diag["anchored"] = _anchored(R_wc, t_wc, points, uv, K, found, iterations=ba_iterations,
                                                   gyro=gyro, gyro_sigma=gyro_sigma, max_reproj_px=max_reproj_px)
            diag["held_scale_sigma"] = adjusted.held_scale_sigma
        else:
            adjusted = refine(R_wc, t_wc, points, uv, visible, K, iterations=ba_iterations, gyro=gyro,
                              gyro_sigma=gyro_sigma)
        R_wc, t_wc, points = adjusted.R_wc, adjusted.t_wc, adjusted.points
        if adjusted.bias is not None:
            diag["gyro_bias"] = adjusted.bias.tolist()
        diag["traj_depth_sigma"] = adjusted.traj_depth_sigma
        points = _clean_points(points, uv, visible, R_wc, t_wc, K, **final)
    good = np.isfinite(points[:, 0])
    proj, _ = project(points[good], R_wc, t_wc, K)
    err = np.linalg.norm(proj - uv[good], axis=-1)[visible[good]]
    diag.update(points=int(good.sum()), reproj_px_median=float(np.median(err)) if err.size else float("nan"))
    return SfmResult(R_wc, t_wc, points, OK, "ok", diag)
