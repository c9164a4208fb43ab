"""The shared per-stream pipeline: messages in (as numpy), the output messages of each clip out, through an
``OutputSink`` that the node implements with rclpy publishers and replay with an MCAP writer.

    add_image / add_imu -> ClipBuffer -> Worker (latest-wins thread, or synchronous for replay) -> process():
    RawClip -> undistorted Clip -> vi3_core.anchor.anchor(on_init=...) -> PoseArray, depth, PointCloud2, TF, status

Which result a message carries: ``~/poses``, ``~/depth`` and ``~/points`` carry each clip's final result (the
``init`` result in ``mode=init``, the refined one in ``cond``/``ttr``). In ``cond``/``ttr`` the fast ``init`` result
is published first on ``~/init/poses``, ``~/init/depth`` and ``~/init/points``. Every result is described on
``~/status`` (key ``result``: init | cond | ttr | none | skipped).

Dropped input messages are counted by reason, exactly, and reported on ``/diagnostics`` by ``publish_diagnostics``
once per ``diagnostics_period`` (the node's timer; replay in bag time) and in the next clip's status; only the first
drop of a reason not seen in the current or the previous period is published at once. They are the ``ClipBuffer``'s
drops, the frames ``add_image`` refuses (``image_unsupported``: not 8-bit mono or RGB; ``image_size_mismatch``: not
the calibrated size) and the messages the node or replay could not decode (``drop_input``: ``image_malformed``,
``image_unsupported``, ``imu_malformed``, ...). Every frame of a clip is checked against the calibration again when
the clip is processed (the calibration may have arrived since): a misfit skips the clip as ``image_size_mismatch``;
a frame is never stretched to the calibrated size.

Frames (see docs/node.md): poses and points are in ``clip_frame``, the clip's first camera (OpenCV optical axes,
metric), or in ``odom_frame`` with ``outputs_in_odom``; depth images in ``camera_frame``; TF ``camera_frame ->
clip_frame`` at the clip's last frame stamp.

With ``online`` (``vi3_core.online``), each clip's initialisation takes the priors carried from the previous clips,
and the clips are chained into one continuous odom trajectory: ``~/odom``, ``~/path`` and TF ``odom_frame ->
base_frame`` (``publish_odom_tf``); the status names the priors used, dropped (with the reason) and resets. Between
clips, ``~/odom/imu`` carries the last chained state propagated with every IMU sample (``vi3_ros.imu_odom``,
``imu_odom_rate``), restarted from each newly chained clip.

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
from typing import Any, Protocol

import numpy as np

from msg_adapters.camera_info import camera_info_to_calib
from msg_adapters.diagnostics import DiagStatus, Level, diagnostic_array
from msg_adapters.image import depth_to_image
from msg_adapters.pointcloud import point_cloud2
from msg_adapters.poses import odometry, path, pose_array, tf_message, tf_message_to_list
from msg_adapters.types import MessageTypes
from vi3_core.anchor import AnchorOptions, anchor, check_mode
from vi3_core.backbones import make_backbone
from vi3_core.camera import backproject
from vi3_core.dataset.calib import CameraCalib, load_calib
from vi3_core.errors import CalibrationError
from vi3_core.init import validate
from vi3_core.init.options import InitOptions
from vi3_core.online import ChainedClip, OnlineEstimator, OnlineOptions
from vi3_core.threads import use_torch_threads
from vi3_core.types import AnchorResult, Clip, Geometry, InitResult, InitStatus
from vi3_ros.clip_buffer import ClipBuffer, ClipBufferOptions, Drop, RawClip
from vi3_ros.imu_odom import ImuOdometry
from vi3_ros.params import options
from vi3_ros.worker import Worker


@dataclass(frozen=True)
class Output:
    """topic: relative to the node (``~/``) or absolute; msgtype: ROS 2 type name."""

    topic: str
    msgtype: str


OUTPUTS: dict[str, Output] = {
    "poses": Output("~/poses", "geometry_msgs/msg/PoseArray"),
    "depth": Output("~/depth", "sensor_msgs/msg/Image"),
    "points": Output("~/points", "sensor_msgs/msg/PointCloud2"),
    "init_poses": Output("~/init/poses", "geometry_msgs/msg/PoseArray"),
    "init_depth": Output("~/init/depth", "sensor_msgs/msg/Image"),
    "init_points": Output("~/init/points", "sensor_msgs/msg/PointCloud2"),
    "status": Output("~/status", "diagnostic_msgs/msg/DiagnosticArray"),
    "diagnostics": Output("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
    "tf": Output("/tf", "tf2_msgs/msg/TFMessage"),
    "odom": Output("~/odom", "nav_msgs/msg/Odometry"),
    "path": Output("~/path", "nav_msgs/msg/Path"),
    "odom_imu": Output("~/odom/imu", "nav_msgs/msg/Odometry"),
}
STATUS_NAME = "vi3: clip"
DIAG_NAME = "vi3: pipeline"


class OutputSink(Protocol):
    """Where the messages of a clip go. ``key`` is a key of ``OUTPUTS``; ``stamp_ns`` the message's header stamp
    (camera time), which replay uses as the log time."""

    def publish(self, key: str, msg: Any, stamp_ns: int) -> None: ...


#: Hz; the fastest IMU the buffer is sized for when it must keep seconds of history.
MAX_IMU_RATE_HZ = 400.0


def buffer_options(values: dict[str, Any]) -> ClipBufferOptions:
    """ClipBufferOptions from parameter values (see vi3_ros.params). With ``online``, the IMU history covers the
    bridge from the previous clip (up to ``online_max_bridge``), and the bounded IMU buffer holds that history (at up
    to MAX_IMU_RATE_HZ) plus a clip."""
    opts = options(ClipBufferOptions, values)
    if not values["online"]:
        return opts
    history = max(opts.history, values["online_max_bridge"])
    span = history + (opts.n - 1) * opts.stride * 0.2 + opts.imu_timeout + 1.0  # a clip at 5 Hz or faster
    return dataclasses.replace(opts, history=history,
                               imu_capacity=max(opts.imu_capacity, int(span * MAX_IMU_RATE_HZ)))


def calib_from_camera_info(K: np.ndarray, dist_model: str, dist: np.ndarray, size: tuple[int, int],
                           T_BC: np.ndarray) -> CameraCalib:
    """A CameraCalib from ``msg_adapters.camera_info.camera_info_to_calib``'s output and T_BC [4,4].

    plumb_bob maps to radtan when k3 = 0 (radtan has k1, k2, p1, p2); all-zero coefficients mean no distortion."""
    dist = np.asarray(dist, dtype=np.float64)
    if not dist.any():
        return CameraCalib(K, "none", np.zeros(0), size, T_BC)
    if dist_model == "equidistant":
        return CameraCalib(K, "equidistant", dist, size, T_BC)
    if dist_model in ("plumb_bob", "rational_polynomial") and not dist[4:].any():
        return CameraCalib(K, "radtan", dist[:4], size, T_BC)
    raise CalibrationError(f"CameraInfo distortion {dist_model} with coefficients {dist.tolist()} has terms beyond "
                           "k1, k2, p1, p2 that the undistorter does not model")


class Calibration:
    """The current camera calibration, assembled from a calibration file and/or live messages.

    Intrinsics come from CameraInfo (``set_intrinsics``) or the file; T_BC from /tf_static (``set_extrinsics``) or
    the file. ``current()`` raises CalibrationError naming what is still missing."""

    def __init__(self, file_calib: CameraCalib | None = None) -> None:
        self._file = file_calib
        self._intrinsics: tuple | None = None
        self._T_BC: np.ndarray | None = None
        self._cached: CameraCalib | None = file_calib

    def set_intrinsics(self, K: np.ndarray, dist_model: str, dist: np.ndarray, size: tuple[int, int]) -> None:
        new = (np.asarray(K, np.float64), dist_model, np.asarray(dist, np.float64), tuple(size))
        old = self._intrinsics
        if old is None or not (np.array_equal(old[0], new[0]) and old[1] == new[1] and np.array_equal(old[2], new[2])
                               and old[3] == new[3]):
            self._intrinsics, self._cached = new, None

    def set_extrinsics(self, T_BC: np.ndarray) -> None:
        T_BC = np.asarray(T_BC, np.float64)
        if self._T_BC is None or not np.array_equal(self._T_BC, T_BC):
            self._T_BC, self._cached = T_BC, None

    def size(self) -> tuple[int, int] | None:
        """(width, height) of the frames the current intrinsics are for, or None while there are none."""
        if self._intrinsics is not None:
            return tuple(self._intrinsics[3])
        return None if self._file is None else tuple(self._file.size)

    def current(self) -> CameraCalib:
        if self._cached is not None:
            return self._cached
        T_BC = self._T_BC if self._T_BC is not None else (self._file.T_BC if self._file is not None else None)
        if self._intrinsics is None and self._file is None:
            raise CalibrationError("no camera intrinsics yet: no CameraInfo received and no calib_file given")
        if T_BC is None:
            raise CalibrationError("no camera-IMU extrinsics: no /tf_static imu_frame -> camera_frame and no "
                                   "calib_file given")
        if self._intrinsics is not None:
            self._cached = calib_from_camera_info(*self._intrinsics, T_BC)
        else:
            f = self._file
            self._cached = CameraCalib(f.K, f.dist_model, f.dist, f.size, T_BC, f.rate_hz)
        return self._cached


class FrameMisfit(CalibrationError):
    """A frame of a clip does not fit the calibration (``vi3_core.dataset.calib.CameraCalib.check_frame``)."""


def make_clip(raw: RawClip, calib: CameraCalib) -> Clip:
    """Undistort the raw frames of ``raw`` with ``calib`` into a Clip (K of the undistorted images). Raises
    FrameMisfit naming the first frame whose size is not the calibrated one."""
    for i, im in enumerate(raw.images):
        problem = calib.check_frame(im)
        if problem is not None:
            raise FrameMisfit(f"frame {i} (stamp {int(raw.stamps_ns[i])} ns): {problem}")
    und = calib.undistorter()
    images = np.stack([und.apply(im) for im in raw.images])
    return Clip(stamps=raw.stamps, images=images, K=und.K, T_BC=calib.T_BC, imu=raw.imu, imu_history=raw.imu_history)


def frame_problem(image: np.ndarray) -> str | None:
    """Why the pipeline cannot take a raw frame whatever the calibration (not [H,W] or [H,W,3] uint8, or empty),
    or None."""
    shape, dtype = np.shape(image), np.asarray(image).dtype
    if dtype != np.uint8:
        return f"frame of dtype {dtype} (shape {list(shape)}): the pipeline takes 8-bit mono or RGB frames"
    if not (len(shape) == 2 or (len(shape) == 3 and shape[2] == 3)) or 0 in shape:
        return f"frame of shape {list(shape)}: the pipeline takes [H,W] mono or [H,W,3] RGB frames"
    return None


def cloud_points(geometry: Geometry, frames: np.ndarray, *, stride: int, conf_quantile: float,
                 max_depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Back-projected depth pixels of ``frames`` in the clip frame (the first camera), metres.

    Keeps every ``stride``-th pixel in each direction whose depth is finite, in (0, max_depth], and whose
    confidence is at least the ``conf_quantile`` quantile of the clip's confidences. Returns points [N,3] float32
    and confidence [N] float32. Vectorised over all selected frames."""
    P, d = backproject(geometry.depth[frames], geometry.K[frames], geometry.T_wc[frames], stride=stride)
    conf = geometry.conf[frames, ::stride, ::stride].astype(np.float64).reshape(len(P), -1)
    finite_conf = geometry.conf[np.isfinite(geometry.conf)]
    thr = np.quantile(finite_conf, conf_quantile) if conf_quantile > 0 and finite_conf.size else -np.inf
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(d) & (d > 0) & (d <= max_depth) & (conf >= thr)
    return P[keep].astype(np.float32), conf[keep].astype(np.float32)


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

    values: parameter values (``vi3_ros.params.resolve``); backbone: a ``vi3_core`` Backbone; calibration: the
    Calibration to use; synchronous: process each clip inside ``add_*`` (replay) instead of on the worker thread;
    on_report: called with each ClipReport (replay's summary). Thread-safe where the node needs it: outputs are
    published from the worker thread, inputs arrive on the executor's thread. torch's thread count of the process is
    set here from ``threads``, before the worker thread starts (``threads``: the count applied)."""

    def __init__(self, values: dict[str, Any], *, backbone: Any, calibration: Calibration, sink: OutputSink,
                 types: MessageTypes, synchronous: bool = False,
                 on_report: Callable[[ClipReport], None] | None = None) -> None:
        check_mode(backbone, values["mode"])  # an unsupported mode fails here, not once per clip
        self.values = dict(values)
        self.backbone = backbone
        self.calibration = calibration
        self.sink = sink
        self.types = types
        self.buffer = ClipBuffer(buffer_options(values))
        self._anchor_options = options(AnchorOptions, values)
        self._init_options = options(InitOptions, values)
        self._on_report = on_report
        online_options = options(OnlineOptions, values)
        self.online = OnlineEstimator(options=online_options, init_options=self._init_options) \
            if values["online"] else None
        self.imu_odom = ImuOdometry(values, init_options=self._init_options, max_tau_s=online_options.max_bridge_s,
                                    types=types, publish=self._publish) \
            if values["online"] and values["imu_odom_rate"] > 0 else None
        self._stopping = threading.Event()  # set by close(): ends a backbone_delay early
        self._path_ns: dict[float, int] = {}  # odom trajectory stamp (s) -> header stamp (ns) of ~/path
        self._lock = threading.Lock()  # guards the buffer and counters (executor thread vs worker thread)
        # Dropped input messages by reason: since the last clip status, in this diagnostics period, and the reasons
        # of the previous period (a reason in neither is news, published at once).
        self._input_drops: collections.Counter[str] = collections.Counter()
        self._period_drops: collections.Counter[str] = collections.Counter()
        self._previous_reasons: frozenset[str] = frozenset()
        self.outcomes: collections.Counter[str] = collections.Counter()
        self.message_drops: collections.Counter[str] = collections.Counter()  # drops before the buffer, by reason
        self.closing = False  # set by close(): outputs of a clip still running are not published
        self.threads = use_torch_threads(values["threads"])
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
        if self.imu_odom is not None:  # before a clip this sample completes is processed: it corrects the next one
            self.imu_odom.add(stamp_ns, gyro, accel)
        self._dispatch(events)

    def add_camera_info(self, msg: Any) -> None:
        """A ``sensor_msgs/CameraInfo`` (rclpy or rosbags): its intrinsics and distortion become the calibration's.
        Raises DataError for a malformed message, CalibrationError for intrinsics it cannot use."""
        self.calibration.set_intrinsics(*camera_info_to_calib(msg))

    def add_tf_static(self, msg: Any) -> None:
        """A ``tf2_msgs/TFMessage`` from /tf_static: its ``imu_frame -> camera_frame`` transform (frame names
        compared without a leading "/") becomes T_BC; other transforms are ignored. Raises DataError when malformed."""
        imu, camera = self.values["imu_frame"], self.values["camera_frame"]
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
            elif self._count_input_drop(ev.reason):
                self._publish_diagnostics(Level.WARN, f"{ev.reason}: {ev.detail}", ev.stamp_ns)

    def _count_input_drop(self, reason: str) -> bool:
        """Count one dropped input message; True when its reason is news (not seen in this or the previous
        diagnostics period), which is published at once. Every other drop waits for ``publish_diagnostics``."""
        with self._lock:
            news = reason not in self._period_drops and reason not in self._previous_reasons
            self._input_drops[reason] += 1
            self._period_drops[reason] += 1
        return news

    # ---- worker side ----------------------------------------------------------------------------------------

    def _process(self, raw: RawClip) -> None:
        t_start = time.perf_counter()
        stamp_ns = int(raw.stamps_ns[-1])
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
        # The initialisation's own data checks, before the backbone: a clip it would reject costs no inference.
        reason = validate.check_stamps(clip.stamps) or validate.check_imu(clip.imu, clip.stamps, self._init_options)
        if reason is not None:
            init = InitResult(status=InitStatus.REJECTED, reason=reason)
            self._publish_status(raw, init, None, "none", time.perf_counter() - t_start)
            return
        if self.values["backbone_delay"] > 0 and self._stopping.wait(self.values["backbone_delay"]):
            return  # closing: the clip's outputs would be discarded anyway
        refine = self.values["mode"] != "init"

        def on_init(result: AnchorResult) -> None:
            if refine and result.init.ok:
                self._publish_geometry(raw, result.geometry, prefix="init_")
                self._publish_status(raw, result.init, result, "init", time.perf_counter() - t_start)

        online = self.online
        result = anchor(clip, self.backbone, mode=self.values["mode"], options=self._anchor_options,
                        init_options=self._init_options, on_init=on_init,
                        init=(lambda base: online.initialise(clip, base)) if online is not None else None)
        chained = online.update(clip, result) if online is not None else None
        latency = time.perf_counter() - t_start
        if result.init.ok and result.mode != "none":
            T_OC1 = chained.T_OB[0] @ clip.T_BC if chained is not None and self.values["outputs_in_odom"] else None
            self._publish_geometry(raw, result.geometry, prefix="", T_OC1=T_OC1)
        if chained is not None:
            self._publish_odom(raw, clip, chained)
            if self.imu_odom is not None:
                self.imu_odom.restart(online.state, self._imu_since)
        self._publish_status(raw, result.init, result, result.mode if result.init.ok else "none", latency)

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

    def _publish_geometry(self, raw: RawClip, geometry: Geometry, *, prefix: str,
                          T_OC1: np.ndarray | None = None) -> None:
        """Poses, depth, points (and the clip TF) of a result; with ``T_OC1`` [4,4] (the clip's first camera in
        odom) poses and points are expressed in ``odom_frame``."""
        v, types = self.values, self.types
        stamp = int(raw.stamps_ns[-1])
        frame = v["clip_frame"] if T_OC1 is None else v["odom_frame"]
        T_wc = geometry.T_wc if T_OC1 is None else T_OC1 @ geometry.T_wc
        self._publish(prefix + "poses", pose_array(T_wc, stamp_ns=stamp, frame_id=frame, types=types), stamp)
        frames = np.arange(geometry.n) if v["depth_frames"] == "all" else np.array([geometry.n - 1])
        for i in frames:
            s = int(raw.stamps_ns[i])
            self._publish(prefix + "depth", depth_to_image(geometry.depth[i], stamp_ns=s,
                                                               frame_id=v["camera_frame"], types=types), s)
        frames = np.arange(geometry.n) if v["points_frames"] == "all" else np.array([geometry.n - 1])
        pts, conf = cloud_points(geometry, frames, stride=v["points_stride"], conf_quantile=v["points_conf_quantile"],
                                 max_depth=v["points_max_depth"])
        if T_OC1 is not None:
            pts = (pts.astype(np.float64) @ T_OC1[:3, :3].T + T_OC1[:3, 3]).astype(np.float32)
        self._publish(prefix + "points", point_cloud2(pts, confidence=conf, stamp_ns=stamp,
                                                          frame_id=frame, types=types), stamp)
        if v["publish_tf"] and not prefix:
            T_last_clip = np.linalg.inv(geometry.T_wc[-1])
            self._publish("tf", tf_message([(T_last_clip, v["camera_frame"], v["clip_frame"], stamp)],
                                               types=types), stamp)

    def _publish_odom(self, raw: RawClip, clip: Clip, chained: ChainedClip) -> None:
        """~/odom (pose and twist of base_frame at the clip's last frame), ~/path (the latest ``path_max_poses``
        poses of the odom trajectory) and, with ``publish_odom_tf``, TF odom_frame -> base_frame."""
        v, types = self.values, self.types
        stamp = int(raw.stamps_ns[-1])
        T = chained.T_OB[-1]
        gyro = np.array([np.interp(clip.stamps[-1], clip.imu.t, clip.imu.gyro[:, a]) for a in range(3)])
        self._publish("odom", odometry(T, T[:3, :3].T @ chained.v_O[-1], gyro - self.online.state.bg,
                                           stamp_ns=stamp, frame_id=v["odom_frame"], child_frame_id=v["base_frame"],
                                           types=types), stamp)
        traj = self.online.trajectory
        keep = slice(max(len(traj.stamps) - v["path_max_poses"], 0), None)
        # The header stamps of the frames (exact ns), kept for the poses the path still shows.
        self._path_ns.update(zip(clip.stamps.tolist(), raw.stamps_ns.tolist()))
        self._path_ns = {t: self._path_ns[t] for t in traj.stamps[keep].tolist()}
        stamps_ns = list(self._path_ns.values())
        self._publish("path", path(traj.T_OB[keep], stamp_ns=stamp, frame_id=v["odom_frame"], types=types,
                                       stamps_ns=stamps_ns), stamp)
        if v["publish_odom_tf"]:
            self._publish("tf", tf_message([(T, v["odom_frame"], v["base_frame"], stamp)], types=types), stamp)

    def _take_input_drops(self) -> str:
        """The input drops since the previous clip status (``reason:count, ...``), and a fresh count."""
        with self._lock:
            text = _counts_text(self._input_drops)
            self._input_drops.clear()
        return text

    def _publish_status(self, raw: RawClip, init: InitResult, result: AnchorResult | None, kind: str,
                        latency: float) -> None:
        """~/status (and, for final results, /diagnostics) of one result; ``result`` None when anchoring did not
        run (data rejected before the backbone)."""
        drops = self._take_input_drops()
        level = Level.OK if init.ok else (Level.WARN if init.status is InitStatus.UNOBSERVABLE else Level.ERROR)
        if drops and level is Level.OK:
            level = Level.WARN
        reason = init.reason if not init.ok else (result.status or "ok")
        alpha = result.alpha if result is not None else float("nan")
        values = {"clip": raw.index, "result": kind, "init_status": init.status.value, "reason": reason,
                  "scale": f"{init.scale:.6g}", "scale_sigma": f"{init.scale_sigma:.3g}",
                  "scale_rel_sigma": f"{init.diagnostics.get('scale_rel_sigma', float('nan')):.3g}",
                  "alpha": f"{alpha:.6g}", "gravity_source": init.gravity_source,
                  "consensus_deg": f"{init.consensus_deg:.4g}", "g": _vec(init.g), "v1": _vec(init.v1),
                  "bg": _vec(init.bg), "ba": _vec(init.ba), "t_first": f"{raw.stamps[0]:.9f}",
                  "t_last": f"{raw.stamps[-1]:.9f}",
                  "input_drops": drops, "latency_ms": f"{latency * 1e3:.1f}"}
        if "online" in init.diagnostics:
            values["online"] = init.diagnostics["online"]
            resets = self.online.trajectory.resets
            values["odom_segment"] = len(resets)  # 0: the first; each reset starts one (its first frame, IMU time)
            if resets:
                values["odom_segment_start"] = f"{resets[-1]:.9f}"
        if result is not None and kind != "init":
            values.update({f"loss_{k}": f"{float(np.asarray(a).reshape(-1)[-1]):.6g}"
                           for k, a in sorted(result.losses.items()) if np.asarray(a).size})
        if result is not None:
            values.update({f"timing_{k}": f"{s:.4g}" for k, s in sorted(result.timings.items())})  # units in k
        self._emit(ClipReport(raw.index, kind, reason, int(raw.stamps_ns[-1]), result, latency),
                   DiagStatus(level, STATUS_NAME, f"{kind}: {reason}", self.values["clip_frame"], values),
                   final=kind != "init" or self.values["mode"] == "init")

    def _report_skip(self, index: int, reason: str, detail: str, stamp_ns: int, level: Level = Level.WARN) -> None:
        values = {"clip": index, "result": "skipped", "reason": reason, "detail": detail,
                  "input_drops": self._take_input_drops()}
        self._emit(ClipReport(index, "skipped", reason, stamp_ns),
                   DiagStatus(level, STATUS_NAME, f"skipped: {reason}: {detail}", self.values["clip_frame"], values),
                   final=True)

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
            values = {"clips_emitted": self.buffer.clips, "worker_processed": self.worker.processed,
                      "worker_replaced": self.worker.replaced, "worker_errors": self.worker.errors}
            values.update({f"outcome_{k}": n for k, n in sorted(self.outcomes.items())})
            values.update({f"drop_{k}": n for k, n in sorted((self.buffer.counts + self.message_drops).items())})
        if self.imu_odom is not None:
            values["imu_odom"] = self.imu_odom.status
        return DiagStatus(level, DIAG_NAME, message, self.values["clip_frame"], values)

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
        msg = diagnostic_array([self.diagnostics_status(level, message)], stamp_ns=stamp_ns, types=self.types)
        self._publish("diagnostics", msg, stamp_ns)


def make_pipeline(values: dict[str, Any], *, sink: OutputSink, types: MessageTypes, synchronous: bool = False,
                  on_report: Callable[[ClipReport], None] | None = None) -> Pipeline:
    """The pipeline of parameter ``values``: backbone from ``backbone``/``device``/``checkpoint``, calibration
    file from ``calib_file`` (empty: calibration must arrive as CameraInfo and /tf_static)."""
    backbone = make_backbone(values["backbone"], device=values["device"], checkpoint=values["checkpoint"] or None)
    calibration = Calibration(load_calib(values["calib_file"]) if values["calib_file"] else None)
    return Pipeline(values, backbone=backbone, calibration=calibration, sink=sink, types=types,
                    synchronous=synchronous, on_report=on_report)


def _counts_text(counts: collections.Counter[str]) -> str:
    """``reason:count, ...`` sorted by reason ("" when empty)."""
    return ", ".join(f"{k}:{n}" for k, n in sorted(counts.items()))


def _vec(v: np.ndarray) -> str:
    return " ".join(f"{x:.6g}" for x in np.asarray(v, dtype=np.float64).reshape(-1))
