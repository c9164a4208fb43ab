"""``vi3 bench init``: wall time of one GT-free initialisation on simulated EuRoC-like clips."""

from __future__ import annotations

import time

import numpy as np

from vi3_core.init.initializer import initialise
from vi3_core.sim.visual import PoseNoise, make_init_case


def bench_init(args) -> dict:
    """Median and p90 milliseconds per clip (n = 8, stride 2, EuRoC IMU noise and accelerometer bias, 3 mm / 0.1 deg
    of pose noise)."""
    n = args.repeats or 200
    cases = [make_init_case(i, pose_noise=PoseNoise(pos_m=0.003, rot_deg=0.1)) for i in range(n)]
    initialise(cases[0].geometry, cases[0].imu, cases[0].stamps, cases[0].T_BC)  # warm-up (imports, caches)
    ms = np.empty(n)
    for k, c in enumerate(cases):
        t0 = time.perf_counter()
        initialise(c.geometry, c.imu, c.stamps, c.T_BC)
        ms[k] = (time.perf_counter() - t0) * 1e3
    return {"median_ms": float(np.median(ms)), "p90_ms": float(np.percentile(ms, 90)), "n": n}
