"""Data checks before initialisation. Each returns a human-readable reason, or None when the data is usable,
so that bad data becomes a ``rejected`` status instead of an exception."""

from __future__ import annotations

import numpy as np

from vi3_core.init.options import InitOptions
from vi3_core.types import Geometry, ImuSamples


def check_stamps(stamps: np.ndarray) -> str | None:
    if len(stamps) < 3:
        return f"need at least 3 frames to observe acceleration, got {len(stamps)}"
    if not np.all(np.isfinite(stamps)):
        return "frame stamps contain NaN/Inf"
    if np.any(np.diff(stamps) <= 0):
        i = int(np.argmax(np.diff(stamps) <= 0))
        return f"frame stamps not strictly increasing at index {i + 1} ({stamps[i]:.6f} -> {stamps[i + 1]:.6f} s)"
    return None


def check_imu(imu: ImuSamples, stamps: np.ndarray, options: InitOptions) -> str | None:
    """NaN/Inf samples, non-monotonic stamps, coverage of [stamps[0], stamps[-1]], gaps, samples per interval. A gap
    is longer than ``max_imu_gap`` by the integer ns stamps where the samples carry them (``ImuSamples.t_ns``), so a
    gap of exactly the limit passes at any epoch; by float seconds otherwise."""
    if len(imu) < 2:
        return f"too few IMU samples ({len(imu)})"
    bad = ~(np.isfinite(imu.t) & np.isfinite(imu.gyro).all(1) & np.isfinite(imu.accel).all(1))
    if bad.any():
        return f"{int(bad.sum())} IMU sample(s) with NaN/Inf (first at t={imu.t[np.argmax(bad)]:.6f} s)"
    dt = np.diff(imu.t)
    if np.any(dt <= 0):
        i = int(np.argmax(dt <= 0))
        return f"IMU stamps not strictly increasing at t={imu.t[i]:.6f} s (next {imu.t[i + 1]:.6f} s)"
    if imu.t[0] > stamps[0] or imu.t[-1] < stamps[-1]:
        return (f"IMU covers [{imu.t[0]:.6f}, {imu.t[-1]:.6f}] s but the clip spans "
                f"[{stamps[0]:.6f}, {stamps[-1]:.6f}] s")
    span = (imu.t[1:] > stamps[0]) & (imu.t[:-1] < stamps[-1])
    if imu.t_ns is not None:  # stamps that came as ns are compared in ns, exactly
        gaps = np.diff(imu.t_ns)
        over = gaps > round(options.max_imu_gap * 1e9)
        dt = gaps * 1e-9
    else:
        over = dt > options.max_imu_gap
    if (span & over).any():
        i = int(np.flatnonzero(span)[np.argmax(dt[span])])
        d = _decimals_apart(dt[i], options.max_imu_gap)
        return f"IMU gap of {dt[i]:.{d}f} s > max_imu_gap {options.max_imu_gap:.{d}f} s at t={imu.t[i]:.6f} s"
    counts = np.diff(np.searchsorted(imu.t, stamps))
    if counts.min() < options.min_samples_per_interval:
        i = int(np.argmin(counts))
        return (f"only {int(counts[i])} IMU sample(s) between frames {i} and {i + 1} "
                f"(need {options.min_samples_per_interval})")
    return None


def _decimals_apart(a: float, b: float) -> int:
    """The fewest decimals (at least 3) at which ``a`` and ``b`` print differently, so that a message comparing
    them never shows two equal numbers (0.0500001 vs 0.05 needs 7)."""
    return next((d for d in range(3, 17) if f"{a:.{d}f}" != f"{b:.{d}f}"), 17)


def check_geometry(geometry: Geometry, n: int) -> str | None:
    if geometry.n != n:
        return f"geometry has {geometry.n} poses for {n} frame stamps"
    if not np.all(np.isfinite(geometry.T_wc)):
        return "backbone poses contain NaN/Inf"
    return None
