"""``vi3 bench ttr``: milliseconds per test-time-refinement step on one 8-frame generated EuRoC-format clip."""

from __future__ import annotations

from vi3_core.anchor.anchor import anchor
from vi3_core.anchor.options import AnchorOptions
from vi3_core.backbones.bench_device import DeviceClock, build_bench_backbone
from vi3_core.dataset.generate import bench_clip
from vi3_core.init.oracle import oracle_init
from vi3_core.threads import torch_thread_settings


def bench_ttr(args) -> dict:
    """TTR on the middle clip (n = 8, stride 2) of a generated 3 s sequence; ``args.repeats`` = steps (default
    40). ``ms_per_iter`` is the median step time (the first steps of a process carry one-time kernel warm-up);
    ``total_s`` is the whole clip (backbone, initialisation and every step; device-synchronised, ``DeviceClock``),
    ``backbone_s`` its base forward, ``init_ms`` its initialisation (``init``: "gt_free", or "ground_truth" with
    random weights), ``ttr_s`` its steps, and ``paper_total_s`` = init + 160 x ms_per_iter, the paper's per-clip
    "Total" (K = 160, base forward excluded).
    Also the backbone's description (``build_bench_backbone``), on CUDA peak_gpu_mem_mb (weights included), and
    ``threads`` and ``omp_wait_policy``, the torch settings it ran with (``vi3_core.threads.torch_thread_settings``)."""
    steps = args.repeats or 40
    backbone, described = build_bench_backbone(args)  # first: a bad option fails before any data is made
    clip = bench_clip()
    clock = DeviceClock(backbone.device)
    # Random weights give geometry the GT-free initialisation rightly rejects, and a step costs the same whatever
    # the weights: with --random-init the TTR target comes from the sequence's ground truth.
    init = (lambda base: oracle_init(clip, base)) if args.random_init else None
    with clock.lap() as lap:
        result = anchor(clip, backbone, mode="ttr", options=AnchorOptions(ttr_steps=steps), init=init)
    h, w = result.geometry.depth.shape[1:]
    nan = float("nan")
    t = result.timings
    ms_per_iter, init_s = t.get("ttr_ms_per_iter", nan), t.get("init_s", nan)
    return {"ms_per_iter": ms_per_iter, "steps": steps, "total_s": lap.wall_s, "backbone_s": t["backbone_s"],
            "init_ms": 1e3 * init_s, "ttr_s": t.get("ttr_s", nan),
            "paper_total_s": init_s + AnchorOptions().ttr_steps * ms_per_iter / 1e3, "frames": clip.n,
            "resolution": [int(h), int(w)], **described, "init": "ground_truth" if args.random_init else "gt_free",
            "init_status": result.init.status.value, "mode": result.mode, **clock.memory(),
            **torch_thread_settings()}
