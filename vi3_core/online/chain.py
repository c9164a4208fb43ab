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
    trustworthy IMU bridge from the previous chained clip (the first clip of the stream is not one)."""

    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    T_OB: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    resets: list[float] = field(default_factory=list)

    def extend(self, clip: ChainedClip) -> None:
        new = clip.stamps > (self.stamps[-1] if len(self.stamps) else -np.inf)
        self.stamps = np.concatenate([self.stamps, clip.stamps[new]])
        self.T_OB = np.concatenate([self.T_OB, clip.T_OB[new]])
