"""Feature tracks across a stream of frames, each frame tracked once as it arrives (a visual-inertial front end).

``FrameTracker.add`` follows the live corners from the previous frame into the new one with pyramidal Lucas-Kanade
(OpenCV), checks each against the flow back to where it came from (forward-backward) and against the epipolar
geometry of the pair (a fundamental matrix by RANSAC), and tops the live set up to its budget with FAST corners on a
grid: each cell of the frame holds its share, new corners only where no live track is near, so a track is never
re-detected on top of itself and texture-poor regions keep what corners they have. ``tracks(keys)`` reads the tracks
of any run of consecutive frames still in its history (a clip): a clip that starts with the last frame of the one
before continues its tracks, so the frames two clips share are tracked once and seen by the same tracks in both.

What the field's front ends do (VINS-Mono: 150 features, 30 px apart, fundamental-matrix RANSAC; OpenVINS: FAST on a
grid, KLT; Basalt: patches on a grid), on one thread: a 752x480 frame costs a few milliseconds, the Lucas-Kanade
passes most of it (OpenCV 5.1's Python binding takes no prebuilt pyramid, so each call builds its own).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from vi3_core.backbones.front_end import LONG_TRACK, FrameLosses

FAST_MIN, FAST_MAX = 5, 60  # the range the FAST threshold follows the scene in
MASK_PX = 4  # side of the squares the detection mask is drawn on


@dataclass(frozen=True)
class Tracks:
    """uv: [m,n,2] float64 pixel positions (x right, y down) of m tracks in the n frames, NaN where unseen; ids: [m]
    the tracks' identities in their ``FrameTracker`` (a track keeps its id from clip to clip)."""

    uv: np.ndarray
    ids: np.ndarray

    @property
    def visible(self) -> np.ndarray:
        """[m,n] bool: the track is observed in that frame."""
        return np.isfinite(self.uv[..., 0])

    def __len__(self) -> int:
        return len(self.uv)


#: One frame of the history: its key, its tracks' ids [k] and positions [k,2], what became of the tracks followed
#: into it
_Frame = tuple[float, np.ndarray, np.ndarray, FrameLosses]


@dataclass(frozen=True)
class TrackerOptions:
    """max_features: live tracks per frame (the budget the grid tops up to); grid: (columns, rows) of cells that share
    the budget; min_distance: px between a new corner and any live track; fast_threshold: FAST's intensity
    threshold at the start (it then follows the scene: up when a frame gives many times the corners it needs, down to
    ``FAST_MIN`` when it gives too few, as plain walls do); window: Lucas-Kanade's window side, px; levels: its
    pyramid levels above the frame; fb_threshold_px: the most a track's backward flow may miss its start; ransac_px:
    the epipolar distance (px) of a pair's inliers; history: frames whose tracks are kept for ``tracks`` (at least:
    ``FrameTracker.hold`` keeps more)."""

    max_features: int = 500
    grid: tuple[int, int] = (8, 5)
    min_distance: int = 12
    fast_threshold: int = 10
    window: int = 11
    levels: int = 3
    fb_threshold_px: float = 1.0
    ransac_px: float = 1.0
    history: int = 32

    def __post_init__(self) -> None:
        if not (self.max_features > 0 and min(self.grid) > 0 and self.window >= 3 and self.levels >= 0
                and self.fb_threshold_px > 0 and self.ransac_px > 0 and self.history >= 2):
            raise ValueError(f"TrackerOptions: invalid values in {self}")


class FrameTracker:
    """Tracks of a stream of frames (see the module docstring). Not thread-safe: one caller adds frames in order.

    ``add(key, gray)``: the next frame, ``key`` its stamp (increasing), gray [H,W] uint8; ``tracks(keys)``: the tracks
    of those frames (consecutive, all still in the history); ``losses(keys)``: where the tracks into those frames
    were lost; ``reset()`` forgets everything (time went back, frames were skipped). ``last_key``: the newest frame's
    key (None after a reset)."""

    def __init__(self, options: TrackerOptions | None = None) -> None:
        self.options = options or TrackerOptions()
        self._history_len = self.options.history
        self._fast = cv2.FastFeatureDetector_create(threshold=self.options.fast_threshold, nonmaxSuppression=True)
        self.reset()

    def reset(self) -> None:
        self._fast.setThreshold(self.options.fast_threshold)
        self._frames: deque[_Frame] = deque(maxlen=self._history_len)
        self._gray: np.ndarray | None = None
        self._ids = np.zeros(0, np.int64)
        self._pts = np.zeros((0, 2), np.float32)
        self._born = np.zeros(0, np.int64)  # [k] the frame (counted from the reset) each live track was first seen in
        self._count = 0  # frames added since the reset
        self._next_id = 0
        self._square_cells: np.ndarray | None = None  # [h,w] the grid cell of each square of the detection mask

    @property
    def frame_shape(self) -> tuple[int, ...] | None:
        """(H, W) of the frames tracked since the last reset (None before the first)."""
        return None if self._gray is None else self._gray.shape

    @property
    def last_key(self) -> float | None:
        return self._frames[-1][0] if self._frames else None

    def keys(self) -> list[float]:
        """The keys of the frames in the history, oldest first."""
        return [f[0] for f in self._frames]

    def add(self, key: float, gray: np.ndarray) -> None:
        if self._gray is not None and self._gray.shape != gray.shape:
            raise ValueError(f"frame of {gray.shape} after frames of {self._gray.shape}: reset the tracker first")
        losses = self._follow(gray) if len(self._pts) else FrameLosses(starts=1)
        before = len(self._ids)
        self._top_up(gray)
        added = len(self._ids) - before
        losses = replace(losses, frames=1, **({"seeded": added} if losses.starts else {"new": added}))
        self._gray = gray
        self._count += 1
        self._frames.append((float(key), self._ids.copy(), self._pts.astype(np.float64), losses))

    def _follow(self, gray: np.ndarray) -> FrameLosses:
        """The live tracks into ``gray``: forward and backward flow, the round trip within ``fb_threshold_px``, inside
        the frame, and inliers of the pair's epipolar geometry; returns what each check dropped."""
        o = self.options
        lk = dict(winSize=(o.window, o.window), maxLevel=o.levels,
                  criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03))
        prev = self._pts.reshape(-1, 1, 2)
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(self._gray, gray, prev, None, **lk)
        # the way back starts where the track came from and searches one pyramid level (VINS-Fusion's reverse
        # check): a consistent track needs no search, and the backward pass costs half the forward one
        back, st_b, _ = cv2.calcOpticalFlowPyrLK(gray, self._gray, nxt, prev.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                                 **{**lk, "maxLevel": min(o.levels, 1)})
        nxt, back = nxt.reshape(-1, 2), back.reshape(-1, 2)
        H, W = gray.shape
        flow = (st.ravel() == 1) & (st_b.ravel() == 1)
        round_trip = flow & (np.linalg.norm(back - self._pts, axis=1) < o.fb_threshold_px)
        ok = round_trip & (nxt[:, 0] >= 0) & (nxt[:, 0] <= W - 1) & (nxt[:, 1] >= 0) & (nxt[:, 1] <= H - 1)
        inside = int(ok.sum())
        if inside >= 16:  # epipolar outliers of the pair (a track that slid along an edge, or onto another)
            _, inl = cv2.findFundamentalMat(self._pts[ok], nxt[ok], cv2.FM_RANSAC, o.ransac_px, 0.99)
            if inl is not None:
                ok[np.flatnonzero(ok)[inl.ravel() == 0]] = False
        newest = self._frames[-1][3].new if self._frames else 0  # the last ``newest`` ids are the frame's new corners
        seen = self._count - self._born[~ok]  # frames each lost track was seen in: from its first to the frame before
        losses = FrameLosses(followed=len(ok), lost_no_flow=int((~flow).sum()),
                             lost_round_trip=int((flow & ~round_trip).sum()),
                             lost_border=int(round_trip.sum()) - inside, lost_epipolar=inside - int(ok.sum()),
                             new_lost=int((~ok[len(ok) - newest:]).sum()), ended_frames=int(seen.sum()),
                             ended_long=int((seen >= LONG_TRACK).sum()))
        self._ids, self._pts, self._born = self._ids[ok], nxt[ok].astype(np.float32), self._born[ok]
        return losses

    def _top_up(self, gray: np.ndarray) -> None:
        """New FAST corners in the grid's cells that hold fewer than their share of the budget (detected there only),
        the strongest first, none within ``min_distance`` of a live track or of another new one."""
        o = self.options
        need = o.max_features - len(self._pts)
        if need <= 0:
            return
        H, W = gray.shape
        cols, rows = o.grid
        have = np.bincount(cell_of(self._pts, W, H, cols, rows), minlength=cols * rows)
        quota = np.maximum(-(-o.max_features // (cols * rows)) - have, 0)
        if not quota.any():
            return
        kps = self._fast.detect(gray, self._free(quota, H, W))
        # the next frame's threshold: a textured scene gives thousands of corners where tens are needed
        t = self._fast.getThreshold()
        self._fast.setThreshold(int(min(t + 2, FAST_MAX) if len(kps) > 8 * need else
                                    max(t - 2, FAST_MIN) if len(kps) < 2 * need else t))
        if not kps:
            return
        xy = cv2.KeyPoint_convert(kps).astype(np.float32)
        score = np.fromiter((k.response for k in kps), np.float32, len(kps))
        # one corner per min_distance square (its strongest), then each cell's strongest up to its quota
        d = max(o.min_distance, 1)
        square = (xy[:, 1] // d).astype(np.int64) * (W // d + 1) + (xy[:, 0] // d).astype(np.int64)
        order = np.lexsort((-score, square))
        order = order[np.r_[True, square[order][1:] != square[order][:-1]]]
        cell = cell_of(xy, W, H, cols, rows)
        order = order[np.lexsort((-score[order], cell[order]))]
        c = cell[order]
        rank = np.arange(len(order)) - np.searchsorted(c, c)  # position within its cell, strongest first
        take = order[rank < quota[c]]
        take = take[np.argsort(-score[take])][:need]
        if len(take):
            self._pts = np.concatenate([self._pts, xy[take]])
            self._ids = np.concatenate([self._ids, self._next_id + np.arange(len(take))])
            self._born = np.concatenate([self._born, np.full(len(take), self._count)])
            self._next_id += len(take)

    def _free(self, quota: np.ndarray, H: int, W: int) -> np.ndarray:
        """[H,W] uint8 mask (255: FAST may look there) of the cells with a ``quota`` [cells] left, less a disc of
        ``min_distance`` around every live track; drawn on a grid of ``MASK_PX`` px squares, so that a corner is
        never within min_distance of a live track and rarely more than MASK_PX further than that."""
        o, s = self.options, MASK_PX
        h, w = -(-H // s), -(-W // s)
        occupied = np.zeros((h, w), np.uint8)
        ij = np.minimum((self._pts // s).astype(np.int64), [w - 1, h - 1])
        occupied[ij[:, 1], ij[:, 0]] = 1
        r = -(-o.min_distance // s)
        occupied = cv2.dilate(occupied, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        if self._square_cells is None or self._square_cells.shape != (h, w):  # once per frame size
            centres = (np.indices((h, w)).transpose(1, 2, 0)[..., ::-1].reshape(-1, 2) + 0.5) * s
            self._square_cells = cell_of(centres, W, H, *o.grid).reshape(h, w)
        wanted = quota[self._square_cells] > 0
        free = (wanted & (occupied == 0)).astype(np.uint8) * 255
        return cv2.resize(free, (w * s, h * s), interpolation=cv2.INTER_NEAREST)[:H, :W]

    def tracks(self, keys: Sequence[float]) -> Tracks:
        """The tracks of the frames ``keys`` (consecutive frames of the history, in order): [m, n, 2] for every
        track seen in at least one of them. Raises KeyError for a frame not in the history."""
        frames = self._history(keys)
        ids = np.unique(np.concatenate([f[1] for f in frames])) if frames else np.zeros(0, np.int64)
        uv = np.full((len(ids), len(frames), 2), np.nan)
        for j, (_, fid, pts, _) in enumerate(frames):
            uv[np.searchsorted(ids, fid), j] = pts
        return Tracks(uv=uv, ids=ids)

    def losses(self, keys: Sequence[float]) -> FrameLosses:
        """What became of the tracks followed into the frames ``keys`` (frames of the history), summed. Raises
        KeyError for a frame not in the history."""
        return sum((f[3] for f in self._history(keys)), FrameLosses())

    def hold(self, n: int) -> None:
        """Keep at least ``n`` frames in the history from now on (a clip of n frames must be there whole: the
        node's clips run to 64 frames, past ``TrackerOptions.history``)."""
        if n > self._history_len:
            self._history_len = n
            self._frames = deque(self._frames, maxlen=n)

    def _history(self, keys: Sequence[float]) -> list[_Frame]:
        index = {f[0]: i for i, f in enumerate(self._frames)}
        return [self._frames[index[float(k)]] for k in keys]


def cell_of(pts: np.ndarray, W: int, H: int, cols: int, rows: int) -> np.ndarray:
    """[k] grid cell (row-major) of each point [k,2] of a W x H frame cut into cols x rows cells of ceil(H / rows)
    by ceil(W / cols) px."""
    return (np.minimum(pts[:, 1] // -(-H // rows), rows - 1).astype(int) * cols
            + np.minimum(pts[:, 0] // -(-W // cols), cols - 1).astype(int))

