"""The shared per-stream pipeline: messages in (as numpy), the output messages of each clip out, through an
``OutputSink`` that the node implements with rclpy publishers and replay with an MCAP writer.

    add_image / add_imu -> ClipBuffer -> Worker (latest-wins thread, or synchronous for replay) -> _process():
    RawClip -> undistorted Clip (``calibration``) -> vi3_core.online.StreamEstimator.process -> ``outputs``

Which result a message carries: ``~/poses``, ``~/depth`` and ``~/points`` carry each clip's final result (the
``init`` result in ``mode=init``, the refined one in ``cond``/``ttr``). In ``cond``/``ttr`` the fast ``init`` result
is published first on ``~/init/poses``, ``~/init/depth`` and ``~/init/points``. Every result is described on
``~/status`` (key ``result``: init | cond | ttr | none | skipped).

Dropped input messages are counted by reason, exactly, and reported on ``/diagnostics`` by ``publish_diagnostics`` once
per ``diagnostics_period`` (the node's timer; replay in bag time) and in the next clip's status; only the first drop of
a reason not seen in the current or the previous period is published at once. /diagnostics is stamped with one clock:
the node's (``clock``), or in replay the data's own stamps (bag time). They are the ``ClipBuffer``'s drops (lost frames
and IMU samples among them, counted from the stamps), the frames ``add_image`` refuses (``image_unsupported``: not 8-bit
mono or RGB; ``image_size_mismatch``: not the calibrated size) and the messages the node or replay could not decode
(``drop_input``: ``image_malformed``, ``image_unsupported``, ``imu_malformed``, ...). Every frame of a clip is checked
against the calibration again when the clip is processed (the calibration may have arrived since): a misfit skips the
clip as ``image_size_mismatch``; a frame is never stretched to the calibrated size.

With ``online``, each clip's initialisation is the stream's window, and the clips are chained into one continuous
odom trajectory: ``~/odom``, ``~/path`` and TF ``odom_frame -> base_frame`` (``publish_odom_tf``); the status names
the window's decision. Between clips, ``~/odom/imu`` carries the last chained state propagated with every IMU sample
(``vi3_ros.imu_odom``, ``imu_odom_rate``), restarted from each newly chained clip. With ``px4_odom`` / ``mavros_odom``
the one or the other also goes to a flight controller (``vi3_ros.flight_odom``, ``flight_odom_source``).

When time goes back for good (``ClipBuffer``'s ``Rewind``: a looped recording, a restarted driver or simulator) the
buffer starts over at once, ``/diagnostics`` says so (WARN, ``time_reset``), and the next status counts it in
``input_drops``; the IMU-rate odometry forgets its state at the first sample after it, and the stream estimator (its
window, biases and odom state) at the first clip after it, which starts a new odom segment at the odom origin.
Clips completed before it are still processed as they were.

``backbone_delay`` pauses every clip's processing before the backbone (a slower model, for testing); ``close`` ends
the pause.
"""

from __future__ import annotations

import collections
import dataclasses
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters.camera_info import camera_info_to_calib
from msg_adapters.diagnostics import DiagStatus, Level, diagnostic_array
from msg_adapters.poses import tf_message_to_list
from msg_adapters.types import MessageTypes
from vi3_core.backbones import make_backbone
from vi3_core.backbones.base import Backbone
from vi3_core.dataset.calib import load_calib
from vi3_core.errors import CalibrationError, DataError
from vi3_core.online import InOdom, OnlineDecision, StreamEstimator
from vi3_core.online.calibration import RigEstimate
from vi3_core.threads import use_threads
from vi3_core.types import AnchorResult, Clip, InitResult
from vi3_ros.calibration import Calibration, FrameMisfit, frame_problem, make_clip
from vi3_ros.clip_buffer import ClipBuffer, ClipBufferOptions, Drop, RawClip, Rewind
from vi3_ros.flight_odom import FlightOdometry
from vi3_ros.imu_odom import ImuOdometry
from vi3_ros.outputs import DIAG_NAME, STATUS_NAME, ClipPublisher, OutputSink, clip_status, result_reason
from vi3_ros.settings import Settings
from vi3_ros.worker import Worker

#: Hz; the fastest IMU the buffer is sized for when it must keep seconds of history.
MAX_IMU_RATE_HZ = 400.0


def buffer_options(settings: Settings) -> ClipBufferOptions:
    """The clip buffer's options of ``settings``: with ``online``, the IMU history covers the bridge from the previous
    clip (up to ``online_max_bridge``), the bounded IMU buffer holds that history (at up to MAX_IMU_RATE_HZ) plus a
    clip, and without a ``hop`` clips start every (clip_length - shared_frames) * stride frames (each shares its first
    frames with the one before). Raises DataError when shared_frames leaves a clip no frame of its own."""
    opts = settings.buffer
    if not settings.stream.online:
        return opts
    shared = settings.online.shared_frames
    if shared >= opts.clip_length:
        raise DataError(f"parameters: shared_frames {shared} must be smaller than clip_length {opts.clip_length}")
    history = max(opts.imu_history, settings.online.online_max_bridge)
    span = history + (opts.clip_length - 1) * opts.stride * 0.2 + opts.imu_timeout + 1.0  # a clip at 5 Hz or faster
    hop = opts.hop if opts.hop is not None else settings.online.clip_hop(opts.clip_length, opts.stride)
    return dataclasses.replace(opts, imu_history=history, hop=hop,
                               imu_buffer=max(opts.imu_buffer, int(span * MAX_IMU_RATE_HZ)))


@dataclass
class ClipReport:
    """What happened to one clip: index, result (init | cond | ttr | none | skipped), reason, stamp
    (camera time, ns), the AnchorResult when one exists, and the wall-clock latency of processing in seconds."""

    index: int
    result: str
    reason: str
    stamp_ns: int
    anchor: AnchorResult | None = None
    latency_s: float = float("nan")


class Pipeline:
    """One camera + IMU stream through buffer, worker and anchoring, to an OutputSink.

    settings: the stream's ``Settings`` (``vi3_ros.params.resolve``); backbone: a ``vi3_core`` Backbone; calibration:
    the Calibration to use; synchronous: process each clip inside ``add_*`` (replay) instead of on the worker thread;
    on_report: called with each ClipReport (replay's summary); clock: the clock (ns) that stamps /diagnostics (the
    node's: sim time with ``use_sim_time``), None: the stamps of the data they report (replay, bag time). Thread-safe
    where the node needs it: outputs are published from the worker thread, inputs arrive on the executor's thread.
    torch's thread count of the process is set here from ``threads``, before the worker thread starts (``threads``:
    the count applied)."""

    def __init__(self, settings: Settings, *, backbone: Any, calibration: Calibration, sink: OutputSink,
                 types: MessageTypes, synchronous: bool = False,
                 on_report: Callable[[ClipReport], None] | None = None, clock: Callable[[], int] | None = None) -> None:
        self.settings = settings
        stream = dataclasses.replace(settings.stream, all_depth=settings.outputs.all_depth)
        self.stream = StreamEstimator(backbone, options=stream, online=settings.online, init=settings.init,
                                      anchor=settings.anchor, calibration=settings.calibration)
        self.calibration = calibration
        self.sink = sink
        self.types = types
        self.buffer = ClipBuffer(buffer_options(settings))
        self._on_report = on_report
        self._clock = clock
        self._epoch = 0  # the buffer epoch of the clips the stream estimator has seen (worker side)
        self._rewind = ""  # why time went back, last time it did
        self.flight = FlightOdometry(settings, types=types, publish=self._publish, clock=clock) \
            if settings.flight.outputs_on else None
        self.outputs = ClipPublisher(settings, types=types, publish=self._publish, flight=self.flight)
        self.imu_odom = ImuOdometry(settings, types=types, publish=self._publish, flight=self.flight) \
            if settings.stream.online and settings.outputs.imu_odom_rate > 0 else None
        self._stopping = threading.Event()  # set by close(): ends a backbone_delay early
        self._rig: RigEstimate | None = None  # the rig's latest self-calibration
        self._rig_note = ""  # why the last clip did not add to it, or did not take all of it
        self._lock = threading.Lock()  # guards the buffer and counters (executor thread vs worker thread)
        # Dropped input messages by reason: since the last clip status, in this diagnostics period, and the reasons
        # of the previous period (a reason in neither is news, published at once).
        self._input_drops: collections.Counter[str] = collections.Counter()
        self._period_drops: collections.Counter[str] = collections.Counter()
        self._previous_reasons: frozenset[str] = frozenset()
        self.outcomes: collections.Counter[str] = collections.Counter()
        self.odom_only = 0  # clips placed in ~/odom at the window's scale without a claim (``places_unclaimed``)
        self.output_errors: collections.Counter[str] = collections.Counter()  # messages not built, by output key
        self.message_drops: collections.Counter[str] = collections.Counter()  # drops before the buffer, by reason
        self.closing = False  # set by close(): outputs of a clip still running are not published
        self.threads = use_threads(settings.model.threads)
        self.worker = Worker(self._process, on_error=self._on_error, on_replaced=self._on_replaced,
                             synchronous=synchronous)

    # ---- inputs (any thread) --------------------------------------------------------------------------------

    def add_image(self, stamp_ns: int, image: np.ndarray) -> None:
        """A camera frame: message stamp (camera time, ns) and the raw image [H,W] or [H,W,3] uint8. Any other
        frame is dropped as ``image_unsupported``, one whose size is not the calibration's (when it is known) as
        ``image_size_mismatch``."""
        problem = frame_problem(image)
        if problem is not None:
            self.drop_input("image_unsupported", stamp_ns, problem)
            return
        size = self.calibration.size()
        h, w = image.shape[:2]
        if size is not None and (w, h) != size:
            self.drop_input("image_size_mismatch", stamp_ns, f"frame is {w}x{h} but the calibration is for "
                            f"{size[0]}x{size[1]}")
            return
        with self._lock:
            events = self.buffer.add_image(stamp_ns, image)
        self._dispatch(events)

    def drop_input(self, reason: str, stamp_ns: int | None, detail: str) -> None:
        """Count one input message dropped before the buffer (e.g. ``image_malformed``: it could not be decoded),
        by ``reason``, like the buffer's drops; ``stamp_ns`` its header stamp (None: unreadable)."""
        with self._lock:
            self.message_drops[reason] += 1
            stamp = self.buffer.last_stamp_ns() if stamp_ns is None else int(stamp_ns)
        self._dispatch([Drop(reason, stamp * 1e-9, stamp, detail)])

    @property
    def drop_counts(self) -> collections.Counter[str]:
        """Every dropped input message and clip so far, by reason (the buffer's and ``drop_input``'s)."""
        with self._lock:
            return self.buffer.counts + self.message_drops

    def add_imu(self, stamp_ns: int, gyro, accel, orientation=None) -> None:
        """An IMU sample: message stamp (IMU time, ns), gyro [3] rad/s, accel [3] m/s^2, orientation [4] xyzw or
        None."""
        with self._lock:
            events = self.buffer.add_imu(stamp_ns, gyro, accel, orientation)
            epoch = self.buffer.epoch
        if self.imu_odom is not None:  # before a clip this sample completes is processed: it corrects the next one
            self.imu_odom.add(stamp_ns, gyro, accel, epoch)
        self._dispatch(events)

    def add_camera_info(self, msg: Any) -> None:
        """A ``sensor_msgs/CameraInfo`` (rclpy or rosbags): its intrinsics and distortion become the calibration's.
        Raises DataError for a malformed message, CalibrationError for intrinsics it cannot use."""
        self.calibration.set_intrinsics(*camera_info_to_calib(msg))

    def add_tf_static(self, msg: Any) -> None:
        """A ``tf2_msgs/TFMessage`` from /tf_static: its ``imu_frame -> camera_frame`` transform (frame names
        compared without a leading "/") becomes T_BC; other transforms are ignored. Raises DataError when malformed."""
        imu, camera = self.settings.frames.imu_frame, self.settings.frames.camera_frame

        for T, parent, child, _ in tf_message_to_list(msg):
            if parent.lstrip("/") == imu and child.lstrip("/") == camera:
                self.calibration.set_extrinsics(T)

    def close(self, timeout: float | None = None) -> None:
        """Stop: replay (synchronous) has nothing left to wait for; the node's worker thread gets up to ``timeout``
        s to finish the clip it is processing (whose outputs are then no longer published: the node is shutting
        down), a waiting clip is discarded."""
        self.closing = True
        self._stopping.set()
        self.worker.stop(timeout)

    def _dispatch(self, events: list[RawClip | Drop]) -> None:
        for ev in events:
            if isinstance(ev, RawClip):
                self.worker.submit(ev)
            elif ev.clip >= 0:
                self._report_skip(ev.clip, ev.reason, ev.detail, ev.stamp_ns)
            else:
                news = self._count_input_drop(ev.reason, ev.count)
                if isinstance(ev, Rewind):
                    with self._lock:
                        self._rewind = ev.detail
                if news or isinstance(ev, Rewind):  # a time reset is always published at once
                    self._publish_diagnostics(Level.WARN, f"{ev.reason}: {ev.detail}", ev.stamp_ns)

    def _count_input_drop(self, reason: str, count: int = 1) -> bool:
        """Count ``count`` dropped input messages of one reason; True when it is news (not seen in this or the
        previous diagnostics period), which is published at once. Every other drop waits for ``publish_diagnostics``."""
        with self._lock:
            news = reason not in self._period_drops and reason not in self._previous_reasons
            self._input_drops[reason] += count
            self._period_drops[reason] += count
        return news

    # ---- worker side ----------------------------------------------------------------------------------------

    def _process(self, raw: RawClip) -> None:
        t_start = time.perf_counter()
        stamp_ns = int(raw.stamps_ns[-1])
        if raw.epoch != self._epoch:  # the first clip since time went back: the stream starts over
            self._epoch = raw.epoch
            with self._lock:
                why = self._rewind
            self.stream.reset(f"time went back ({why})")
        try:
            calib = self.calibration.current()
        except CalibrationError as exc:
            self._report_skip(raw.index, "calibration_missing", str(exc), stamp_ns)
            return
        try:
            clip = make_clip(raw, calib)
        except FrameMisfit as exc:
            self._report_skip(raw.index, "image_size_mismatch", str(exc), stamp_ns)
            return

        def on_init(processed: Clip, result: AnchorResult) -> None:
            self.outputs.geometry(processed, result.geometry, prefix="init_")
            self._publish_status(raw, processed, result.init, "init", time.perf_counter() - t_start, result=result,
                                 decision=self.stream.decision)

        outcome = self.stream.process(clip, on_init=on_init, before_backbone=self._backbone_delay)
        if outcome is None:
            return  # closing: the clip's outputs would be discarded anyway
        latency = time.perf_counter() - t_start
        chained, clip = outcome.chained, outcome.clip
        self._rig, self._rig_note = outcome.calibration, outcome.calibration_note
        with self._lock:
            self.buffer.imu_lead = self.stream.imu_lead
        if outcome.init.ok and outcome.mode != "none":
            T_OC1 = chained.T_OB[0] @ clip.T_BC if chained is not None and self.settings.frames.outputs_in_odom \
                else None
            self.outputs.geometry(clip, outcome.result.geometry, prefix="", T_OC1=T_OC1)
        if chained is not None:
            if outcome.in_odom is InOdom.WINDOW_SCALE:
                with self._lock:
                    self.odom_only += 1
            anchor = self.outputs.odom(clip, outcome, self.stream.trajectory)
            if self.imu_odom is not None:
                self.imu_odom.restart(outcome.state, self._imu_since, raw.epoch, anchor)
        self._publish_status(raw, clip, outcome.init, outcome.mode, latency, result=outcome.result,
                             decision=outcome.decision, in_odom=outcome.in_odom)

    def _backbone_delay(self) -> bool:
        """``backbone_delay`` s before the backbone; False when ``close`` ended it (the clip is abandoned)."""
        delay = self.settings.model.backbone_delay
        return not (delay > 0 and self._stopping.wait(delay))

    def _imu_since(self, t: float) -> Any:
        with self._lock:
            return self.buffer.imu_since(t)

    def _on_error(self, raw: RawClip, exc: BaseException) -> None:
        self._report_skip(raw.index, "error", f"{type(exc).__name__}: {exc}", int(raw.stamps_ns[-1]), Level.ERROR)

    def _on_replaced(self, raw: RawClip) -> None:
        self._report_skip(raw.index, "worker_busy", "replaced by a newer clip while the worker was busy",
                          int(raw.stamps_ns[-1]))

    # ---- outputs --------------------------------------------------------------------------------------------

    def _publish(self, key: str, msg: Any, stamp_ns: int) -> None:
        """One output message to the sink, unless the pipeline is closing (the node shuts down mid-clip)."""
        if not self.closing:
            self.sink.publish(key, msg, stamp_ns)

    def _take_input_drops(self) -> str:
        """The input drops since the previous clip status (``reason:count, ...``), and a fresh count."""
        with self._lock:
            text = _counts_text(self._input_drops)
            self._input_drops.clear()
        return text

    def _publish_status(self, raw: RawClip, clip: Clip, init: InitResult, kind: str, latency: float, *,
                        result: AnchorResult | None, decision: OnlineDecision | None,
                        in_odom: InOdom | None = None) -> None:
        """~/status (and, for final results, /diagnostics) of one result of ``raw`` processed as ``clip``; ``result``
        None when anchoring did not run (data rejected before the backbone); ``decision``: the online window's (None
        without online); ``in_odom``: how the clip went into odom (None: not known yet)."""
        errors = self.outputs.take_errors()
        with self._lock:
            self.output_errors.update(key for key, _ in errors)
        status = clip_status(raw.index, clip, init, kind, latency, drops=self._take_input_drops(),
                             clip_frame=self.settings.frames.clip_frame, result=result, decision=decision,
                             trajectory=self.stream.trajectory, rig=self._rig, rig_note=self._rig_note,
                             output_errors=errors, front_end=self._front_end(result), in_odom=in_odom)
        self._emit(ClipReport(raw.index, kind, result_reason(init, result), int(raw.stamps_ns[-1]), result, latency),
                   status, final=kind != "init" or self.settings.stream.mode == "init")

    def _front_end(self, result: AnchorResult | None) -> dict | None:
        """Where the backbone's front end lost the tracks of the clip it just predicted (None: it did not run, or it
        has no front end)."""
        return self.stream.backbone.diagnostics().get("front_end") if result is not None else None

    def _report_skip(self, index: int, reason: str, detail: str, stamp_ns: int, level: Level = Level.WARN) -> None:
        values = {"clip": index, "result": "skipped", "reason": reason, "detail": detail,
                  "input_drops": self._take_input_drops()}
        status = DiagStatus(level, STATUS_NAME, f"skipped: {reason}: {detail}", self.settings.frames.clip_frame, values)
        self._emit(ClipReport(index, "skipped", reason, stamp_ns), status, final=True)

    def _emit(self, report: ClipReport, status: DiagStatus, *, final: bool) -> None:
        self._publish("status", diagnostic_array([status], stamp_ns=report.stamp_ns, types=self.types),
                          report.stamp_ns)
        if final:
            with self._lock:
                self.outcomes[report.result if report.result != "skipped" else f"skipped:{report.reason}"] += 1
            self._publish_diagnostics(status.level, status.message, report.stamp_ns)
            if self._on_report is not None:
                self._on_report(report)

    def diagnostics_status(self, level: Level = Level.OK, message: str = "running") -> DiagStatus:
        """The pipeline's summary: counters of clips, outcomes, buffer drops and worker replacements."""
        with self._lock:
            values = {"clips_emitted": self.buffer.clips, "imu_samples": self.buffer.imu_samples,
                      "worker_processed": self.worker.processed,
                      "worker_replaced": self.worker.replaced, "worker_errors": self.worker.errors}
            values.update({f"outcome_{k}": n for k, n in sorted(self.outcomes.items())})
            values["odom_only"] = self.odom_only
            values.update({f"output_error_{k}": n for k, n in sorted(self.output_errors.items())})
            values.update({f"drop_{k}": n for k, n in sorted((self.buffer.counts + self.message_drops).items())})
        if self.imu_odom is not None:
            values["imu_odom"] = self.imu_odom.status
        rig = self._rig
        if rig is not None:
            values["rig"] = rig.describe()
            off = rig.off_by()
            if off and level is Level.OK:
                level, message = Level.WARN, (f"the configured calibration is off: {off} (estimated from the flight; "
                                              "vi3 calib prints the corrected Kalibr file)")
        return DiagStatus(level, DIAG_NAME, message, self.settings.frames.clip_frame, values)

    def publish_diagnostics(self, stamp_ns: int) -> None:
        """The periodic /diagnostics summary (every ``diagnostics_period``: the node's timer, replay in bag time),
        stamped ``stamp_ns``: WARN naming the input drops of the period by reason with their exact counts, else OK
        "running". Starts the next period."""
        with self._lock:
            drops, self._period_drops = self._period_drops, collections.Counter()
            self._previous_reasons = frozenset(drops)
        if drops:
            self._publish_diagnostics(Level.WARN, f"input drops in the last period: {_counts_text(drops)}", stamp_ns)
        else:
            self._publish_diagnostics(Level.OK, "running", stamp_ns)

    def _publish_diagnostics(self, level: Level, message: str, stamp_ns: int) -> None:
        """/diagnostics, stamped by ``clock`` when there is one, else ``stamp_ns`` (the data's time)."""
        stamp_ns = self._clock() if self._clock is not None else stamp_ns
        msg = diagnostic_array([self.diagnostics_status(level, message)], stamp_ns=stamp_ns, types=self.types)
        self._publish("diagnostics", msg, stamp_ns)


def make_pipeline(settings: Settings, *, sink: OutputSink, types: MessageTypes, synchronous: bool = False,
                  on_report: Callable[[ClipReport], None] | None = None,
                  clock: Callable[[], int] | None = None, backbone: Backbone | None = None) -> Pipeline:
    """The pipeline of ``settings``: backbone from ``backbone``/``device``/``checkpoint`` (or the ``backbone`` given:
    ``vi3 bench pipeline``'s recorded one), calibration file from ``calib_file`` (empty: calibration must arrive as
    CameraInfo and /tf_static); ``clock``: see ``Pipeline``."""
    model, inputs = settings.model, settings.inputs
    if backbone is None:
        backbone = make_backbone(model.backbone, device=model.device, checkpoint=model.checkpoint or None,
                                 **model.backbone_options())
    calibration = Calibration(load_calib(inputs.calib_file) if inputs.calib_file else None)
    return Pipeline(settings, backbone=backbone, calibration=calibration, sink=sink, types=types,
                    synchronous=synchronous, on_report=on_report, clock=clock)


def _counts_text(counts: collections.Counter[str]) -> str:
    """``reason:count, ...`` sorted by reason ("" when empty)."""
    return ", ".join(f"{k}:{n}" for k, n in sorted(counts.items()))
