"""The paper's evaluation metrics (Sec. "Experimental setup", paragraph "Evaluation metrics"), per clip.

Poses: ``T`` [n,4,4] camera-to-world in the clip's first camera frame C1. Both prediction and ground truth are
re-anchored at their first frame (T_0^-1 T_i) and never aligned otherwise: the metrics measure absolute metric
accuracy, as the paper does.

Depth: [n,h,w] z-depth in metres on the *same* pixel grid (see ``resample_depth``); a pixel is valid where both
depths are finite and > 0.

- Trans: RMSE of per-frame camera positions against GT (m).
- Rot: mean geodesic angle between predicted and GT orientations (deg).
- Scale (Traj.): median over frames of |t_pred| / |t_gt|, excluding frames whose GT displacement from the first
  frame is < 1 cm (the ratio is undefined there); a clip with no such frame (stationary) gives NaN.
- Scale (fit) (beyond the paper): the least-squares ratio sum t_pred . t_gt / sum |t_gt|^2 over the frames (same
  exclusion). It weighs long baselines, where pose noise matters least: a per-frame ratio at a 10 cm baseline moves by
  3 % with 3 mm of noise, which Scale (Traj.)'s median does not average away. It is the reference of the trust metrics
  (``claims``): the error a clip's scale sigma is checked against.
- AbsRel: per frame, the prediction is aligned by the median ratio s_i = median(D_gt) / median(D_pred); AbsRel is
  the mean over valid pixels of |s_i D_pred - D_gt| / D_gt, averaged over the frames that have valid pixels.
- delta < 1.25: fraction of valid pixels with max(D_pred / D_gt, D_gt / D_pred) < 1.25, without alignment.
- Scale (Depth): median(D_pred / D_gt) over the valid pixels of the clip, without alignment.

Init metrics (paper Tables "Calibration-parameter init error" and "Initial velocity estimation"): gravity angle
error (deg), gyro-bias error (absolute |bg_hat - bg| in rad/s and relative to |bg|), v1 direction error (deg),
magnitude error ||v1_hat| - |v1|| / |v1| and the implied ratio |v1_hat| / |v1| (supplementary OLS-vs-TLS table).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from vi3_core import so3
from vi3_core.errors import DataError
from vi3_core.init.oracle import gt_init_state
from vi3_core.types import GroundTruth, InitResult

#: GT displacements below this (m) are excluded from Scale (Traj.) (paper: "near-stationary (< 1 cm)").
MIN_GT_DISPLACEMENT_M = 0.01
#: Inlier threshold of the delta metric.
DELTA_THRESHOLD = 1.25


@dataclass(frozen=True)
class GeometryMetrics:
    """Pose, scale and depth metrics of one clip (NaN where undefined, e.g. no GT depth)."""

    trans_rmse_m: float
    rot_deg: float
    scale_traj: float
    scale_fit: float
    absrel: float
    delta125: float
    scale_depth: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


@dataclass(frozen=True)
class InitMetrics:
    """Errors of an inertial initialisation against GT (NaN where the GT quantity is unknown)."""

    gravity_err_deg: float
    gyro_bias_err: float
    gyro_bias_rel: float
    v1_dir_deg: float
    v1_mag_err: float
    v1_mag_ratio: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def _check_poses(T_pred: np.ndarray, T_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    T_pred, T_gt = np.asarray(T_pred, dtype=np.float64), np.asarray(T_gt, dtype=np.float64)
    if T_pred.shape != T_gt.shape or T_pred.ndim != 3 or T_pred.shape[1:] != (4, 4):
        raise DataError(f"poses must both be [n,4,4]; got prediction {T_pred.shape} and GT {T_gt.shape}")
    return so3.relative_to_first(T_pred), so3.relative_to_first(T_gt)


def trans_rmse(T_pred: np.ndarray, T_gt: np.ndarray) -> float:
    """RMSE (m) of camera positions, both trajectories in their first camera frame, no alignment."""
    P, G = _check_poses(T_pred, T_gt)
    return float(np.sqrt(np.mean(np.sum((P[:, :3, 3] - G[:, :3, 3]) ** 2, axis=-1))))


def rot_error_deg(T_pred: np.ndarray, T_gt: np.ndarray) -> float:
    """Mean geodesic angle (deg) between predicted and GT orientations, both relative to their first frame."""
    P, G = _check_poses(T_pred, T_gt)
    dR = np.einsum("nji,njk->nik", P[:, :3, :3], G[:, :3, :3])  # R_pred^T R_gt
    return float(np.degrees(np.mean(so3.angle(dR))))


def scale_traj(T_pred: np.ndarray, T_gt: np.ndarray, *, min_disp: float = MIN_GT_DISPLACEMENT_M) -> float:
    """Median per-frame |t_pred| / |t_gt| over frames with GT displacement >= ``min_disp`` (m); NaN if none."""
    P, G = _check_poses(T_pred, T_gt)
    d_pred = np.linalg.norm(P[:, :3, 3], axis=-1)
    d_gt = np.linalg.norm(G[:, :3, 3], axis=-1)
    keep = d_gt >= min_disp
    return float(np.median(d_pred[keep] / d_gt[keep])) if keep.any() else float("nan")


def scale_fit(T_pred: np.ndarray, T_gt: np.ndarray, *, min_disp: float = MIN_GT_DISPLACEMENT_M) -> float:
    """Least-squares sum t_pred . t_gt / sum |t_gt|^2 over frames with GT displacement >= ``min_disp`` (m); NaN if
    none."""
    P, G = _check_poses(T_pred, T_gt)
    t_pred, t_gt = P[:, :3, 3], G[:, :3, 3]
    keep = np.linalg.norm(t_gt, axis=-1) >= min_disp
    return float((t_pred[keep] * t_gt[keep]).sum() / (t_gt[keep] ** 2).sum()) if keep.any() else float("nan")


def _valid_depths(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pred, gt = np.asarray(pred, dtype=np.float64), np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape or pred.ndim != 3:
        raise DataError(f"depth maps must both be [n,h,w] on the same grid; got prediction {pred.shape} and "
                        f"GT {gt.shape} (resample GT with vi3_core.eval.metrics.resample_depth)")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(pred) & np.isfinite(gt) & (pred > 0) & (gt > 0)
    return pred, gt, valid


def absrel_median_aligned(pred: np.ndarray, gt: np.ndarray) -> float:
    """AbsRel after per-frame median scale alignment, mean over frames with valid pixels (NaN if none)."""
    pred, gt, valid = _valid_depths(pred, gt)
    P, G = np.where(valid, pred, np.nan), np.where(valid, gt, np.nan)
    frames = valid.any(axis=(1, 2))
    if not frames.any():
        return float("nan")
    P, G = P[frames], G[frames]
    s = np.nanmedian(G, axis=(1, 2)) / np.nanmedian(P, axis=(1, 2))
    per_frame = np.nanmean(np.abs(s[:, None, None] * P - G) / G, axis=(1, 2))
    return float(np.mean(per_frame))


def delta_inlier(pred: np.ndarray, gt: np.ndarray, *, threshold: float = DELTA_THRESHOLD) -> float:
    """Fraction of valid pixels with max(pred/gt, gt/pred) < ``threshold``, no alignment (NaN if none)."""
    pred, gt, valid = _valid_depths(pred, gt)
    if not valid.any():
        return float("nan")
    p, g = pred[valid], gt[valid]
    return float(np.mean(np.maximum(p / g, g / p) < threshold))


def scale_depth(pred: np.ndarray, gt: np.ndarray) -> float:
    """median(D_pred / D_gt) over the clip's valid pixels, no alignment (NaN if none)."""
    pred, gt, valid = _valid_depths(pred, gt)
    return float(np.median(pred[valid] / gt[valid])) if valid.any() else float("nan")


def resample_depth(depth: np.ndarray, K_src: np.ndarray, K_dst: np.ndarray, hw_dst: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resampling of depth maps [n,H,W] (intrinsics ``K_src`` [3,3]) onto the pixel grid of a
    pinhole camera with intrinsics ``K_dst`` [3,3] and size ``hw_dst`` = (h, w) of the same optical centre, e.g.
    the backbone's resized/cropped working resolution. Each destination pixel takes the source pixel its centre
    falls in, so no depth value is invented (invalid/NaN source pixels stay NaN); pixels outside the source image
    are NaN. Pixel centres are at integer coordinates (OpenCV convention)."""
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 3:
        raise DataError(f"depth must be [n,H,W], got {depth.shape}")
    K_src, K_dst = np.asarray(K_src, dtype=np.float64), np.asarray(K_dst, dtype=np.float64)
    h, w = hw_dst
    H, W = depth.shape[1:]
    u_dst, v_dst = np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)
    u = np.rint(K_src[0, 0] * (u_dst - K_dst[0, 2]) / K_dst[0, 0] + K_src[0, 2]).astype(np.int64)
    v = np.rint(K_src[1, 1] * (v_dst - K_dst[1, 2]) / K_dst[1, 1] + K_src[1, 2]).astype(np.int64)
    out = np.full((depth.shape[0], h, w), np.nan, dtype=np.float32)
    iu, iv = np.flatnonzero((u >= 0) & (u < W)), np.flatnonzero((v >= 0) & (v < H))
    out[:, iv[:, None], iu[None, :]] = depth[:, v[iv][:, None], u[iu][None, :]]
    return out


def geometry_metrics(T_pred: np.ndarray, T_gt: np.ndarray, depth_pred: np.ndarray | None = None,
                     depth_gt: np.ndarray | None = None) -> GeometryMetrics:
    """All six metrics of one clip; depth metrics are NaN when either depth is None."""
    has_depth = depth_pred is not None and depth_gt is not None
    nan = float("nan")
    return GeometryMetrics(
        trans_rmse_m=trans_rmse(T_pred, T_gt), rot_deg=rot_error_deg(T_pred, T_gt),
        scale_traj=scale_traj(T_pred, T_gt), scale_fit=scale_fit(T_pred, T_gt),
        absrel=absrel_median_aligned(depth_pred, depth_gt) if has_depth else nan,
        delta125=delta_inlier(depth_pred, depth_gt) if has_depth else nan,
        scale_depth=scale_depth(depth_pred, depth_gt) if has_depth else nan)


def init_metrics(init: InitResult, gt: GroundTruth) -> InitMetrics:
    """Errors of ``init`` (its g, v1 in B1 and bg) against the clip's GT."""
    g, v1, bg = gt_init_state(gt)
    v1_hat = np.asarray(init.v1, dtype=np.float64)
    v1_norm = float(np.linalg.norm(v1))
    ratio = float(np.linalg.norm(v1_hat)) / v1_norm if v1_norm > 0 else float("nan")
    bg_abs = bg_rel = float("nan")
    if bg is not None:
        bg_abs = float(np.linalg.norm(np.asarray(init.bg, dtype=np.float64) - bg))
        bg_rel = bg_abs / float(np.linalg.norm(bg)) if np.linalg.norm(bg) > 0 else float("nan")
    return InitMetrics(
        gravity_err_deg=float(np.degrees(so3.angle_between(init.g, g))),
        gyro_bias_err=bg_abs, gyro_bias_rel=bg_rel,
        v1_dir_deg=float(np.degrees(so3.angle_between(v1_hat, v1))),
        v1_mag_err=abs(ratio - 1.0), v1_mag_ratio=ratio)
