"""The point-cloud benchmark runs and reports consistent numbers (the 5 ms target is measured, not asserted:
test machines are shared)."""

from __future__ import annotations

import argparse

from msg_adapters.bench import FRAMES, HEIGHT, WIDTH, bench_pointcloud


def test_bench_pointcloud_reports_points_time_and_rate():
    out = bench_pointcloud(argparse.Namespace(repeats=3))
    assert out["points"] == FRAMES * HEIGHT * WIDTH == 8 * 120 * 188
    assert out["median_ms"] > 0 and out["repeats"] == 3
    assert abs(out["mpoints_per_s"] - out["points"] / out["median_ms"] / 1e3) <= 0.05 * out["mpoints_per_s"] + 0.1
