"""Bag replay: drive the node's pipeline (same ClipBuffer, worker and anchoring) over a recorded sequence in bag
time and write what the node would publish into a rosbag2 MCAP.

Deterministic by default: the worker runs synchronously, so every clip is processed, and output log times are the
header stamps (camera time) rather than wall-clock times; the node's diagnostics timer runs in bag time. With
``realtime`` the input is fed at its recorded rate into the node's latest-wins worker thread instead, so the output is
what the node would publish on this machine, clips the busy worker could not take included (``skipped:
worker_busy``); log times are then the replay clock (bag time as it runs) at which each message was published, so a
player shows each result's latency. Input: anything
``vi3_ros.io.reader.iter_events`` accepts (ASL folder, ``vi3 make-bag`` folder, ROS 1 bag, rosbag2 directory or
``.mcap``), read once; bags may also carry ``sensor_msgs/CameraInfo`` on ``camera_info_topic`` and ``/tf_static``
(with ``use_tf_static``), which come in the same stream and go to the Pipeline exactly as the node's callbacks do.
Output: ``OUT.mcap`` (a single MCAP file) or, for any other name, a rosbag2 directory (``metadata.yaml`` + MCAP),
written under a hidden temporary folder beside it and moved into place only when the replay finished and some clip
produced a result: an output at ``OUT`` is always complete, and a partial output an earlier run left beside it is
removed then. An error, an interruption or a replay in which no clip produced a result keeps what was written as
``OUT.partial.mcap`` (``OUT.partial``), or nothing; the messages of one clip (its geometry, odometry and the
``~/status`` that ends them) are written together, so a partial output never holds a clip without its status. An
output that is, lies inside or contains an input (symbolic links resolved) is refused whatever ``force`` says, and
one run at a time writes an output (``vi3_ros.io.output_lock``: a second run fails at once, naming the first).

Memory does not grow with the input: events are read, fed and released one at a time, and the summary keeps one
latency per clip.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from tqdm import tqdm

from msg_adapters.image import numpy_to_image
from msg_adapters.imu import samples_to_imus
from msg_adapters.types import MessageTypes, jazzy_types
from vi3_core.anchor.options import MODES
from vi3_core.backbones.base import Backbone
from vi3_core.dataset.asl import find_mav0
from vi3_core.dataset.calib import CameraCalib, load_calib
from vi3_core.errors import CalibrationError, DataError, Vi3Error
from vi3_core.eval.report import gyro_check_hint
from vi3_core.init.initializer import GYRO_FAILURE
from vi3_core.online.calibration import RigEstimate
from vi3_core.paths import check_apart
from vi3_core.types import ImuSamples
from vi3_ros import interrupts
from vi3_ros.io.output_lock import OutputLock
from vi3_ros.io.reader import (
    BAG_DAMAGE,
    CameraInfoEvent,
    DropEvent,
    Event,
    ImageEvent,
    ImuEvent,
    TopicRequest,
    find_calib,
    iter_events,
    resolve_input,
)
from vi3_ros.io.topics import IMAGE_TRANSPORTS
from vi3_ros.outputs import OutputSink, published_outputs, stream_keys
from vi3_ros.params import NODE_NAME
from vi3_ros.pipeline import ClipReport, Pipeline, make_pipeline
from vi3_ros.settings import InputOptions, Settings
from vi3_ros.time_offset import resolve_time_offset

REALTIME_STOP_WAIT_S = 0.5  # s an interrupted realtime replay waits for the clip in the worker, as the node's shutdown
UNIT_END_KEY = "status"


def topic_name(topic: str, node: str = NODE_NAME) -> str:
    """``~/poses`` -> ``/vi3_node/poses`` (private topics resolved the way rclpy resolves them)."""
    return f"/{node}/{topic[2:]}" if topic.startswith("~/") else topic


def partial_path(path: Path) -> Path:
    """Where an interrupted or failed replay keeps what it wrote: ``OUT.partial.mcap`` for ``OUT.mcap``,
    ``OUT.partial`` for a rosbag2 directory ``OUT``."""
    return path.with_name(f"{path.stem}.partial.mcap") if path.suffix == ".mcap" else \
        path.with_name(f"{path.name}.partial")


def check_output(path: Path, *, force: bool) -> None:
    """DataError unless ``path`` can be written: its folder exists, and it does not exist yet (``force``: it is
    an MCAP file or a rosbag2 directory, which will be replaced)."""
    folder = path.parent
    if not folder.is_dir():
        raise DataError(f"replay output {path}: folder {folder} does not exist" if not folder.exists() else
                        f"replay output {path}: {folder} is not a folder")
    if path.exists() or path.is_symlink():
        if not force:
            raise DataError(f"replay output {path} already exists; choose a new name, delete it or pass --force")
        if not (path.is_file() and path.suffix == ".mcap") and not (path / "metadata.yaml").is_file():
            raise DataError(f"replay output {path} exists and is not an MCAP file or a rosbag2 directory; --force "
                            "replaces only those")


def _unwritable(path: Path, err: OSError) -> DataError:
    """The error of an output ``path`` whose folder refuses a new entry (``err``)."""
    return DataError(f"replay output {path}: cannot write into {path.parent} ({err.strerror})")


@contextmanager
def _locked(path: Path) -> Iterator[None]:
    """The output lock of ``path`` (``OutputLock``) for the block; DataError when it cannot be taken."""
    lock = OutputLock(path, what="replay output")
    try:
        lock.acquire()
    except OSError as err:
        raise _unwritable(path, err) from None
    try:
        yield
    finally:
        lock.release()


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


class McapSink:
    """OutputSink writing CDR messages of the rosbags Jazzy typestore into a rosbag2 MCAP under a hidden temporary
    folder beside ``path`` (an ``OUT.mcap`` file, or a rosbag2 directory for any other name). ``commit`` moves the
    result to ``path`` (replacing it with ``force``); ``abandon`` keeps what was written at ``partial_path(path)``,
    or nothing when nothing was written. Either way the temporary folder is removed.

    ``publish`` keeps a clip's messages (each thread its own) until its ``~/status`` arrives and writes them with it
    in one step that a signal does not cut short; the outputs published outside any clip (``stream_keys``: the
    diagnostics timer, the IMU-rate odometry) are written at once. ``settings``: the stream's, which say the outputs'
    topics (``published_outputs``; None: the defaults). Thread-safe (the realtime
    replay's worker thread publishes beside the input thread); a message that arrives after ``commit`` or
    ``abandon`` is discarded, as the node discards the outputs of a clip still running at shutdown, and so is a
    clip whose status never came. An error writing the bag (a full disk) is a DataError naming ``path``.
    ``clock``: when set, a function giving the log time (ns) of published outputs; else their header stamps."""

    def __init__(self, path: str | Path, *, types: MessageTypes, force: bool = False,
                 settings: Settings | None = None) -> None:
        self.path = Path(path)
        check_output(self.path, force=force)
        self.types = types
        settings = settings or Settings()
        self.outputs, self.stream_keys = published_outputs(settings), stream_keys(settings)
        try:
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.vi3-replay-", dir=self.path.parent))
        except OSError as err:
            raise _unwritable(self.path, err) from None
        self._bagdir = self._tmp / "bag"
        try:
            with self._writing():
                self._writer = Writer(self._bagdir, version=9, storage_plugin=StoragePlugin.MCAP)
                self._writer.open()
        except Exception:
            shutil.rmtree(self._tmp, ignore_errors=True)
            raise
        self._connections: dict[str, Any] = {}
        self.counts: Counter[str] = Counter()
        self.clock: Callable[[], int] | None = None
        self._lock = threading.Lock()
        self._closed = False
        self._units: dict[int, list[tuple[str, str, bytes, int]]] = {}  # thread -> its clip's messages so far

    @contextmanager
    def _writing(self) -> Iterator[None]:
        """An OSError of the bag writer (a full disk, a file too large) as a DataError naming the output."""
        try:
            yield
        except OSError as err:
            raise DataError(f"replay output {self.path}: cannot write it ({err.strerror or err})") from err

    def publish(self, key: str, msg: Any, stamp_ns: int) -> None:
        out = self.outputs[key]
        entry = (topic_name(out.topic), out.msgtype, self.types.typestore.serialize_cdr(msg, out.msgtype),
                 int(stamp_ns if self.clock is None else self.clock()))
        if key in self.stream_keys:
            self._write([entry])
            return
        unit = self._units.setdefault(threading.get_ident(), [])
        unit.append(entry)
        if key == UNIT_END_KEY:
            del self._units[threading.get_ident()]
            with interrupts.held():
                self._write(unit)

    def write(self, topic: str, msgtype: str, msg: Any, stamp_ns: int) -> None:
        """One message at once (an input copied to the output)."""
        self._write([(topic, msgtype, self.types.typestore.serialize_cdr(msg, msgtype), int(stamp_ns))])

    def _write(self, entries: list[tuple[str, str, bytes, int]]) -> None:
        """(topic, type, CDR bytes, log time ns) entries, in one step."""
        with self._lock, self._writing():
            if self._closed:
                return
            for topic, msgtype, data, stamp_ns in entries:
                conn = self._connections.get(topic)
                if conn is None:
                    conn = self._connections[topic] = self._writer.add_connection(topic, msgtype,
                                                                                  typestore=self.types.typestore)
                self._writer.write(conn, stamp_ns, data)
                self.counts[topic] += 1

    def _close(self) -> None:
        with self._lock, self._writing():
            self._closed = True
            self._units.clear()
            self._writer.close()

    def _result(self) -> Path:
        """The written output inside the temporary folder: its MCAP file (``OUT.mcap``) or the rosbag2 folder."""
        return next(self._bagdir.glob("*.mcap")) if self.path.suffix == ".mcap" else self._bagdir

    def commit(self) -> Path:
        """Close the bag and move it to ``path``, removing the partial output of an earlier run; OSError or
        DataError (e.g. a full disk) leaves nothing behind."""
        try:
            self._close()
            _remove(self.path)
            os.replace(self._result(), self.path)
            _remove(partial_path(self.path))
        finally:
            shutil.rmtree(self._tmp, ignore_errors=True)
        return self.path

    def abandon(self) -> Path | None:
        """Keep what was written as ``partial_path(path)`` (replacing an older one) and return it; None when
        nothing was written or it cannot be closed into a readable bag."""
        kept = None
        try:
            self._close()
            if sum(self.counts.values()):
                kept = partial_path(self.path)
                _remove(kept)
                os.replace(self._result(), kept)
        except Exception:  # already failing (full disk, interrupted): keep nothing rather than a broken file
            kept = None
        finally:
            shutil.rmtree(self._tmp, ignore_errors=True)
        return kept


class ReplayAborted(Vi3Error):
    """A replay that could not finish: the message says why and what was kept (``partial``: the path, or None)."""

    def __init__(self, message: str, partial: Path | None) -> None:
        super().__init__(message)
        self.partial = partial


class ReplayInterrupted(KeyboardInterrupt):
    """A replay stopped by SIGINT (or SIGTERM, which the command turns into this); ``partial`` as ReplayAborted."""

    def __init__(self, partial: Path | None) -> None:
        super().__init__(kept_text(partial))
        self.partial = partial


def kept_text(partial: Path | None) -> str:
    """What an unfinished replay left behind, as a sentence."""
    return f"kept what was produced in {partial} (incomplete)" if partial is not None else "nothing was written"


@dataclass
class ReplaySummary:
    """clips: clips the buffer completed; outcomes: final result per clip (init/cond/ttr/none/skipped:<reason>);
    drops: dropped input messages and clips by reason; latencies_ms: processing time per processed clip; wall_s:
    replay wall time (backbone loading excluded); bag_s: span of the input's stamps; frames: camera frames read
    (dropped ones included); written: messages per output topic; output: where they are (``--output``, or the
    partial output when no clip produced a result or odometry); realtime: fed at the recorded rate
    (``feed_lag_ms``: the most the feeding fell behind that rate, reading and decoding the input); checked: clips
    with a result (not skipped), gyro_failures: those of them the gyro check rejected (``hint``); output_errors:
    messages that could not be built, by output (a bug; each clip's status names its own); odom_only: clips placed in
    ``~/odom`` at the window's scale without a claim (``odom_max_scale_sigma``), an output of their own."""

    clips: int = 0
    outcomes: Counter = field(default_factory=Counter)
    drops: Counter = field(default_factory=Counter)
    latencies_ms: list[float] = field(default_factory=list)
    wall_s: float = 0.0
    bag_s: float = 0.0
    frames: int = 0
    written: Counter = field(default_factory=Counter)
    output: Path | None = None
    realtime: bool = False
    feed_lag_ms: float = 0.0
    checked: int = 0
    gyro_failures: int = 0
    output_errors: Counter = field(default_factory=Counter)
    odom_only: int = 0

    @property
    def hint(self) -> str:
        """What most likely went wrong when most clips failed the gyro check ("" otherwise)."""
        return gyro_check_hint(self.gyro_failures, self.checked)

    @property
    def realtime_factor(self) -> float:
        return self.bag_s / self.wall_s if self.wall_s > 0 else float("nan")

    @property
    def median_latency_ms(self) -> float:
        return float(np.median(self.latencies_ms)) if self.latencies_ms else float("nan")

    @property
    def results(self) -> int:
        """Clips that produced metric output (result init, cond or ttr)."""
        return sum(n for k, n in self.outcomes.items() if k in MODES)

    def why_nothing(self) -> str:
        """Why no clip produced a result (for a summary line), from the frames, drops and outcomes."""
        if self.frames == 0:
            return "the input has no camera frames"
        drops = _counts(self.drops)
        if self.clips == 0:
            return f"no clip was completed from {self.frames} frames (drops: {drops or 'none'})"
        hint = f"; {self.hint}" if self.hint else ""
        return f"every clip failed: outcomes {_counts(self.outcomes)} (drops: {drops or 'none'}){hint}"

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: a value that does not exist (no latency, no wall time) is None."""
        def num(x: float, digits: int) -> float | None:
            return round(x, digits) if np.isfinite(x) else None

        return {"clips": self.clips, "results": self.results, "odom_only": self.odom_only, "frames": self.frames,
                "outcomes": dict(sorted(self.outcomes.items())), "drops": dict(sorted(self.drops.items())),
                "median_latency_ms": num(self.median_latency_ms, 1), "wall_s": round(self.wall_s, 3),
                "bag_s": round(self.bag_s, 3), "realtime_factor": num(self.realtime_factor, 3),
                "written": dict(sorted(self.written.items())),
                "output": None if self.output is None else str(self.output),
                **({"hint": self.hint} if self.hint else {}),
                **({"output_errors": dict(sorted(self.output_errors.items()))} if self.output_errors else {}),
                **({"realtime": True, "feed_lag_ms": round(self.feed_lag_ms, 1)} if self.realtime else {})}

    def text(self) -> str:
        d = self.as_dict()
        lines = [f"clips: {d['clips']}  outcomes: {d['outcomes'] or '-'}  placed in odom without a claim: "
                 f"{d['odom_only']}", f"drops: {d['drops'] or '-'}",
                 f"median latency: {d['median_latency_ms']} ms  bag: {d['bag_s']} s  wall: {d['wall_s']} s  "
                 f"realtime factor: {d['realtime_factor']}"]
        lines += [f"  {topic}: {n}" for topic, n in d["written"].items()]
        if self.output_errors:
            lines.append(f"outputs not built (a bug, please report; each clip's status names it): "
                         f"{_counts(self.output_errors)}")
        return "\n".join(lines + ([f"hint: {self.hint}"] if self.hint else []))


def _counts(counts: Counter) -> str:
    return ", ".join(f"{k}:{n}" for k, n in sorted(counts.items()))


def input_calib(path: Path) -> Path | None:
    """The calibration that comes with the input: an ASL folder's ``cam0/sensor.yaml`` or a Kalibr
    ``*camchain-imucam*.yaml`` beside a bag (``vi3 make-bag`` writes one); None if there is none."""
    source, kind = resolve_input(path)  # the reader's own detection (a make-bag folder reads its mcap/)
    if kind == "asl":
        sensor = find_mav0(source) / "cam0" / "sensor.yaml"
        return sensor if sensor.is_file() else None
    return find_calib(source)


class _ReplayClock:
    """Bag time as the realtime replay runs: from the first stamp fed (``wait_until``), it advances with the
    monotonic wall clock. ``lag_ns``: the most a stamp was fed after its time."""

    def __init__(self) -> None:
        self._t0: int | None = None
        self._w0 = 0
        self.lag_ns = 0

    def wait_until(self, t_ns: int) -> None:
        """Sleep until bag time ``t_ns`` (ns)."""
        if self._t0 is None:
            self._t0, self._w0 = t_ns, time.monotonic_ns()
        ahead = t_ns - self.now_ns()
        if ahead > 0:
            time.sleep(ahead * 1e-9)
        else:
            self.lag_ns = max(self.lag_ns, -ahead)

    def now_ns(self) -> int:
        return self._t0 + time.monotonic_ns() - self._w0


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
    elif isinstance(event, DropEvent):
        pipeline.drop_input(event.reason, event.t_ns, event.detail)
    else:
        pipeline.add_tf_static(event.msg)


_COPY_ENCODINGS = {("u1", 2): "mono8", ("u1", 3): "rgb8", ("u2", 2): "mono16"}  # (dtype, ndim) -> encoding


def _copy_input(sink: McapSink, event: ImageEvent | ImuEvent, settings: Settings) -> None:
    """The input image / IMU sample as a Jazzy message on its input topic with its exact stamp (so the output bag
    is self-contained)."""
    types = sink.types
    if isinstance(event, ImageEvent):
        img = event.image
        enc = _COPY_ENCODINGS.get((img.dtype.str[1:], img.ndim))
        if enc is None:  # a frame no Image encoding here describes (the pipeline drops it, naming it)
            return
        msg = numpy_to_image(img, encoding=enc, stamp_ns=event.t_ns, frame_id=settings.frames.camera_frame,
                             types=types)
        sink.write(settings.inputs.image_topic, "sensor_msgs/msg/Image", msg, event.t_ns)
    else:
        ori = None if event.orientation is None else np.asarray(event.orientation, np.float64)[None]
        (msg,) = samples_to_imus(ImuSamples(np.array([event.t]), np.asarray(event.gyro)[None],
                                            np.asarray(event.accel)[None], ori),
                                 frame_id=settings.frames.imu_frame, types=types, stamps_ns=[event.t_ns])
        sink.write(settings.inputs.imu_topic, "sensor_msgs/msg/Imu", msg, event.t_ns)


def topic_requests(inputs: InputOptions, image_topic: str | None = None,
                   imu_topic: str | None = None) -> tuple[TopicRequest, TopicRequest]:
    """The image and IMU topics replay reads: ``image_topic`` / ``imu_topic`` (``--image-topic`` /
    ``--imu-topic``) when given, else the parameters' topics when the recording has them, else the only topic of
    the type (``vi3_ros.io.reader.choose_topics``); images of the type ``image_transport`` allows."""
    return (TopicRequest(image_topic, inputs.image_topic, IMAGE_TRANSPORTS[inputs.image_transport]),
            TopicRequest(imu_topic, inputs.imu_topic))


def input_settings(input_path: Path, settings: Settings, *,
                   on_note: Callable[[str], None] | None = None) -> Settings:
    """``settings`` for replaying ``input_path``: without ``calib_file``, the input's own calibration
    (``input_calib``) unless CameraInfo or /tf_static are to be read from the input; a Kalibr calibration's
    ``timeshift_cam_imu`` as ``time_offset`` (``vi3_ros.time_offset``; ``on_note`` is told when the parameter
    overrides it). A calibration that cannot be used raises CalibrationError."""
    inputs = settings.inputs
    if not inputs.calib_file and not inputs.camera_info_topic and not inputs.use_tf_static:
        found = input_calib(input_path)
        settings = settings.replace(calib_file=str(found) if found is not None else "")
    if settings.inputs.calib_file:
        settings, note = resolve_time_offset(settings, load_calib(settings.inputs.calib_file))
        if note and on_note is not None:
            on_note(f"{settings.inputs.calib_file}: {note}")
    return settings


def input_events(input_path: Path, settings: Settings, image_topic: str | None = None,
                 imu_topic: str | None = None, on_note: Callable[[str], None] | None = None) -> Iterator[Event]:
    """The input's events as ``settings`` and the explicit topics choose them (``topic_requests``); ``on_note`` is
    told what of a recording cut short or damaged could not be read (``BAG_DAMAGE``), as its drop is fed."""
    image, imu = topic_requests(settings.inputs, image_topic, imu_topic)
    for event in iter_events(input_path, image=image, imu=imu, camera_info_topic=settings.inputs.camera_info_topic,
                             tf_static=settings.inputs.use_tf_static):
        if on_note is not None and isinstance(event, DropEvent) and event.reason in BAG_DAMAGE:
            on_note(event.detail)
        yield event


def replay(input_path: str | Path, output: str | Path, *, settings: Settings, copy_inputs: bool = False,
           progress: bool = True, force: bool = False, image_topic: str | None = None,
           imu_topic: str | None = None, realtime: bool = False,
           on_note: Callable[[str], None] | None = None, backbone: Backbone | None = None) -> ReplaySummary:
    """Replay ``input_path`` through the pipeline configured by ``settings``; write outputs to ``output``;
    ``realtime``: at the recorded rate into the node's worker thread (see the module docstring); ``backbone``: the
    one to run instead of the settings' (``vi3 bench pipeline``).

    The calibration and time offset: ``input_settings`` (``on_note``: its notes). Topics: ``topic_requests``. The
    output is written beside ``output`` and moved there only when the replay finishes and some clip produced a
    result; otherwise (the summary says why) it is kept as ``partial_path(output)``. An input or output that cannot
    be used raises ReplayAborted (a DataError before anything is written: an output that is, lies inside or contains
    an input, or one that another run is writing, too); an interruption raises ReplayInterrupted; either says what
    was kept. Bad data inside the input becomes drops and statuses."""
    if not str(output).strip():
        raise DataError("replay output is empty: name an OUT.mcap file or a rosbag2 folder")
    input_path, output, types = Path(input_path), Path(output), jazzy_types()
    resolve_input(input_path)  # a missing or unknown input fails before anything is written
    settings = input_settings(input_path, settings, on_note=on_note)
    calib_file = settings.inputs.calib_file
    inputs = [input_path] + ([Path(calib_file)] if calib_file else [])
    check_apart(output, inputs, what="replay output")
    check_apart(partial_path(output), inputs, what=f"the partial output of {output},")
    check_output(output, force=force)  # its folder exists (McapSink checks again under the lock)
    summary = ReplaySummary(realtime=realtime)
    interrupts.hold()  # a temporary output (and the lock) exist only together with the code that removes them
    with _locked(output):
        sink = McapSink(output, types=types, force=force, settings=settings)
        try:
            interrupts.release()  # a signal that came meanwhile interrupts here
            pipeline = make_pipeline(settings, sink=sink, types=types, synchronous=not realtime,
                                     on_report=lambda r: record_report(summary, r), backbone=backbone)
            start = time.perf_counter()  # model loading is not part of the replay's speed
            feed_pipeline(pipeline, sink, input_events(input_path, settings, image_topic, imu_topic, on_note), summary,
                          settings, copy_inputs=copy_inputs, progress=progress, name=input_path.name)
            summary.wall_s = time.perf_counter() - start
            summary.clips = pipeline.buffer.clips
            summary.drops = pipeline.drop_counts
            summary.outcomes, summary.output_errors = Counter(pipeline.outcomes), Counter(pipeline.output_errors)
            summary.odom_only = pipeline.odom_only
            summary.written = Counter(sink.counts)
            interrupts.hold()  # the output is finished from here on: a signal is recorded (the command reports it)
        except BaseException as err:
            interrupts.hold()  # what is kept is decided without a signal cutting it short
            partial = sink.abandon()
            if isinstance(err, KeyboardInterrupt):
                raise ReplayInterrupted(partial) from None
            if isinstance(err, Vi3Error | OSError):
                why = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
                raise ReplayAborted(f"{why}; {kept_text(partial)}", partial) from err
            raise
        try:
            summary.output = sink.commit() if summary.results or summary.odom_only else sink.abandon()
        except (OSError, DataError) as err:
            why = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
            raise ReplayAborted(f"writing {output}: {why}; nothing was written", None) from err
    return summary


class DiscardSink:
    """OutputSink that keeps nothing (``replay_rig``: the pipeline runs for its state, not its messages)."""

    def publish(self, key: str, msg: Any, stamp_ns: int) -> None:
        pass


@dataclass
class RigRun:
    """What ``replay_rig`` found: ``estimate``, the rig's self-calibration at the end (None when no clip reached the
    backbone); ``calib``, the configured camera calibration (None when none could be assembled); ``time_offset``, the
    configured camera-IMU offset, s (t_imu = t_cam + time_offset); ``summary``, the replay's counts; ``calib_file``,
    the file the calibration came from ("" when it came from CameraInfo and /tf_static)."""

    estimate: RigEstimate | None
    calib: CameraCalib | None
    time_offset: float
    summary: ReplaySummary
    calib_file: str = ""


def replay_rig(input_path: str | Path, *, settings: Settings, progress: bool = True, image_topic: str | None = None,
               imu_topic: str | None = None, on_note: Callable[[str], None] | None = None) -> RigRun:
    """Run the node's pipeline over ``input_path`` as ``replay`` does (every clip, in order; calibration and topics
    as there) in ``init`` mode, online, with self-calibration on, writing nothing: the rig's estimate from the whole
    recording (``vi3 calib``). An input that cannot be used raises a Vi3Error naming it."""
    input_path = Path(input_path)
    resolve_input(input_path)
    settings = input_settings(input_path, settings, on_note=on_note).replace(mode="init", online=True,
                                                                          self_calibration=True)
    summary, types = ReplaySummary(), jazzy_types()
    sink = DiscardSink()
    pipeline = make_pipeline(settings, sink=sink, types=types, synchronous=True,
                             on_report=lambda r: record_report(summary, r))
    start = time.perf_counter()
    feed_pipeline(pipeline, sink, input_events(input_path, settings, image_topic, imu_topic, on_note), summary,
                  settings, copy_inputs=False, progress=progress, name=input_path.name)
    summary.wall_s = time.perf_counter() - start
    summary.clips, summary.drops = pipeline.buffer.clips, pipeline.drop_counts
    summary.outcomes = Counter(pipeline.outcomes)
    try:
        calib = pipeline.calibration.current()
    except CalibrationError:
        calib = None
    calibrator = pipeline.stream.calibrator
    return RigRun(calibrator.estimate if calibrator is not None and calibrator.clips else None, calib,
                  settings.buffer.time_offset, summary, settings.inputs.calib_file)


def record_report(summary: ReplaySummary, report: ClipReport) -> None:
    """A clip's final result in the summary: its latency, and whether the gyro check rejected it."""
    if np.isfinite(report.latency_s):
        summary.latencies_ms.append(report.latency_s * 1e3)
    if report.result != "skipped":
        summary.checked += 1
        summary.gyro_failures += report.reason.startswith(GYRO_FAILURE)


def feed_pipeline(pipeline: Pipeline, sink: OutputSink, events: Iterable[Event], summary: ReplaySummary,
                  settings: Settings, *, copy_inputs: bool, progress: bool, name: str) -> None:
    """Feed every input event to the pipeline, the diagnostics timer in bag time (realtime: at the recorded rate, then
    wait for the worker to finish its clips); publish the final counts and close the pipeline (also when interrupted:
    a clip still running then publishes nothing). Sets ``summary.frames``, ``summary.bag_s`` and
    ``summary.feed_lag_ms``."""
    t_first = t_last = None
    timer = _BagTimer(round(settings.outputs.diagnostics_period * 1e9))
    clock = _ReplayClock() if summary.realtime else None
    try:
        with tqdm(desc=f"replay {name}", unit=" frames", disable=not progress, leave=False) as bar:
            for event in events:
                if isinstance(event, ImageEvent | ImuEvent):
                    t_first = event.t_ns if t_first is None else t_first
                    t_last = event.t_ns
                    if clock is not None:
                        clock.wait_until(t_last)
                        sink.clock = clock.now_ns
                    if copy_inputs:
                        _copy_input(sink, event, settings)
                _feed(pipeline, event)
                if t_last is not None and timer.due(t_last):
                    pipeline.publish_diagnostics(t_last)
                is_frame = isinstance(event, ImageEvent) or (isinstance(event, DropEvent) and
                                                             event.reason.startswith("image"))
                summary.frames += is_frame
                bar.update(is_frame)
        pipeline.worker.wait_idle()  # realtime: the clips the node would still process (replay: nothing left)
        if t_last is not None:  # the final counts
            pipeline.publish_diagnostics(t_last)
    finally:
        pipeline.close(timeout=REALTIME_STOP_WAIT_S)
    summary.bag_s = 0.0 if t_first is None else (t_last - t_first) * 1e-9
    summary.feed_lag_ms = 0.0 if clock is None else clock.lag_ns * 1e-6
