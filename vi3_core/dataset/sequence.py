"""A recorded visual-inertial sequence (whatever file it came from), its ground truth, and clips cut from it."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from vi3_core import so3
from vi3_core.dataset.calib import CameraCalib
from vi3_core.errors import CalibrationError, DataError
from vi3_core.types import CLIP_LENGTH, CLIP_STRIDE, Clip, GroundTruth, ImuSamples

G_W = np.array([0.0, 0.0, -9.81])


@dataclass
class GroundTruthTrack:
    """Body states in the world W (z up): t [M] s; T_WB [M,4,4]; v_WB [M,3] m/s; bg, ba [M,3] (or None);
    t_ns: [M] int64 stamps as recorded (derived from t when not given).

    When velocities are absent (bags carry poses only) they are derived from the positions by second-order
    central differences on the (possibly non-uniform) stamps, ``numpy.gradient``; biases then stay None.
    """

    t: np.ndarray
    T_WB: np.ndarray
    v_WB: np.ndarray | None = None
    bg: np.ndarray | None = None
    ba: np.ndarray | None = None
    g_W: np.ndarray = field(default_factory=lambda: G_W.copy())
    t_ns: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=np.float64)
        if self.t_ns is None:
            self.t_ns = np.round(self.t * 1e9).astype(np.int64)
        if len(self.t) < 2 or np.any(np.diff(self.t) <= 0):
            raise DataError(f"ground truth needs >= 2 strictly increasing stamps, got {len(self.t)}")
        if self.v_WB is None:
            self.v_WB = np.gradient(self.T_WB[:, :3, 3], self.t, axis=0)
        self._slerp = Slerp(self.t, Rotation.from_matrix(self.T_WB[:, :3, :3]))

    def covers(self, t: np.ndarray) -> bool:
        """Whether every stamp of t lies within the track."""
        return bool(len(t)) and self.t[0] <= np.min(t) and np.max(t) <= self.t[-1]

    def _lerp(self, values: np.ndarray, t: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(t, self.t, values[:, k]) for k in range(values.shape[1])], 1)

    def at(self, t: np.ndarray, *, depth: np.ndarray | None = None) -> GroundTruth:
        """Ground truth at stamps t [n] (slerp for rotations, linear otherwise); biases averaged over [t0, tn].

        Biases are NaN when the track has none. Raises DataError when a stamp lies outside the track.
        """
        t = np.asarray(t, dtype=np.float64)
        if not self.covers(t):
            raise DataError(f"stamps [{t.min():.6f}, {t.max():.6f}] s lie outside the ground truth "
                            f"[{self.t[0]:.6f}, {self.t[-1]:.6f}] s")
        T = so3.make_T(self._slerp(t).as_matrix(), self._lerp(self.T_WB[:, :3, 3], t))

        def bias(b):
            return np.full(3, np.nan) if b is None else self._lerp(b, t).mean(0)

        return GroundTruth(T_WB=T, v_WB=self._lerp(self.v_WB, t), bg=bias(self.bg), ba=bias(self.ba),
                           g_W=self.g_W.copy(), depth=depth)


@dataclass
class Sequence:
    """Camera frames, IMU and optional ground truth of one recording.

    stamps: [N] cam0 stamps, float64 s; stamps_ns: [N] the same stamps as recorded, int64 ns; imu: all IMU
    samples (imu_ns: their int64 ns stamps); calib: cam0 calibration (None when the source has none);
    gt: ground-truth track (None when absent). Images and depth are loaded on demand by ``load_image(i)``
    (raw mono8 [H,W] uint8, as recorded) and ``load_depth(i)`` ([H,W] float32 z-depth in metres, NaN invalid, or
    None for a frame without depth): on the undistorted image's grid, or on the raw (distorted) image's grid when
    ``depth_on_raw_grid``. depth_gt: what ground-truth depth the source has, for reports: "none", a description of
    the format read, or "unreadable: <why>" when a depth folder exists but cannot be used.
    has_images: False for a recording of IMU and ground truth only (its stamps are placed on the IMU clock).
    """

    name: str
    stamps: np.ndarray
    imu: ImuSamples
    calib: CameraCalib | None
    gt: GroundTruthTrack | None
    load_image: Callable[[int], np.ndarray] = field(repr=False)
    load_depth: Callable[[int], np.ndarray | None] | None = field(default=None, repr=False)
    stamps_ns: np.ndarray | None = None
    imu_ns: np.ndarray | None = None
    depth_on_raw_grid: bool = False
    depth_gt: str = "none"
    has_images: bool = True

    def __len__(self) -> int:
        return len(self.stamps)

    def image(self, i: int) -> np.ndarray:
        """Raw (distorted, as recorded) uint8 [H,W] mono8 image of frame i."""
        return self.load_image(int(i))

    def within(self, t0: float, t1: float) -> Sequence:
        """The frames stamped within [t0, t1] s (the IMU whole, for the clips' history), e.g. the span a reference
        trajectory covers. DataError when none is."""
        keep = np.flatnonzero((self.stamps >= t0) & (self.stamps <= t1))
        if len(keep) == 0:
            raise DataError(f"no frame of {self.name!r} lies within [{t0:.3f}, {t1:.3f}] s")
        i0, load_depth = int(keep[0]), self.load_depth
        return replace(self, stamps=self.stamps[keep],
                       stamps_ns=None if self.stamps_ns is None else self.stamps_ns[keep],
                       load_image=lambda i: self.load_image(i + i0),
                       load_depth=None if load_depth is None else (lambda i: load_depth(i + i0)))

    def gt_depth(self, i: int) -> np.ndarray | None:
        """[H,W] float32 z-depth (m) of the UNDISTORTED image of frame i, NaN where invalid; None if unknown.

        Depth recorded per raw pixel is carried through the undistortion map by nearest neighbour (each undistorted
        pixel takes the raw pixel its ray falls in: z-depth belongs to the ray, and no value is invented)."""
        depth = None if self.load_depth is None else self.load_depth(int(i))
        if depth is None or not self.depth_on_raw_grid:
            return depth
        if self.calib is None:
            raise DataError(f"sequence {self.name!r} has no camera calibration; cannot undistort its depth")
        return self.calib.undistorter().apply(depth, interpolation=cv2.INTER_NEAREST, border_value=np.nan)


def make_clip(seq: Sequence, indices: np.ndarray, *, with_depth: bool = True, history_s: float = 2.0,
              lead_s: float = 0.0, with_images: bool = True) -> Clip:
    """The clip of frames ``indices`` [n]: undistorted images (an empty [n,0,0] array without ``with_images``),
    ``calib.undistorter().K``, ``T_BC``, the IMU window with >= 1 sample beyond each end, ``imu_history`` (the
    ``history_s`` seconds before the clip, the clip, and ``lead_s`` seconds after it, as the node's clip buffer waits
    for them), ground truth at the stamps when the track covers them (depth maps included when ``with_depth``), and
    the frames' recorded stamps (ns)."""
    if seq.calib is None:
        raise DataError(f"sequence {seq.name!r} has no camera calibration; cannot undistort its images")
    idx = np.asarray(indices, dtype=np.int64)
    if idx.ndim != 1 or len(idx) == 0 or idx.min() < 0 or idx.max() >= len(seq):
        raise DataError(f"clip indices {idx.tolist()} out of range for {len(seq)} frames of {seq.name!r}")
    stamps = seq.stamps[idx]
    und = seq.calib.undistorter()
    images = (np.stack([und.apply(_fitting_frame(seq, i)) for i in idx]) if with_images
              else np.zeros((len(idx), 0, 0), np.uint8))
    if not seq.imu.covers(stamps[0], stamps[-1]):
        raise DataError(f"IMU of {seq.name!r} does not cover the clip [{stamps[0]:.6f}, {stamps[-1]:.6f}] s")
    imu = seq.imu.window(stamps[0], stamps[-1], margin=1)
    gt = None
    if seq.gt is not None and seq.gt.covers(stamps):
        depth = None
        if with_depth and seq.load_depth is not None:
            maps = [seq.gt_depth(i) for i in idx]
            shape = next((d.shape for d in maps if d is not None), None)
            if shape is not None:  # a frame without depth is all invalid
                depth = np.stack([np.full(shape, np.nan, np.float32) if d is None else d for d in maps])
        gt = seq.gt.at(stamps, depth=depth)
    history = seq.imu.window(stamps[0] - history_s, stamps[-1] + lead_s, margin=1)
    return Clip(stamps=stamps, images=images, K=und.K.copy(), T_BC=seq.calib.T_BC.copy(), imu=imu, gt=gt,
                imu_history=history, stamps_ns=None if seq.stamps_ns is None else seq.stamps_ns[idx])


def gt_camera_poses(gt: GroundTruth, T_BC: np.ndarray) -> np.ndarray:
    """GT camera poses [n,4,4] of a clip in its first camera frame: T_WC = T_WB T_BC, re-anchored at frame 0."""
    return so3.relative_to_first(np.einsum("nij,jk->nik", np.asarray(gt.T_WB, dtype=np.float64), T_BC))


def _fitting_frame(seq: Sequence, i: int) -> np.ndarray:
    """Raw frame ``i``, or CalibrationError naming it when it does not fit the calibration (never stretched)."""
    image = seq.image(i)
    problem = seq.calib.check_frame(image)
    if problem is not None:
        raise CalibrationError(f"sequence {seq.name!r}, frame {i} (t = {seq.stamps[i]:.6f} s): {problem}")
    return image


def sample_clips(n_total: int, *, n: int = CLIP_LENGTH, stride: int = CLIP_STRIDE, mode: str = "paper",
                 hop: int | None = None) -> list[np.ndarray]:
    """Frame indices of clips of ``n`` frames ``stride`` apart in a sequence of ``n_total`` frames.

    "paper": three clips at the start, middle and end of the sequence (as in the paper's evaluation);
    "sliding": a clip every ``hop`` frames (default n * stride, i.e. back to back). Each entry is [n] int64.
    """
    span = (n - 1) * stride + 1
    if n < 1 or stride < 1:
        raise ValueError(f"n and stride must be >= 1, got n={n}, stride={stride}")
    if span > n_total:
        raise DataError(f"a clip of {n} frames at stride {stride} spans {span} frames; the sequence has {n_total}")
    offsets = np.arange(n, dtype=np.int64) * stride
    if mode == "paper":
        starts = sorted({0, (n_total - span) // 2, n_total - span})
    elif mode == "sliding":
        step = hop if hop is not None else n * stride
        if step < 1:
            raise ValueError(f"hop must be >= 1, got {hop}")
        starts = range(0, n_total - span + 1, step)
    else:
        raise ValueError(f"unknown clip sampling mode {mode!r}; choose 'paper' or 'sliding'")
    return [s + offsets for s in starts]
