"""``vi3 bench pointcloud``: build a ``sensor_msgs/PointCloud2`` of 8 x 120 x 188 points (x, y, z, intensity)."""

from __future__ import annotations

import argparse
import time

import numpy as np

from msg_adapters.pointcloud import point_cloud2
from msg_adapters.types import jazzy_types

FRAMES, HEIGHT, WIDTH = 8, 120, 188
DEFAULT_REPEATS = 50
WARMUP = 3


def bench_pointcloud(args: argparse.Namespace) -> dict:
    """Median wall time of ``point_cloud2`` (rosbags Jazzy classes) over ``args.repeats`` builds.

    Input: one clip's back-projected depth maps as an unorganised cloud, float32 points and uint8 grey
    intensities. CDR serialisation is timed separately (``serialize_median_ms``): it is not part of building.
    """
    repeats = DEFAULT_REPEATS if getattr(args, "repeats", None) is None else max(int(args.repeats), 1)
    rng = np.random.default_rng(0)
    n = FRAMES * HEIGHT * WIDTH
    points = rng.uniform(-5.0, 5.0, size=(n, 3)).astype(np.float32)
    intensity = rng.integers(0, 256, size=n, dtype=np.uint8)
    types = jazzy_types()
    build = lambda: point_cloud2(points, intensity=intensity, stamp_ns=1, frame_id="world", types=types)
    for _ in range(WARMUP):
        msg = build()
    build_s, serialize_s = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        msg = build()
        t1 = time.perf_counter()
        build_s.append(t1 - t0)
    for _ in range(max(repeats // 10, 1)):
        t0 = time.perf_counter()
        types.typestore.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2")
        serialize_s.append(time.perf_counter() - t0)
    median_s = float(np.median(build_s))
    return {"points": n, "median_ms": round(median_s * 1e3, 3), "mpoints_per_s": round(n / median_s / 1e6, 1),
            "repeats": repeats, "serialize_median_ms": round(float(np.median(serialize_s)) * 1e3, 3)}
