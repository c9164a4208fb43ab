"""The continuous ``odom`` trajectory (REP-105: continuous, gravity-aligned, z up) that clips are chained into.

``T_OB`` are body (IMU frame) poses in odom; gravity in odom is [0, 0, -|g|] by construction.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vi3_core import so3

UP = np.array([0.0, 0.0, 1.0])


def gravity_align(R_ref: np.ndarray, g_B: np.ndarray) -> np.ndarray:
    """The attitude R_OB [3,3] nearest to ``R_ref`` that maps gravity ``g_B`` [3] (body frame) onto -z of odom:
    the smallest rotation of R_ref that levels it, so its yaw is kept."""
    u = R_ref @ (np.asarray(g_B, dtype=np.float64) / np.linalg.norm(g_B))
    axis = np.cross(u, -UP)
    angle = np.arctan2(np.linalg.norm(axis), float(u @ -UP))
    if np.linalg.norm(axis) < 1e-12:
        return R_ref.copy() if angle < 1.0 else so3.exp(np.pi * np.array([1.0, 0.0, 0.0])) @ R_ref
    return so3.exp(axis / np.linalg.norm(axis) * angle) @ R_ref


@dataclass
class ChainedClip:
    """One clip placed in odom: stamps [n] s, T_OB [n,4,4] body poses, v_O [n,3] body velocities in odom, m/s."""

    stamps: np.ndarray
    T_OB: np.ndarray
    v_O: np.ndarray


@dataclass
class Trajectory:
    """The chained odom trajectory: every frame once, in time order (an overlapping clip adds only its new frames).

    stamps: [N] s; T_OB: [N,4,4]; resets: first stamps of the clips that start a new segment, placed without a
    trustworthy IMU bridge from the previous chained clip (the first clip of the stream is not one), or the first
    after the stream was reset (``StreamEstimator.reset``: time went back, the trajectory then holds only the frames
    since, and its stamps may be earlier than the resets before). The position uncertainty of the newest frame
    relative to its segment's first frame: error_m, m, what the chained clips' relative errors add up to (each clip's
    metres flown, from the frame before its first new one, times its ``rel_sigma``, summed: the clips' scales and
    gravity are tied through the window, so their errors are correlated); bridge_var, m^2 per axis, what the IMU
    bridges between the segment's clips added (clips a busy worker dropped; independent, in quadrature)."""

    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    T_OB: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    resets: list[float] = field(default_factory=list)
    error_m: float = 0.0
    bridge_var: float = 0.0
    segment_start: int = 0  # index of the current segment's first frame

    def start_segment(self, t: float) -> None:
        """The next frames start a new segment, its first frame at ``t`` s; its uncertainty starts from zero."""
        self.resets.append(t)
        self.error_m = self.bridge_var = 0.0
        self.segment_start = len(self.stamps)

    def extend(self, clip: ChainedClip, *, rel_sigma: float = 0.0, bridge_sigma: float = 0.0) -> None:
        """Add the frames of ``clip`` after the newest one; ``rel_sigma``: the clip's relative position error (per
        metre flown), ``bridge_sigma``: m, the 1-sigma of the IMU bridge that placed it."""
        new = clip.stamps > (self.stamps[-1] if len(self.stamps) else -np.inf)
        P = np.concatenate([self.T_OB[max(len(self.stamps) - 1, self.segment_start):, :3, 3], clip.T_OB[new, :3, 3]])
        self.error_m += rel_sigma * float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum())
        self.bridge_var += bridge_sigma**2
        self.stamps = np.concatenate([self.stamps, clip.stamps[new]])
        self.T_OB = np.concatenate([self.T_OB, clip.T_OB[new]])
