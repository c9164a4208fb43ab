"""Bag replay: drive the node's pipeline (same ClipBuffer, worker and anchoring) over a recorded sequence in bag
time and write what the node would publish into a rosbag2 MCAP.

Deterministic: the worker runs synchronously, so every clip is processed, and output log times are the header
stamps (camera time) rather than wall-clock times; the node's diagnostics timer runs in bag time. Input: anything
``vi3_ros.io.reader.iter_events`` accepts (ASL folder, ``vi3 make-bag`` folder, ROS 1 bag, rosbag2 directory or
``.mcap``), read once; bags may also carry ``sensor_msgs/CameraInfo`` on ``camera_info_topic`` and ``/tf_static``
(with ``use_tf_static``), which come in the same stream and go to the Pipeline exactly as the node's callbacks do.
Output: ``OUT.mcap`` (a single MCAP file) or, for any other name, a rosbag2 directory (``metadata.yaml`` + MCAP).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from tqdm import tqdm

from msg_adapters.image import numpy_to_image
from msg_adapters.imu import samples_to_imus
from msg_adapters.types import MessageTypes, jazzy_types
from vi3_core.dataset.asl import find_mav0
from vi3_core.errors import DataError
from vi3_core.types import ImuSamples
from vi3_ros.io.reader import CameraInfoEvent, Event, ImageEvent, ImuEvent, find_calib, iter_events, resolve_input
from vi3_ros.params import NODE_NAME
from vi3_ros.pipeline import OUTPUTS, ClipReport, Pipeline, make_pipeline


def topic_name(topic: str, node: str = NODE_NAME) -> str:
    """``~/poses`` -> ``/vi3_node/poses`` (private topics resolved the way rclpy resolves them)."""
    return f"/{node}/{topic[2:]}" if topic.startswith("~/") else topic


class McapSink:
    """OutputSink writing CDR messages of the rosbags Jazzy typestore into a rosbag2 MCAP (``path``: a
    directory, or a ``.mcap`` file moved out of a temporary rosbag2 directory on ``close``)."""

    def __init__(self, path: str | Path, *, types: MessageTypes) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise DataError(f"replay output {self.path} already exists; choose a new name or delete it")
        self.types = types
        self._single = self.path.suffix == ".mcap"
        self._tmp = Path(tempfile.mkdtemp(prefix=".vi3-replay-", dir=self.path.parent)) if self._single else None
        self._bagdir = self._tmp / "bag" if self._tmp else self.path
        self._writer = Writer(self._bagdir, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._connections: dict[str, Any] = {}
        self.counts: Counter[str] = Counter()

    def publish(self, key: str, msg: Any, stamp_ns: int) -> None:
        out = OUTPUTS[key]
        self.write(topic_name(out.topic), out.msgtype, msg, stamp_ns)

    def write(self, topic: str, msgtype: str, msg: Any, stamp_ns: int) -> None:
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._connections[topic] = self._writer.add_connection(topic, msgtype,
                                                                          typestore=self.types.typestore)
        self._writer.write(conn, int(stamp_ns), self.types.typestore.serialize_cdr(msg, msgtype))
        self.counts[topic] += 1

    def close(self) -> None:
        self._writer.close()
        if self._tmp is not None:
            (mcap,) = self._bagdir.glob("*.mcap")
            shutil.move(mcap, self.path)
            shutil.rmtree(self._tmp, ignore_errors=True)


@dataclass
class ReplaySummary:
    """clips: clips the buffer completed; outcomes: final result per clip (init/cond/ttr/none/skipped:<reason>);
    drops: buffer drops by reason; latencies_ms: processing time per processed clip; wall_s: replay wall time;
    (backbone loading excluded); bag_s: span of the input's stamps; written: messages per output topic."""

    clips: int = 0
    outcomes: Counter = field(default_factory=Counter)
    drops: Counter = field(default_factory=Counter)
    latencies_ms: list[float] = field(default_factory=list)
    wall_s: float = 0.0
    bag_s: float = 0.0
    written: Counter = field(default_factory=Counter)
    reports: list[ClipReport] = field(default_factory=list)

    @property
    def realtime_factor(self) -> float:
        return self.bag_s / self.wall_s if self.wall_s > 0 else float("nan")

    @property
    def median_latency_ms(self) -> float:
        return float(np.median(self.latencies_ms)) if self.latencies_ms else float("nan")

    def as_dict(self) -> dict[str, Any]:
        return {"clips": self.clips, "outcomes": dict(sorted(self.outcomes.items())),
                "drops": dict(sorted(self.drops.items())), "median_latency_ms": round(self.median_latency_ms, 1),
                "wall_s": round(self.wall_s, 3), "bag_s": round(self.bag_s, 3),
                "realtime_factor": round(self.realtime_factor, 3), "written": dict(sorted(self.written.items()))}

    def text(self) -> str:
        d = self.as_dict()
        lines = [f"clips: {d['clips']}  outcomes: {d['outcomes'] or '-'}", f"drops: {d['drops'] or '-'}",
                 f"median latency: {d['median_latency_ms']} ms  bag: {d['bag_s']} s  wall: {d['wall_s']} s  "
                 f"realtime factor: {d['realtime_factor']}"]
        lines += [f"  {topic}: {n}" for topic, n in d["written"].items()]
        return "\n".join(lines)


def input_calib(path: Path) -> Path | None:
    """The calibration that comes with the input: an ASL folder's ``cam0/sensor.yaml`` or a Kalibr
    ``*camchain-imucam*.yaml`` beside a bag (``vi3 make-bag`` writes one); None if there is none."""
    source, kind = resolve_input(path)  # the reader's own detection (a make-bag folder reads its mcap/)
    if kind == "asl":
        sensor = find_mav0(source) / "cam0" / "sensor.yaml"
        return sensor if sensor.is_file() else None
    return find_calib(source)


@dataclass
class _BagTimer:
    """The node's diagnostics timer in bag time: ``due(t_ns)`` is True once per ``period_ns`` of input stamps (ns),
    the first time one period after the first stamp."""

    period_ns: int
    next_ns: int | None = None

    def due(self, t_ns: int) -> bool:
        if self.next_ns is None:
            self.next_ns = t_ns + self.period_ns
        if t_ns < self.next_ns:
            return False
        self.next_ns += ((t_ns - self.next_ns) // self.period_ns + 1) * self.period_ns
        return True


def _feed(pipeline: Pipeline, event: Event) -> None:
    """Hand one input event to the pipeline, as the node's callback for its topic does."""
    if isinstance(event, ImageEvent):
        pipeline.add_image(event.t_ns, event.image)
    elif isinstance(event, ImuEvent):
        pipeline.add_imu(event.t_ns, event.gyro, event.accel, event.orientation)
    elif isinstance(event, CameraInfoEvent):
        pipeline.add_camera_info(event.msg)
    else:
        pipeline.add_tf_static(event.msg)


def _copy_input(sink: McapSink, event: ImageEvent | ImuEvent, values: dict[str, Any]) -> None:
    """The input image / IMU sample as a Jazzy message on its input topic with its exact stamp (so the output bag
    is self-contained)."""
    types = sink.types
    if isinstance(event, ImageEvent):
        img = event.image
        enc = "mono8" if img.ndim == 2 else "rgb8"
        msg = numpy_to_image(img, encoding=enc, stamp_ns=event.t_ns, frame_id=values["camera_frame"], types=types)
        sink.write(values["image_topic"], "sensor_msgs/msg/Image", msg, event.t_ns)
    else:
        ori = None if event.orientation is None else np.asarray(event.orientation, np.float64)[None]
        (msg,) = samples_to_imus(ImuSamples(np.array([event.t]), np.asarray(event.gyro)[None],
                                            np.asarray(event.accel)[None], ori),
                                 frame_id=values["imu_frame"], types=types, stamps_ns=[event.t_ns])
        sink.write(values["imu_topic"], "sensor_msgs/msg/Imu", msg, event.t_ns)


def replay(input_path: str | Path, output: str | Path, *, values: dict[str, Any], copy_inputs: bool = False,
           progress: bool = True) -> ReplaySummary:
    """Replay ``input_path`` through the pipeline configured by parameter ``values``; write outputs to ``output``.

    Without ``calib_file`` the input's own calibration (``input_calib``) is used, unless CameraInfo or /tf_static
    are to be read from the input. Raises DataError for an unreadable input or an existing output; bad data inside
    the input becomes statuses."""
    input_path, types = Path(input_path), jazzy_types()
    if not values["calib_file"] and not values["camera_info_topic"] and not values["use_tf_static"]:
        found = input_calib(input_path)
        values = {**values, "calib_file": str(found) if found is not None else ""}
    summary = ReplaySummary()
    sink = McapSink(output, types=types)
    t_first = t_last = None
    timer = _BagTimer(round(values["diagnostics_period"] * 1e9))
    try:
        pipeline = make_pipeline(values, sink=sink, types=types, synchronous=True, on_report=summary.reports.append)
        start = time.perf_counter()  # model loading is not part of the replay's speed
        events = iter_events(input_path, image_topic=values["image_topic"], imu_topic=values["imu_topic"],
                             camera_info_topic=values["camera_info_topic"], tf_static=values["use_tf_static"])
        with tqdm(desc=f"replay {input_path.name}", unit=" frames", disable=not progress, leave=False) as bar:
            for event in events:
                if isinstance(event, ImageEvent | ImuEvent):
                    t_first = event.t_ns if t_first is None else t_first
                    t_last = event.t_ns
                    if copy_inputs:
                        _copy_input(sink, event, values)
                _feed(pipeline, event)
                if t_last is not None and timer.due(t_last):
                    pipeline.publish_diagnostics(t_last)
                bar.update(isinstance(event, ImageEvent))
        pipeline.close()
        if t_last is not None:  # the final counts
            pipeline.publish_diagnostics(t_last)
    finally:
        sink.close()
    summary.wall_s = time.perf_counter() - start
    summary.bag_s = 0.0 if t_first is None else (t_last - t_first) * 1e-9
    summary.clips = pipeline.buffer.clips
    summary.drops = Counter(pipeline.buffer.counts)
    summary.outcomes = Counter(pipeline.outcomes)
    summary.latencies_ms = [r.latency_s * 1e3 for r in summary.reports if np.isfinite(r.latency_s)]
    summary.written = Counter(sink.counts)
    return summary
