"""Keyframes that hold the ``classical`` front end's scale from clip to clip (beyond the paper).

A clip's bundle adjustment alone leaves its scale gauge free: the points it carries from the clip before start it at
that clip's scale, and its own frames, 0.56 s of gentle motion, then move it by what their short baselines allow.
On a handheld camera whose tracks live three frames the scale so handed on walked some 5 % per sqrt(s) against an
offline reconstruction (docs/accuracy.md). A visual odometry front end holds it instead against keyframes: frames of
the last few seconds whose poses are fixed, seen again by the new frames' points through descriptor matching, so that
the new poses are triangulated against baselines of seconds rather than of a clip (ORB-SLAM's local map, in small).

``KeyframeMap`` keeps the last ``size`` keyframes, each a frame's ORB corners (pixels, 256-bit descriptors) and its
camera-to-map pose; ``anchors`` finds, for a clip that continues the map (it starts with the frame the last clip ended
on), where its triangulated points appear in each keyframe: the keyframe's corner nearest in descriptor within
``radius_px`` of the point's projection, unambiguous by Lowe's ratio and one-to-one; ``extend`` then records the
clip's last frame (a keyframe where it is ``min_baseline`` of the scene's depth from the newest one).
The map's frame and units are those of the first clip after a reset; a clip that does not continue it resets it.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from vi3_core import so3
from vi3_core.backbones.classical.tracks import Tracks

PATCH = 31  # px, the side of ORB's descriptor patch (its default)


@dataclass(frozen=True)
class Keyframe:
    """key: the frame's stamp (s); uv [k,2] px and desc [k,32] uint8 its ORB corners (upright, at full resolution);
    T_mc [4,4] camera-to-map (map units); tree: a k-d tree of uv."""

    key: float
    uv: np.ndarray
    desc: np.ndarray
    T_mc: np.ndarray
    tree: cKDTree


@dataclass(frozen=True)
class Anchors:
    """Where a clip's points are seen in the keyframes: uv [m,K,2] px (NaN: not matched) and the keyframes' poses
    R_wc [K,3,3], t_wc [K,3] in the clip's world (its first camera, at the map's scale)."""

    uv: np.ndarray
    R_wc: np.ndarray
    t_wc: np.ndarray

    @property
    def count(self) -> int:
        return int(np.isfinite(self.uv[..., 0]).sum())


class KeyframeMap:
    """The last ``size`` keyframes of the front end (see the module docstring). Not thread-safe."""

    def __init__(self, *, size: int = 6, min_baseline: float = 0.02, radius_px: float = 12.0, max_hamming: int = 64,
                 ratio: float = 0.8, n_features: int = 1000) -> None:
        self.size, self.min_baseline, self.radius_px = size, min_baseline, radius_px
        self.max_hamming, self.ratio = max_hamming, ratio
        self._orb = cv2.ORB_create(nfeatures=n_features, edgeThreshold=PATCH, patchSize=PATCH)
        self.reset()

    def reset(self) -> None:
        self.frames: deque[Keyframe] = deque(maxlen=self.size)
        self._last: tuple[float, np.ndarray] | None = None  # the last clip's last frame: key and its T_mc [4,4]

    def continues(self, first_key: float) -> bool:
        """Whether a clip starting at ``first_key`` starts where the map's last clip ended."""
        return self._last is not None and self._last[0] == first_key

    def _describe(self, gray: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Upright ORB descriptors [k',32] at the pixels uv [k,2] of ``gray`` and the indices [k'] of the pixels that
        had one (those a patch from the border)."""
        H, W = gray.shape
        inside = np.flatnonzero((uv >= PATCH).all(1) & (uv[:, 0] < W - PATCH) & (uv[:, 1] < H - PATCH))
        if not len(inside):
            return np.zeros((0, 32), np.uint8), inside
        kps, desc = self._orb.compute(gray, cv2.KeyPoint_convert(uv[inside].astype(np.float32), size=PATCH))
        if desc is None or not kps:
            return np.zeros((0, 32), np.uint8), np.zeros(0, np.int64)
        # compute may drop keypoints: each one kept is found again by its position
        return desc, inside[cKDTree(uv[inside]).query(cv2.KeyPoint_convert(kps))[1]]

    def anchors(self, gray: np.ndarray, K: np.ndarray, tracks: Tracks, points: np.ndarray,
                first_key: float) -> Anchors | None:
        """The keyframes' observations of ``points`` [m,3] (clip world, NaN: none) of ``tracks`` in the clip's frames
        ``gray`` [n,H,W] (``K`` [3,3] px); None where the clip does not continue the map or no keyframe is older than
        its first frame."""
        if not self.continues(first_key):
            return None
        frames = [f for f in self.frames if f.key < first_key]
        if not frames:
            return None
        T_m0 = self._last[1]
        T_0m = so3.inv_T(T_m0)
        T = np.stack([T_0m @ f.T_mc for f in frames])  # keyframe cameras in the clip's world
        good = np.flatnonzero(np.isfinite(points[:, 0]))
        vis = tracks.visible[good]
        # each point described in the frame in the middle of its run (its look changes least from there)
        runs = np.cumsum(vis, 1)
        mid = np.argmax(runs >= (vis.sum(1, keepdims=True) + 1) // 2, axis=1)
        desc = np.zeros((len(good), 32), np.uint8)
        has = np.zeros(len(good), bool)
        for j in np.unique(mid):
            rows = np.flatnonzero(mid == j)
            d, kept = self._describe(gray[j], tracks.uv[good[rows], j])
            desc[rows[kept]], has[rows[kept]] = d, True
        rows = np.flatnonzero(has)
        uv = np.full((len(points), len(frames), 2), np.nan)
        X = points[good[rows]]
        for k, (f, Tk) in enumerate(zip(frames, T)):
            Xc = (X - Tk[:3, 3]) @ Tk[:3, :3]
            ahead = np.flatnonzero(Xc[:, 2] > 0)
            if not len(ahead) or not len(f.uv):
                continue
            proj = Xc[ahead, :2] / Xc[ahead, 2:] * np.diag(K)[:2] + K[:2, 2]
            q, t = self._match(desc[rows[ahead]], proj, f)
            uv[good[rows[ahead[q]]], k] = f.uv[t]
        return Anchors(uv, T[:, :3, :3], T[:, :3, 3])

    def _match(self, desc: np.ndarray, proj: np.ndarray, f: Keyframe) -> tuple[np.ndarray, np.ndarray]:
        """Matches (query rows [j], keyframe corners [j]) of descriptors desc [q,32] projected at proj [q,2] px into
        keyframe ``f``: among its corners within ``radius_px``, the nearest in Hamming distance, at most
        ``max_hamming`` and under ``ratio`` times the second nearest; a corner two queries take is given to neither."""
        pairs = cKDTree(proj).sparse_distance_matrix(f.tree, self.radius_px, output_type="ndarray")
        if not len(pairs):
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        qi, ti = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
        ham = np.unpackbits(desc[qi] ^ f.desc[ti], axis=1).sum(1)
        order = np.lexsort((ham, qi))
        qi, ti, ham = qi[order], ti[order], ham[order]
        first = np.r_[True, qi[1:] != qi[:-1]]  # each query's nearest
        has_second = np.r_[~first[1:], False] & first  # a query with another candidate: its second follows its first
        second = np.where(has_second, np.r_[ham[1:], 0], np.iinfo(np.int64).max)
        take = first & (ham <= self.max_hamming) & (ham < self.ratio * second)
        q, t = qi[take], ti[take]
        once = np.bincount(t, minlength=len(f.uv))[t] == 1
        return q[once], t[once]

    def extend(self, gray_last: np.ndarray, key_last: float, first_key: float, T_0l: np.ndarray,
               depth: float, *, same_scale: bool) -> None:
        """Record the clip (first frame ``first_key``) that ended on ``gray_last`` [H,W] (stamp ``key_last``) at
        T_0l [4,4] in its first camera's frame: its end is the next clip's start; it becomes a keyframe when its centre
        is ``min_baseline`` x ``depth`` (the scene's median depth, map units) from the newest keyframe's, or the map
        has none. A clip that does not continue the map, or not at its scale (``same_scale`` False: it started
        afresh and no keyframe held it), starts it afresh."""
        if not (same_scale and self.continues(first_key)):
            self.reset()
            T_m0 = np.eye(4)
        else:
            T_m0 = self._last[1]
        T_ml = T_m0 @ T_0l
        self._last = (key_last, T_ml)
        if self.frames and np.linalg.norm(T_ml[:3, 3] - self.frames[-1].T_mc[:3, 3]) < self.min_baseline * depth:
            return
        kps = self._orb.detect(gray_last, None)
        if not kps:
            return
        uv = cv2.KeyPoint_convert(kps).astype(np.float64)
        desc, kept = self._describe(gray_last, uv)
        self.frames.append(Keyframe(key_last, uv[kept], desc, T_ml, cKDTree(uv[kept])))
