"""Scale links between consecutive clips (beyond the paper): what two clips' predictions of the frames they share say
about the ratio of their model scales.

A 3DFM normalises every clip on its own, so two clips' model units differ by an unknown factor; on a frame both clips
predicted, every length is the same physical length in both units: lam_k / lam_(k-1) = depth_k / depth_(k-1) pixel by
pixel, and = |d_k| / |d_(k-1)| for the displacement d between two shared frames (lam = model units per metre). On
gentle motion a 0.7 s clip cannot pin its own scale at a 3DFM's noise, but the chain of such ratios lets the window's
clips share one scale, so scale evidence accumulates over the flight as gravity and the biases do. A backbone whose
front end holds one scale across clips (the ``classical`` keyframes) says the ratio itself (``Geometry.units_link``).

Depth: the per-pixel log ratio over the pixels both clips trust (finite, positive, confidence positive and at or
above ``CONF_QUANTILE`` of each map's positive confidences), summarised per block of a ``GRID`` x ``GRID`` grid of
each shared frame; the link is the median of the block medians, and its 1-sigma comes from their spread (a depth
error that varies across the image shows up there; per-pixel noise averages out), times the Student-t factor for the
number of blocks, with ``link_sigma_floor`` for the errors no spread within one frame shows. Poses (two or more
shared frames): the ratio of the norms of the first-to-last displacement, with the clips' own visual noise. When both
exist they must agree within ``AGREE_SIGMA`` sigma, else the link is refused; agreeing, they are combined by their
weights. The backbone's own ratio, to the clip the shared frames came from, joins them on the same terms (its sigma
with the floor; against the depth, also within both clips' trajectory-against-depth sigmas).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from itertools import combinations

import numpy as np

from vi3_core.fit import ScaleLink
from vi3_core.fit.linalg import Z975, t975
from vi3_core.types import Clip, Geometry, GroundTruth

GRID = 4  # blocks per image side for the depth link's sigma
MIN_BLOCK_PIXELS = 30  # a block counts when this many of its pixels are valid in both maps
MIN_BLOCKS = 6  # fewer valid blocks than this: no depth link
CONF_QUANTILE = 0.3  # pixels below this quantile of a map's finite confidences are left out
AGREE_SIGMA = 3.0  # depth and pose links further apart than this many combined sigmas refuse the link
MIN_DISPLACEMENT_SIGMAS = 5.0  # a pose link needs a displacement this many of its noise sigmas long


@dataclass(frozen=True)
class SharedFrames:
    """The last frames of a clip, kept for the next clip to share: stamps [k] s (and their header stamps_ns [k]
    int64, or None); images [k,H,W] or [k,H,W,3] uint8 (undistorted, as the backbone saw them); T_wc [k,4,4] in their
    clip's first camera frame and depth, conf [k,h,w] (model units of that clip); sigma_v: that clip's visual noise
    per axis (model units); gt: their ground truth (evaluation only, else None); clip_start: that clip's first stamp
    (s), which names it; bridge: None for a clip that joined the window; for one that did not (inconsistent with
    it), its own link to the window's newest member, through which the next clip links across it; traj_depth_sigma:
    that clip's ``Geometry``'s."""

    stamps: np.ndarray
    stamps_ns: np.ndarray | None
    images: np.ndarray
    T_wc: np.ndarray
    depth: np.ndarray
    conf: np.ndarray
    sigma_v: float
    gt: GroundTruth | None
    clip_start: float
    bridge: MeasuredLink | None = None
    traj_depth_sigma: float = 0.0

    @staticmethod
    def of(clip: Clip, geometry: Geometry, *, k: int, sigma_v: float,
           bridge: MeasuredLink | None = None) -> SharedFrames:
        """The last ``k`` frames of ``clip`` and of its prediction ``geometry``; sigma_v: its visual noise; bridge:
        see the class docstring."""
        tail = slice(clip.n - k, None)
        return SharedFrames(np.array(clip.stamps[tail]), None if clip.stamps_ns is None else
                            np.array(clip.stamps_ns[tail]), np.array(clip.images[tail]), np.array(geometry.T_wc[tail]),
                            np.array(geometry.depth[tail]), np.array(geometry.conf[tail]), float(sigma_v),
                            _gt_frames(clip.gt, tail), float(clip.stamps[0]), bridge, geometry.traj_depth_sigma)

    def __len__(self) -> int:
        return len(self.stamps)

    def starts(self, clip: Clip) -> bool:
        """Whether ``clip`` starts with these frames (the same header stamps where both have them: the IMU-time
        stamps move with the rig's estimated time offset)."""
        k = len(self)
        if clip.n <= k:
            return False
        if self.stamps_ns is not None and clip.stamps_ns is not None:
            return np.array_equal(clip.stamps_ns[:k], self.stamps_ns)
        return np.array_equal(clip.stamps[:k], self.stamps)

    def into(self, clip: Clip) -> Clip | None:
        """``clip`` with these frames in place of its first ones, or None where that cannot be: frames of another size,
        or no IMU (its ``imu_history``) back to them."""
        k = len(self)
        stamps = np.concatenate([self.stamps, clip.stamps[k:]])
        history = clip.imu_history
        if self.images.shape[1:] != clip.images.shape[1:] or history is None or not len(history) \
                or history.t[0] > stamps[0]:
            return None
        gt = None
        if self.gt is not None and clip.gt is not None:
            rest = _gt_frames(clip.gt, slice(k, None))
            depth = (np.concatenate([self.gt.depth, rest.depth]) if self.gt.depth is not None
                     and rest.depth is not None and self.gt.depth.shape[1:] == rest.depth.shape[1:] else None)
            gt = GroundTruth(T_WB=np.concatenate([self.gt.T_WB, rest.T_WB]),
                             v_WB=np.concatenate([self.gt.v_WB, rest.v_WB]), bg=clip.gt.bg, ba=clip.gt.ba,
                             g_W=clip.gt.g_W, depth=depth)
        stamps_ns = None if self.stamps_ns is None or clip.stamps_ns is None else \
            np.concatenate([self.stamps_ns, clip.stamps_ns[k:]])
        return replace(clip, stamps=stamps, images=np.concatenate([self.images, clip.images[k:]]),
                       imu=history.window(float(stamps[0]), float(stamps[-1])), gt=gt, stamps_ns=stamps_ns)


@dataclass(frozen=True)
class MeasuredLink:
    """A link measured on ``frames`` shared frames from ``source`` ("depth", "poses", "units" or those joined by "+";
    "units": the backbone's own ``UnitsLink``): ``link`` the
    ratio for the fit, and the clip it links to (``clip_start``, s); ``via``: the first stamp of a clip that did not
    join the window, when the link runs across it (the product of this clip's link to it and its own to the clip at
    clip_start), else None."""

    link: ScaleLink
    frames: int
    source: str
    clip_start: float
    via: float | None = None

    def describe(self) -> str:
        ratio = math.exp(self.link.log_ratio)
        shared = (f"shared with the clip at {self.via:.3f} s (not in the window), across it to the clip at "
                  f"{self.clip_start:.3f} s" if self.via is not None else
                  f"shared with the clip at {self.clip_start:.3f} s")
        return (f"{self.source} of {self.frames} frame(s) {shared}: scale ratio {ratio:.4f} +- "
                f"{100 * self.link.sigma:.2f} %")

    def across(self, bridge: MeasuredLink, via: float) -> MeasuredLink:
        """This link (to the clip at ``via``) continued by that clip's ``bridge`` to the window: ratios multiply,
        independent errors add."""
        return MeasuredLink(ScaleLink(self.link.log_ratio + bridge.link.log_ratio,
                                      math.hypot(self.link.sigma, bridge.link.sigma)),
                            self.frames, self.source, bridge.clip_start, via)


def depth_link(prev_depth: np.ndarray, prev_conf: np.ndarray, depth: np.ndarray, conf: np.ndarray, *,
               sigma_floor: float) -> tuple[float, float, int] | str:
    """(log ratio of ``depth`` over ``prev_depth``, its 1-sigma, blocks used), or why there is none. All maps
    [k,h,w] of the same k frames at the same resolution (z-depth, model units; confidence, higher is better)."""
    if prev_depth.shape != depth.shape:
        return f"depth maps of different shapes ({list(prev_depth.shape)} and {list(depth.shape)})"
    with np.errstate(invalid="ignore", divide="ignore"):
        valid = (np.isfinite(depth) & np.isfinite(prev_depth) & (depth > 0) & (prev_depth > 0)
                 & _trusted(conf) & _trusted(prev_conf))
        rho = np.where(valid, np.log(np.where(valid, depth, 1.0)) - np.log(np.where(valid, prev_depth, 1.0)), np.nan)
    k, h, w = rho.shape
    if h < GRID or w < GRID:
        return f"depth maps of {h}x{w} pixels: too small for a {GRID}x{GRID} grid"
    rows, cols = np.array_split(np.arange(h), GRID), np.array_split(np.arange(w), GRID)
    medians = []
    for r in rows:  # GRID x GRID blocks per frame: a handful of vectorised medians, not a per-pixel loop
        for c in cols:
            block = rho[:, r[0]:r[-1] + 1, c[0]:c[-1] + 1].reshape(k, -1)
            count = np.isfinite(block).sum(1)
            medians += [float(np.nanmedian(b)) for b, n in zip(block, count) if n >= MIN_BLOCK_PIXELS]
    if len(medians) < MIN_BLOCKS:
        return f"{len(medians)} depth blocks valid in both predictions (need {MIN_BLOCKS})"
    m = np.array(medians)
    center = float(np.median(m))
    spread = 1.4826 * float(np.median(np.abs(m - center)))
    # the median of B values: 1.2533 sigma / sqrt(B), with the Student-t factor for the spread's own uncertainty
    sigma = 1.2533 * spread / math.sqrt(len(m)) * t975(len(m) - 1) / Z975
    return center, math.hypot(sigma, sigma_floor), len(m)


def pose_link(prev_T_wc: np.ndarray, prev_sigma_v: float, T_wc: np.ndarray,
              sigma_v: float) -> tuple[float, float] | str:
    """(log ratio of the first-to-last displacement of ``T_wc`` [k,4,4] over that of ``prev_T_wc``, its 1-sigma), or
    why there is none; sigma_v: each clip's visual noise per axis in its own model units."""
    if len(T_wc) < 2:
        return "one shared frame: no displacement"
    d_prev = float(np.linalg.norm(prev_T_wc[-1, :3, 3] - prev_T_wc[0, :3, 3]))
    d = float(np.linalg.norm(T_wc[-1, :3, 3] - T_wc[0, :3, 3]))
    if not (np.isfinite(prev_sigma_v) and np.isfinite(sigma_v)):
        return "no visual noise estimate"
    rel_prev, rel = math.sqrt(2.0) * prev_sigma_v / max(d_prev, 1e-300), math.sqrt(2.0) * sigma_v / max(d, 1e-300)
    if min(d_prev, d) <= 0.0 or max(rel_prev, rel) > 1.0 / MIN_DISPLACEMENT_SIGMAS:
        return "the shared frames moved too little against the visual noise"
    return math.log(d / d_prev), math.hypot(rel_prev, rel)


def measure_link(shared: SharedFrames, geometry: Geometry, sigma_v: float, *, sigma_floor: float) -> MeasuredLink | str:
    """The link from the clip whose last frames are ``shared`` to the clip predicted as ``geometry`` (whose first
    len(shared) frames are the shared ones) with visual noise ``sigma_v``, or why there is none."""
    k = len(shared)
    found, why = {}, []
    d = depth_link(shared.depth, shared.conf, geometry.depth[:k], geometry.conf[:k], sigma_floor=sigma_floor)
    if isinstance(d, str):
        why.append(f"depth: {d}")
    else:
        found["depth"] = d[:2]
    p = pose_link(shared.T_wc, shared.sigma_v, geometry.T_wc[:k], sigma_v)
    if isinstance(p, str):
        why.append(f"poses: {p}")
    else:
        found["poses"] = (p[0], math.hypot(p[1], sigma_floor))
    u = geometry.units_link
    if u is not None and u.prev_start == shared.clip_start:
        found["units"] = (u.log_ratio, math.hypot(u.sigma, sigma_floor))
    if not found:
        return "; ".join(why)
    for a, b in combinations(found, 2):
        # the depth ratio reads the two clips' plane sweeps, the units their trajectories: apart by both clips' own
        # trajectory against their depth as well
        other = (geometry.traj_depth_sigma, shared.traj_depth_sigma) if {a, b} == {"depth", "units"} else ()
        if _apart(found[a], found[b], *other):
            return _disagree(a, found[a], b, found[b])
    return MeasuredLink(ScaleLink(*_combined(found)), k, "+".join(found), shared.clip_start)


def _apart(x: tuple[float, float], y: tuple[float, float], *other_sigmas: float) -> bool:
    """Whether two ratios (log ratio, sigma) are more than ``AGREE_SIGMA`` of their combined sigma (and
    ``other_sigmas``) apart."""
    return abs(x[0] - y[0]) > AGREE_SIGMA * math.hypot(x[1], y[1], *other_sigmas)


def _combined(parts: dict[str, tuple[float, float]]) -> tuple[float, float]:
    """The inverse-variance weighted mean of the ratios ``parts`` (log ratio, sigma) and its sigma (one: itself)."""
    if len(parts) == 1:
        return next(iter(parts.values()))
    w = np.array([sig**-2 for _, sig in parts.values()])
    return float(w @ np.array([r for r, _ in parts.values()]) / w.sum()), float(w.sum() ** -0.5)


def _disagree(a: str, x: tuple[float, float], b: str, y: tuple[float, float]) -> str:
    """Why a link is refused: its sources ``a`` and ``b`` (log ratio, sigma) disagree."""
    return (f"{a} ({math.exp(x[0]):.4f} +- {100 * x[1]:.2f} %) and {b} ({math.exp(y[0]):.4f} +- {100 * y[1]:.2f} %) "
            "disagree on the scale ratio")


def _trusted(conf: np.ndarray) -> np.ndarray:
    """Pixels whose confidence is positive and at least ``CONF_QUANTILE`` of the map's positive confidences [k,h,w]
    (zero: the backbone has no depth there)."""
    positive = conf[np.isfinite(conf) & (conf > 0)]
    if not positive.size:
        return np.zeros(conf.shape, bool)
    with np.errstate(invalid="ignore"):
        return conf >= np.quantile(positive, CONF_QUANTILE)


def _gt_frames(gt: GroundTruth | None, frames: slice) -> GroundTruth | None:
    """``gt`` of the clip's ``frames`` (per-frame arrays cut, biases as they are)."""
    if gt is None:
        return None
    depth = None if gt.depth is None else np.array(gt.depth[frames])
    return GroundTruth(T_WB=np.array(gt.T_WB[frames]), v_WB=np.array(gt.v_WB[frames]), bg=gt.bg, ba=gt.ba,
                       g_W=gt.g_W, depth=depth)


__all__ = ["MeasuredLink", "SharedFrames", "depth_link", "measure_link", "pose_link"]
