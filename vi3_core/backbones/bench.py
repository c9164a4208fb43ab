"""``vi3 bench backbone``: seconds per clip of a backbone's ``predict`` (preprocess + no-grad forward) on one
8-frame clip (stride 2 at 20 Hz) of a generated EuRoC-format sequence, 752x480 input."""

from __future__ import annotations

import numpy as np

from vi3_core.backbones.bench_device import DeviceClock, build_bench_backbone
from vi3_core.dataset.generate import bench_clip
from vi3_core.threads import torch_thread_settings


def bench_backbone(args) -> dict:
    """Wall and process-CPU seconds per clip over ``args.repeats`` runs (default 5) after one warm-up run, each
    read after synchronising the device (``DeviceClock``).

    Keys: median_s, min_s, cpu_median_s (process CPU time, less sensitive to other load on the machine),
    frames, resolution (input [H, W]), working_resolution ([h, w] of depth), repeats, the backbone's description
    (backbone, device, dtype, random_init: ``build_bench_backbone``), on CUDA peak_gpu_mem_mb (weights included),
    threads and omp_wait_policy (``vi3_core.threads.torch_thread_settings``),
    and for backbones that report them (``Backbone.diagnostics``) stages_s, the per-stage seconds of the last run,
    and status, the clip's outcome.
    """
    repeats = args.repeats or 5
    backbone, described = build_bench_backbone(args)  # first: a bad option fails before any data is made
    clip = bench_clip()
    clock = DeviceClock(backbone.device)
    geometry = backbone.predict(clip.images, clip.K)  # warm-up: imports, allocator, thread pools, kernel choice
    laps = []
    for _ in range(repeats):
        with clock.lap() as lap:
            geometry = backbone.predict(clip.images, clip.K)
        laps.append(lap)
    wall, cpu = np.array([lap.wall_s for lap in laps]), np.array([lap.cpu_s for lap in laps])
    out = {"median_s": float(np.median(wall)), "min_s": float(wall.min()), "cpu_median_s": float(np.median(cpu)),
           "frames": int(clip.n), "resolution": [int(s) for s in clip.images.shape[1:3]],
           "working_resolution": [int(s) for s in geometry.depth.shape[1:]], **described, "repeats": repeats,
           **clock.memory(), **torch_thread_settings()}
    diagnostics = backbone.diagnostics()
    stages = {k: round(float(v), 4) for k, v in diagnostics.items() if k.endswith("_s")}
    if stages:
        out["stages_s"] = stages
    if "status" in diagnostics:
        out["status"] = diagnostics["status"]
    return out
