"""``vi3 bench ttr``: milliseconds per test-time-refinement step on one 8-frame generated EuRoC-format clip."""

from __future__ import annotations

import os
from pathlib import Path

from vi3_core.anchor.anchor import anchor
from vi3_core.anchor.options import AnchorOptions
from vi3_core.backbones import make_backbone
from vi3_core.dataset.asl import read_asl
from vi3_core.dataset.generate import cached_sequence
from vi3_core.dataset.sequence import make_clip, sample_clips
from vi3_core.threads import torch_thread_settings


def bench_cache_dir() -> Path:
    """Where benchmarks keep generated sequences (``VI3_CACHE``, default ``.cache/bench`` in the working dir)."""
    return Path(os.environ.get("VI3_CACHE", ".cache")) / "bench"


def bench_ttr(args) -> dict:
    """TTR on the middle clip (n = 8, stride 2) of a generated 3 s sequence; ``args.repeats`` = steps (default
    40). ``ms_per_iter`` is the median step time (the first steps of a process carry one-time kernel warm-up);
    ``total_s`` is the whole clip: backbone, initialisation and every step; ``threads`` and ``omp_wait_policy``
    the torch settings it ran with (``vi3_core.threads.torch_thread_settings``)."""
    steps = args.repeats or 40
    seq = read_asl(cached_sequence(bench_cache_dir(), seconds=3.0, seed=0) / "mav0")
    clip = make_clip(seq, sample_clips(len(seq), n=8, stride=2, mode="paper")[1], with_depth=False)
    backbone = make_backbone(args.backbone, device=args.device)
    result = anchor(clip, backbone, mode="ttr", options=AnchorOptions(steps=steps))
    h, w = result.geometry.depth.shape[1:]
    return {"ms_per_iter": result.timings.get("ttr_ms_per_iter", float("nan")), "steps": steps,
            "total_s": sum(v for k, v in result.timings.items() if k.endswith("_s")), "frames": clip.n,
            "resolution": [int(h), int(w)], "backbone": args.backbone, "init_status": result.init.status.value,
            "mode": result.mode, **torch_thread_settings()}
