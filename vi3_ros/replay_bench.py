"""``vi3 bench replay``: replay speed in bag time.

Without ``--input`` it generates (once, cached under ``.cache/bench`` of the working directory) a 20 s EuRoC-format
sequence and converts it like a user would (ASL -> ROS 1 bag -> rosbag2 MCAP), then replays it in ``init`` mode
with the chosen backbone. ``realtime_factor`` = bag seconds / replay wall seconds (backbone loading excluded), so
>= 1 means the pipeline keeps up with the recording while processing every clip. ``cpu_s_per_clip`` = process CPU
seconds of the replay (all threads; reading, decoding and writing included) / clips: less sensitive than wall time to
other load on the machine. ``peak_rss_mb``: the process's peak resident memory (MB, ``getrusage``) when the replays
end, before the ground truth is read and their odometry read back and scored (which holds every ``~/odom/imu``
message); it must not grow with the bag's length (``--seconds``). The replay's defaults include the IMU-rate odometry
(``imu_odom_rate``), so its cost is in these numbers (``--param imu_odom_rate=0`` to leave it out). ``threads`` and
``omp_wait_policy``: the torch settings the replay ran with (parameter ``threads``).

``--realtime`` replays at the recorded rate into the node's worker thread, ``--backbone-delay S`` emulates a slower
model: the clips the busy worker drops show in ``outcomes`` (``skipped:worker_busy``). With ground truth (the
generated input, or an input with an ASL folder: a make-bag folder's ``asl/``) the report adds the odometry the
replay wrote, scored against it (``vi3_ros.replay_odom``: the chained ``~/path`` per odom segment, window resets,
``~/odom/imu`` rate and its jumps at corrections) from the median run.
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from msg_adapters.types import jazzy_types
from vi3_core.backbones import make_backbone
from vi3_core.backbones.recorded import RecordedBackbone, Recording, RecordingBackbone
from vi3_core.dataset.asl import find_mav0, read_groundtruth
from vi3_core.dataset.calib import write_euroc_sensor_yaml
from vi3_core.dataset.generate import EUROC_CAM0, bench_cache_dir, cached_sequence, generation_tag
from vi3_core.dataset.sequence import GroundTruthTrack
from vi3_core.errors import DataError
from vi3_core.online import OdomState
from vi3_core.threads import torch_thread_settings
from vi3_core.types import ImuSamples
from vi3_ros.imu_odom import ImuOdometry
from vi3_ros.io.convert import convert_to_rosbag2
from vi3_ros.io.reader import ImuEvent, imu_samples, iter_events
from vi3_ros.io.ros1 import write_ros1_bag
from vi3_ros.params import parse_assignment, resolve
from vi3_ros.replay import replay
from vi3_ros.replay_odom import odometry_report, read_odometry
from vi3_ros.soak import peak_rss_mb, soak

BENCH_SECONDS = 20.0
SOAK_MINUTES = 30.0

def _default_input(seconds: float) -> tuple[Path, Path, Path]:
    """(rosbag2 MCAP directory, calibration YAML, ASL folder) of the cached sequence of ``seconds``."""
    asl = cached_sequence(bench_cache_dir(), seconds=seconds, seed=0, with_depth=False)
    derived = asl / f"derived_{generation_tag(asl)}"  # a regenerated sequence never meets a stale bag
    derived.mkdir(exist_ok=True)
    bag, mcap, calib = derived / "seq.bag", derived / "mcap", derived / "cam0_sensor.yaml"
    if not mcap.exists():
        if not bag.exists():
            write_ros1_bag(asl, bag)
        convert_to_rosbag2(bag, mcap)
    if not calib.exists():
        write_euroc_sensor_yaml(EUROC_CAM0, calib)
    return mcap, calib, asl


def ground_truth(inp: Path) -> GroundTruthTrack | None:
    """The ground truth of an input that is (or holds, as ``asl/``) an ASL folder with one; else None."""
    for folder in (inp, inp / "asl"):
        try:
            return read_groundtruth(find_mav0(folder))
        except DataError:
            continue
    return None


def _bench_input(args: argparse.Namespace):
    """(input, ASL folder, settings) of a replay benchmark: ``--input`` or the generated bench sequence, init mode,
    ``--backbone``, ``--device``, ``--backbone-delay`` and every ``--param``."""
    if args.input:
        inp, calib, asl = Path(args.input), None, Path(args.input)
    else:
        inp, calib, asl = _default_input(args.seconds or BENCH_SECONDS)
    overrides = {"backbone": args.backbone, "device": args.device, "mode": "init",
                 **({"calib_file": str(calib)} if calib is not None else {}), **dict(map(parse_assignment, args.param))}
    if args.backbone_delay is not None:
        overrides["backbone_delay"] = args.backbone_delay
    return inp, asl, resolve(overrides)


def bench_replay(args: argparse.Namespace) -> dict:
    """Replay the input ``args.repeats`` times (default 1); median realtime factor and per-clip latency, and the
    odometry of the median run against ground truth where there is one."""
    inp, asl, settings = _bench_input(args)
    runs, cpu, odometry = [], [], []
    with tempfile.TemporaryDirectory(prefix="vi3-bench-replay-") as tmp:
        for i in range(args.repeats or 1):
            c0 = time.process_time()
            runs.append(replay(inp, Path(tmp) / f"out{i}.mcap", settings=settings, progress=False,
                               realtime=args.realtime))
            cpu.append((time.process_time() - c0) / max(runs[-1].clips, 1))
        peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        gt = ground_truth(asl)  # read after the peak: a long recording's ground truth is no part of the replay
        for run in runs:
            if gt is not None and run.output is not None:
                odometry.append(odometry_report(read_odometry(run.output), gt, time_offset=settings.buffer.time_offset))
    rtf = [r.realtime_factor for r in runs]
    median = int(np.argsort(rtf)[len(rtf) // 2])
    best = runs[median]
    return {"realtime_factor": round(float(np.median(rtf)), 3), "cpu_s_per_clip": round(float(np.median(cpu)), 4),
            "clips": best.clips,
            "median_latency_ms": round(best.median_latency_ms, 1), "bag_s": round(best.bag_s, 3),
            "wall_s": round(best.wall_s, 3), "outcomes": dict(best.outcomes), "backbone": args.backbone,
            "realtime": args.realtime, "backbone_delay": settings.model.backbone_delay,
            "imu_odom_rate": settings.outputs.imu_odom_rate, "input": str(inp),
            "peak_rss_mb": round(peak_rss_mb, 1), **torch_thread_settings(),
            **(odometry[median] if len(odometry) == len(runs) else {})}


def bench_pipeline(args: argparse.Namespace) -> dict:
    """What the replay costs beside its backbone: the input replayed once with the backbone (``--backbone``) while
    its base prediction of every clip is recorded, then ``args.repeats`` times (default 3) with those predictions
    served from the recording (``vi3_core.backbones.recorded``): reading, clip assembly and undistortion, the
    initialisation, the window and its links, self-calibration, the outputs, ``~/odom/imu`` and writing, every clip
    as the node runs it. ``cpu_s_per_clip``: process CPU seconds per clip of those replays (median);
    ``imu_odom_us_per_sample``: CPU microseconds of ``ImuOdometry.add`` per IMU sample of the input's first 20 s, its
    message built (rosbags classes, as replay writes them) and handed to a sink that keeps nothing (median of
    ``args.repeats`` passes)."""
    inp, _, settings = _bench_input(args)
    imu = _input_imu(inp)  # read first: an input without IMU fails before the replays
    recording = Recording()
    inner = make_backbone(settings.model.backbone, device=settings.model.device,
                          checkpoint=settings.model.checkpoint or None, **settings.model.backbone_options())
    cpu, runs = [], []
    with tempfile.TemporaryDirectory(prefix="vi3-bench-pipeline-") as tmp:
        replay(inp, Path(tmp) / "recorded.mcap", settings=settings, progress=False,
               backbone=RecordingBackbone(inner, recording))
        for i in range(args.repeats or 3):
            c0 = time.process_time()
            runs.append(replay(inp, Path(tmp) / f"out{i}.mcap", settings=settings, progress=False,
                               backbone=RecordedBackbone(recording, name=f"recorded {inner.name}")))
            cpu.append((time.process_time() - c0) / max(runs[-1].clips, 1))
    median = runs[int(np.argsort(cpu)[len(cpu) // 2])]
    imu_us = [_imu_odom_cost(settings, imu) for _ in range(args.repeats or 3)]
    return {"cpu_s_per_clip": round(float(np.median(cpu)), 4), "clips": median.clips,
            "recorded_clips": len(recording), "wall_s": round(median.wall_s, 3), "bag_s": round(median.bag_s, 3),
            "outcomes": dict(median.outcomes), "imu_odom_us_per_sample": round(float(np.median(imu_us)), 1),
            "backbone": inner.name, "input": str(inp), **torch_thread_settings()}


def bench_soak(args: argparse.Namespace) -> dict:
    """A long flight (``vi3_ros.soak``): the input (default: the generated 20 s bench bag) replayed in passes, time
    going forward, for ``--minutes`` (default 30) of bag time, every clip as ``vi3 replay`` runs it. ``errors``: clips
    ended in an error and messages that could not be built (0); ``outputs_per_clip``: messages per completed clip by
    output; per pass its bag end time, clips, outcomes, median latency and resident memory; ``rss_mb`` and
    ``peak_rss_mb`` of the first pass and the last, which must agree within 10 %."""
    inp, _, settings = _bench_input(args)
    minutes = args.minutes or SOAK_MINUTES
    before = peak_rss_mb()
    run = soak(inp, settings=settings, minutes=minutes)
    s, passes = run.summary, run.passes
    first, last = passes[0], passes[-1]
    return {"input": str(inp), "minutes": minutes, "passes": len(passes), "bag_s": round(s.bag_s, 1),
            "clips": s.clips, "errors": run.errors, "outcomes": dict(sorted(s.outcomes.items())),
            "output_errors": dict(s.output_errors), "drops": dict(sorted(s.drops.items())),
            "outputs_per_clip": {k: round(n / max(s.clips, 1), 2) for k, n in sorted(run.written.items())},
            "cpu_s_per_clip": round(run.cpu_s / max(s.clips, 1), 4), "wall_s": round(s.wall_s, 1),
            "realtime_factor": round(s.realtime_factor, 3), "peak_rss_mb_before": round(before, 1),
            "rss_mb": {"first_pass": round(first.rss_mb, 1), "last_pass": round(last.rss_mb, 1)},
            "peak_rss_mb": {"first_pass": round(first.peak_rss_mb, 1), "last_pass": round(last.peak_rss_mb, 1)},
            "by_pass": [{"end_s": round(p.end_s, 1), "clips": p.clips, "outcomes": p.outcomes,
                         "median_latency_ms": round(p.median_latency_ms, 1), "rss_mb": round(p.rss_mb, 1)}
                        for p in passes], "backbone": args.backbone, **torch_thread_settings()}


def _input_imu(inp: Path, *, seconds: float = 20.0) -> ImuSamples:
    """The first ``seconds`` of the IMU samples of ``inp`` (any recording ``iter_events`` reads): the work per sample
    does not depend on the motion, and a long bag is not read whole."""
    first: list[ImuEvent] = []
    for event in iter_events(inp):
        if isinstance(event, ImuEvent):
            if first and event.t_ns - first[0].t_ns > seconds * 1e9:
                break
            first.append(event)
    if len(first) < 2:
        raise DataError(f"{inp}: {len(first)} IMU sample(s): ~/odom/imu cannot be timed")
    return imu_samples(first)


def _imu_odom_cost(settings, imu: ImuSamples) -> float:
    """CPU microseconds per sample of ``ImuOdometry.add`` over ``imu`` (its first sample the chained state's, at
    rest: the work per sample does not depend on the motion), every sample propagated and published (no sigma or
    bridge limit stops it)."""
    first = np.array([imu.t[0]])
    state = OdomState(first, np.eye(4)[None], np.zeros((1, 3)), np.zeros(3), np.zeros(3), 0.01, 0.001)
    span = float(imu.t[-1] - imu.t[0]) + 1.0
    odom = ImuOdometry(settings.replace(imu_odom_max_sigma=0.0, online_max_bridge=span), types=jazzy_types(),
                       publish=lambda *_: None)
    odom.restart(state, lambda t: imu.select(slice(0, 1)))  # the samples since the state: its own only
    ns, gyro, accel = imu.t_ns.tolist(), imu.gyro, imu.accel
    c0 = time.process_time()
    for i in range(1, len(ns)):
        odom.add(ns[i], gyro[i], accel[i])
    return (time.process_time() - c0) / max(len(ns) - 1, 1) * 1e6
