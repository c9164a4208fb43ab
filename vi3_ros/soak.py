"""A long flight from a short recording: the recording replayed again and again through the node's pipeline, time
going forward (``vi3 bench soak``). What an hour in the air does to the node that a minute does not: memory that
grows with the flight, rotations that drift from orthonormal, outputs that stop, latency that creeps up.

Each pass of the input is moved in time past the previous one by the input's span plus one IMU interval, so the
clocks run on without a gap while the motion jumps back to the recording's start at every seam (the window rejects
or restarts there, as after any inconsistent stretch of data). The messages are serialised as replay writes them
(CDR) and then dropped: a half-hour soak would otherwise write gigabytes of depth images.
"""

from __future__ import annotations

import dataclasses
import resource
import statistics
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from msg_adapters.types import MessageTypes, jazzy_types
from vi3_core.backbones.base import Backbone
from vi3_core.errors import DataError
from vi3_ros.io.reader import DropEvent, Event, ImageEvent, ImuEvent, resolve_input
from vi3_ros.outputs import published_outputs
from vi3_ros.pipeline import make_pipeline
from vi3_ros.replay import ReplaySummary, feed_pipeline, input_events, input_settings, record_report
from vi3_ros.settings import Settings


class SerialisingSink:
    """OutputSink that serialises every message to CDR, as replay's MCAP writer does, and keeps only its counts by
    output key (``counts``) and bytes."""

    def __init__(self, *, types: MessageTypes, settings: Settings) -> None:
        self.types, self.outputs = types, published_outputs(settings)
        self.counts: Counter[str] = Counter()
        self.bytes = 0

    def publish(self, key: str, msg: Any, stamp_ns: int) -> None:
        self.bytes += len(self.types.typestore.serialize_cdr(msg, self.outputs[key].msgtype))
        self.counts[key] += 1


@dataclass(frozen=True)
class SoakPass:
    """One pass of the input: end_s, bag seconds since the soak's start at its end; clips completed in it and their
    outcomes (init/cond/ttr/none/skipped:<reason>); median_latency_ms of its clips; rss_mb, the process's resident
    memory at its end; peak_rss_mb, the process's peak resident memory so far (MB)."""

    end_s: float
    clips: int
    outcomes: dict[str, int]
    median_latency_ms: float
    rss_mb: float
    peak_rss_mb: float


@dataclass
class SoakRun:
    """summary: the whole soak as a replay's (``ReplaySummary``); passes: one ``SoakPass`` per pass of the input;
    written: messages per output key; cpu_s: process CPU seconds of the soak."""

    summary: ReplaySummary
    passes: list[SoakPass] = field(default_factory=list)
    written: Counter = field(default_factory=Counter)
    cpu_s: float = 0.0

    @property
    def errors(self) -> int:
        """Clips that ended in an error and messages that could not be built: 0 in a sound soak."""
        return self.summary.outcomes.get("skipped:error", 0) + sum(self.summary.output_errors.values())


def rss_mb() -> float:
    """The process's resident memory now, MB (Linux ``/proc``; NaN elsewhere)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return float("nan")
    return pages * resource.getpagesize() / 2**20


def peak_rss_mb() -> float:
    """The process's peak resident memory so far, MB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def looped(events: Callable[[], Iterator[Event]], passes: int, *,
           on_pass: Callable[[int, int], None] | None = None) -> Iterator[Event]:
    """``passes`` passes of the events ``events()`` yields, each moved in time (stamps of frames, IMU samples and
    dropped messages) past the previous pass's last frame or sample by the input's span and its median IMU interval;
    calibration messages (CameraInfo, /tf_static) in the first pass only. ``on_pass(k, shift_ns)`` after pass k."""
    shift = 0
    for k in range(passes):
        first = last = None
        imu_dt: list[int] = []
        for ev in events():
            if isinstance(ev, ImageEvent | ImuEvent):
                if isinstance(ev, ImuEvent) and last is not None and len(imu_dt) < 1000:
                    imu_dt.append(ev.t_ns - last)
                first, last = ev.t_ns if first is None else first, ev.t_ns
                ev = dataclasses.replace(ev, t=ev.t + shift * 1e-9, t_ns=ev.t_ns + shift)
            elif isinstance(ev, DropEvent):
                ev = ev if ev.t_ns is None else dataclasses.replace(ev, t_ns=ev.t_ns + shift)
            elif k:
                continue
            yield ev
        if first is None:
            raise DataError("the input has no camera frames or IMU samples to loop")
        if on_pass is not None:
            on_pass(k, shift)
        shift += last - first + int(statistics.median(imu_dt) if imu_dt else 5_000_000)


def soak(input_path: str | Path, *, settings: Settings, minutes: float, progress: bool = False,
         backbone: Backbone | None = None) -> SoakRun:
    """Replay ``input_path`` through the node's pipeline (every clip, in order, as ``vi3 replay``) in as many passes as
    make ``minutes`` of bag time, recording each pass (``SoakPass``). Raises a Vi3Error for an input that cannot be
    used."""
    input_path = Path(input_path)
    resolve_input(input_path)
    settings = input_settings(input_path, settings)
    first = [ev.t_ns for ev in input_events(input_path, settings) if isinstance(ev, ImageEvent | ImuEvent)]
    span_s = (max(first) - min(first)) * 1e-9 if first else 0.0
    if span_s <= 0:
        raise DataError(f"{input_path}: no span of frames and IMU samples to loop")
    passes = max(int(np.ceil(minutes * 60.0 / span_s)), 1)
    types = jazzy_types()
    run = SoakRun(ReplaySummary())
    sink = SerialisingSink(types=types, settings=settings)
    pipeline = make_pipeline(settings, sink=sink, types=types, synchronous=True,
                             on_report=lambda r: record_report(run.summary, r), backbone=backbone)
    seen = {"clips": 0, "latencies": 0, "outcomes": Counter()}

    def on_pass(k: int, shift_ns: int) -> None:
        outcomes = Counter(pipeline.outcomes) - seen["outcomes"]
        latencies = run.summary.latencies_ms[seen["latencies"]:]
        run.passes.append(SoakPass(end_s=shift_ns * 1e-9 + span_s, clips=pipeline.buffer.clips - seen["clips"],
                                   outcomes=dict(sorted(outcomes.items())),
                                   median_latency_ms=float(np.median(latencies)) if latencies else float("nan"),
                                   rss_mb=rss_mb(), peak_rss_mb=peak_rss_mb()))
        seen.update(clips=pipeline.buffer.clips, latencies=len(run.summary.latencies_ms),
                    outcomes=Counter(pipeline.outcomes))

    c0, start = time.process_time(), time.perf_counter()
    feed_pipeline(pipeline, sink, looped(lambda: input_events(input_path, settings), passes, on_pass=on_pass),
                  run.summary, settings, copy_inputs=False, progress=progress, name=input_path.name)
    run.cpu_s, run.summary.wall_s = time.process_time() - c0, time.perf_counter() - start
    run.summary.clips, run.summary.drops = pipeline.buffer.clips, pipeline.drop_counts
    run.summary.outcomes, run.summary.output_errors = Counter(pipeline.outcomes), Counter(pipeline.output_errors)
    run.written = Counter(sink.counts)
    return run


__all__ = ["SerialisingSink", "SoakPass", "SoakRun", "looped", "peak_rss_mb", "rss_mb", "soak"]
