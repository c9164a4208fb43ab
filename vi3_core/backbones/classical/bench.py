"""``vi3 bench tracker``: CPU milliseconds per frame of the ``classical`` backbone's front end (``FrameTracker.add``)
on one thread, at EuRoC's 752x480 and at a RealSense's 1280x720, over the frames of a generated sequence."""

from __future__ import annotations

import time

import cv2
import numpy as np

from vi3_core.backbones.classical.tracks import FrameTracker
from vi3_core.dataset import asl
from vi3_core.dataset.generate import bench_cache_dir, cached_sequence

#: (width, height) the front end is timed at: EuRoC's camera, and a RealSense's colour stream (the same frames,
#: resized: the front end's cost is per pixel of its pyramid and per corner tracked)
SIZES = ((752, 480), (1280, 720))
CLIP = 8  # frames per clip: the share of a clip's tracks that last it whole is over every run of CLIP frames


def bench_tracker(args) -> dict:
    """For each of ``SIZES``: the process CPU ms per frame of ``FrameTracker.add`` (one thread: OpenCV's pool at one
    for the benchmark) over the 20 Hz frames of a generated 3 s sequence, median of ``args.repeats`` passes
    (default 5) after a warm-up pass; the live tracks after the last frame and the mean share of a clip's tracks
    (every run of ``CLIP`` frames) that last it whole."""
    seq = asl.read_asl(cached_sequence(bench_cache_dir(), seconds=3.0, seed=0) / "mav0")
    frames = [seq.image(i) for i in range(len(seq))]
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    out = {}
    try:
        for w, h in SIZES:
            gray = [cv2.resize(f, (w, h), interpolation=cv2.INTER_LINEAR) if f.shape != (h, w) else f for f in frames]
            runs, live, whole = [], [], []
            for rep in range((args.repeats or 5) + 1):
                tracker = FrameTracker()
                c0 = time.process_time()
                for i, g in enumerate(gray):
                    tracker.add(float(i), g)
                if rep:  # the first pass warms up
                    runs.append((time.process_time() - c0) / len(gray) * 1e3)
                live.append(len(tracker.tracks(tracker.keys()[-1:])))
                keys = tracker.keys()
                whole.append(float(np.mean([tracker.tracks(keys[i:i + CLIP]).visible.all(axis=1).mean()
                                            for i in range(len(keys) - CLIP + 1)])))
            out[f"{w}x{h}"] = {"cpu_ms_per_frame": round(float(np.median(runs)), 3),
                               "min_ms": round(float(np.min(runs)), 3), "live_tracks": int(np.median(live)),
                               "whole_clip_share": round(float(np.median(whole)), 3)}
    finally:
        cv2.setNumThreads(before)
    return {**out, "frames": len(frames), "repeats": args.repeats or 5, "options": vars(FrameTracker().options)}
