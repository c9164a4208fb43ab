"""Feature tracks through a clip: Shi-Tomasi corners followed frame to frame by pyramidal Lucas-Kanade (OpenCV).

A forward-backward check drops tracks whose round trip misses its start, and fresh corners are detected in
every frame but the last (a corner seen once constrains nothing) away from the live tracks, so a track may start late
but never resumes after it is lost.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Tracks:
    """uv: [m,n,2] float64 pixel positions (x right, y down) of m tracks in the n frames, NaN where unseen."""

    uv: np.ndarray

    @property
    def visible(self) -> np.ndarray:
        """[m,n] bool: the track is observed in that frame."""
        return np.isfinite(self.uv[..., 0])

    def __len__(self) -> int:
        return len(self.uv)


def _detect(gray: np.ndarray, live: np.ndarray, *, count: int, min_distance: int, quality: float) -> np.ndarray:
    """[k,2] new corners of ``gray`` at least ``min_distance`` px from the live points [l,2]."""
    if count <= 0:
        return np.zeros((0, 2))
    mask = np.full(gray.shape, 255, np.uint8)
    for x, y in np.round(live).astype(int):  # one small disc per live track (OpenCV draw call, not pixel work)
        cv2.circle(mask, (int(x), int(y)), min_distance, 0, -1)
    pts = cv2.goodFeaturesToTrack(gray, maxCorners=count, qualityLevel=quality, minDistance=min_distance,
                                  mask=mask, blockSize=7)
    return np.zeros((0, 2)) if pts is None else pts.reshape(-1, 2).astype(np.float64)


def track_features(gray: np.ndarray, *, max_features: int = 1000, min_distance: int = 10,
                   quality: float = 0.005, fb_threshold_px: float = 1.0, window: int = 21,
                   levels: int = 3) -> Tracks:
    """Track corners through ``gray`` [n,H,W] uint8.

    Each frame keeps up to ``max_features`` live tracks; a track is dropped when the backward flow misses its
    start by more than ``fb_threshold_px`` or leaves the image.
    """
    n, H, W = gray.shape
    lk = dict(winSize=(window, window), maxLevel=levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    start = _detect(gray[0], np.zeros((0, 2)), count=max_features, min_distance=min_distance, quality=quality)
    live_idx = np.arange(len(start))
    rows = np.full((len(start), n, 2), np.nan)
    rows[:, 0] = start
    for i in range(1, n):
        prev = rows[live_idx, i - 1].astype(np.float32).reshape(-1, 1, 2)
        if len(prev):
            nxt, st, _ = cv2.calcOpticalFlowPyrLK(gray[i - 1], gray[i], prev, None, **lk)
            back, st_b, _ = cv2.calcOpticalFlowPyrLK(gray[i], gray[i - 1], nxt, None, **lk)
            nxt, fb = nxt.reshape(-1, 2), np.linalg.norm(back.reshape(-1, 2) - prev.reshape(-1, 2), axis=1)
            ok = (st.ravel() == 1) & (st_b.ravel() == 1) & (fb < fb_threshold_px)
            ok &= (nxt[:, 0] >= 0) & (nxt[:, 0] <= W - 1) & (nxt[:, 1] >= 0) & (nxt[:, 1] <= H - 1)
            rows[live_idx[ok], i] = nxt[ok]
            live_idx = live_idx[ok]
        if i == n - 1:
            break
        fresh = _detect(gray[i], rows[live_idx, i], count=max_features - len(live_idx),
                        min_distance=min_distance, quality=quality)
        if len(fresh):
            block = np.full((len(fresh), n, 2), np.nan)
            block[:, i] = fresh
            live_idx = np.concatenate([live_idx, np.arange(len(rows), len(rows) + len(fresh))])
            rows = np.concatenate([rows, block])
    return Tracks(uv=rows)
