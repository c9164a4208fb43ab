"""What a stream publishes: the output topics, the sink that carries them (rclpy publishers in the node, an MCAP
writer in replay), and the messages of one clip's outcome: poses, depth, points and the clip TF, ``~/odom``,
``~/path``, the odom TF and the flight controllers' odometry at clip rate, and the clip's ``~/status``.

Frames (see docs/node.md): poses and points are in ``clip_frame``, the clip's first camera (OpenCV optical axes,
metric), or in ``odom_frame`` with ``outputs_in_odom``; depth images in ``camera_frame``; TF ``camera_frame ->
clip_frame`` at the clip's last frame stamp; ``~/odom`` and its TF ``odom_frame -> base_frame``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from msg_adapters.camera_info import calib_to_camera_info
from msg_adapters.diagnostics import DiagStatus, Level
from msg_adapters.image import depth_to_image
from msg_adapters.pointcloud import point_cloud2
from msg_adapters.poses import odometry, path, pose_array, tf_message
from msg_adapters.types import MessageTypes
from vi3_core.backbones.front_end import FrameLosses
from vi3_core.camera import backproject
from vi3_core.online import ClipOutcome, InOdom, OnlineDecision, Trajectory
from vi3_core.online.calibration import RigEstimate
from vi3_core.types import AnchorResult, Clip, Geometry, InitResult, InitStatus
from vi3_ros.flight_odom import Anchor, FlightOdometry
from vi3_ros.imu_odom import chained_covariances, start_covariances
from vi3_ros.settings import Settings


@dataclass(frozen=True)
class Output:
    """topic: relative to the node (``~/``) or absolute; msgtype: ROS 2 type name."""

    topic: str
    msgtype: str


OUTPUTS: dict[str, Output] = {
    "poses": Output("~/poses", "geometry_msgs/msg/PoseArray"),
    "depth": Output("~/depth", "sensor_msgs/msg/Image"),
    "depth_info": Output("~/depth/camera_info", "sensor_msgs/msg/CameraInfo"),
    "points": Output("~/points", "sensor_msgs/msg/PointCloud2"),
    "init_poses": Output("~/init/poses", "geometry_msgs/msg/PoseArray"),
    "init_depth": Output("~/init/depth", "sensor_msgs/msg/Image"),
    "init_depth_info": Output("~/init/depth/camera_info", "sensor_msgs/msg/CameraInfo"),
    "init_points": Output("~/init/points", "sensor_msgs/msg/PointCloud2"),
    "status": Output("~/status", "diagnostic_msgs/msg/DiagnosticArray"),
    "diagnostics": Output("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
    "tf": Output("/tf", "tf2_msgs/msg/TFMessage"),
    "odom": Output("~/odom", "nav_msgs/msg/Odometry"),
    "path": Output("~/path", "nav_msgs/msg/Path"),
    "odom_imu": Output("~/odom/imu", "nav_msgs/msg/Odometry"),
}
#: The flight controllers' odometry (``vi3_ros.flight_odom``): message types; each is published only when its
#: parameter is on, on the topic its ``*_topic`` parameter names.
FLIGHT_TYPES: dict[str, str] = {"px4_odom": "px4_msgs/msg/VehicleOdometry", "mavros_odom": "nav_msgs/msg/Odometry"}
STATUS_NAME = "vi3: clip"
DIAG_NAME = "vi3: pipeline"


def published_outputs(settings: Settings) -> dict[str, Output]:
    """The outputs a stream with ``settings`` publishes: those of OUTPUTS (/tf only with ``publish_tf`` or
    ``publish_odom_tf``), and those of FLIGHT_TYPES that are on (``px4_odom``, ``mavros_odom``) on their topics."""
    tf_on = settings.frames.publish_tf or settings.frames.publish_odom_tf
    own = {key: out for key, out in OUTPUTS.items() if key != "tf" or tf_on}
    return own | {key: Output(topic, FLIGHT_TYPES[key]) for key, topic in settings.flight.outputs_on.items()}


def stream_keys(settings: Settings) -> frozenset[str]:
    """The outputs published outside any clip's messages (``~/status`` ends those): /diagnostics (timer), the
    IMU-rate odometry, and the flight controllers' odometry when ``~/odom/imu`` feeds it."""
    keys = {"diagnostics", "odom_imu"}
    return frozenset(keys | set(FLIGHT_TYPES) if settings.flight.flight_odom_source == "imu" else keys)


class OutputSink(Protocol):
    """Where the messages of a clip go. ``key`` is a key of ``OUTPUTS``; ``stamp_ns`` the message's header stamp
    (camera time), which replay uses as the log time."""

    def publish(self, key: str, msg: Any, stamp_ns: int) -> None: ...


def cloud_points(geometry: Geometry, frames: np.ndarray, *, stride: int, conf_quantile: float,
                 max_depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Back-projected depth pixels of ``frames`` in the clip frame (the first camera), metres.

    Keeps every ``stride``-th pixel in each direction whose depth is finite, in (0, max_depth], and whose
    confidence is at least the ``conf_quantile`` quantile of the confidences of the clip's pixels with depth (a frame
    the backbone gave no depth, NaN with zero confidence, does not lower it). Returns points [N,3] float32 and
    confidence [N] float32. Vectorised over all selected frames."""
    P, d = backproject(geometry.depth[frames], geometry.K[frames], geometry.T_wc[frames], stride=stride)
    conf = geometry.conf[frames, ::stride, ::stride].astype(np.float64).reshape(len(P), -1)
    rated = geometry.conf[np.isfinite(geometry.depth) & np.isfinite(geometry.conf)]
    thr = np.quantile(rated, conf_quantile) if conf_quantile > 0 and rated.size else -np.inf
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(d) & (d > 0) & (d <= max_depth) & (conf >= thr)
    return P[keep].astype(np.float32), conf[keep].astype(np.float32)


class ClipPublisher:
    """The messages of one stream's clips, built from its ``settings`` and handed to ``publish(key, msg, stamp_ns)``
    (the Pipeline's, which drops them while it is closing). Used from the worker thread only.

    Every input was checked before a message is built, so a message that cannot be built is a bug: it is named in
    ``errors`` (``take_errors``; the clip's status says so) and the clip's other messages, and the next clips', are
    published as usual."""

    def __init__(self, settings: Settings, *, types: MessageTypes, publish: Callable[[str, Any, int], None],
                 flight: FlightOdometry | None = None) -> None:
        self.settings, self.types, self._publish, self.flight = settings, types, publish, flight
        self._path_ns: dict[float, int] = {}  # odom trajectory stamp (s) -> header stamp (ns) of ~/path
        self.errors: list[tuple[str, str]] = []  # (output key, what failed) since ``take_errors``

    def take_errors(self) -> list[tuple[str, str]]:
        """The outputs that could not be built since the last call, as (key, "Type: message")."""
        errors, self.errors = self.errors, []
        return errors

    def _send(self, key: str, stamp: int, build: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Publish ``build(*args, **kwargs)`` as output ``key`` stamped ``stamp`` (ns), or name it in ``errors``."""
        try:
            msg = build(*args, **kwargs)
        except Exception as exc:  # any failure of a builder is reported, not raised (see the class)
            self.errors.append((key, f"{type(exc).__name__}: {exc}"))
            return
        self._publish(key, msg, stamp)

    def geometry(self, clip: Clip, geometry: Geometry, *, prefix: str, T_OC1: np.ndarray | None = None) -> None:
        """Poses, depth with its CameraInfo (the intrinsics of the undistorted image at the depth's resolution, no
        distortion), points (and the clip TF) of a result of ``clip`` (its frames' header stamps: ``stamps_ns``);
        ``prefix`` "init_" for the fast result that cond/ttr refine; with ``T_OC1`` [4,4] (the clip's first camera in
        odom) poses and points are in ``odom_frame``."""
        fr, out, types = self.settings.frames, self.settings.outputs, self.types
        stamp = int(clip.stamps_ns[-1])
        frame = fr.clip_frame if T_OC1 is None else fr.odom_frame
        T_wc = geometry.T_wc if T_OC1 is None else T_OC1 @ geometry.T_wc
        self._send(prefix + "poses", stamp, pose_array, T_wc, stamp_ns=stamp, frame_id=frame, types=types)
        frames = np.arange(geometry.n) if out.depth_frames == "all" else np.array([geometry.n - 1])
        for i in frames:
            s, (h, w) = int(clip.stamps_ns[i]), geometry.depth[i].shape
            self._send(prefix + "depth", s, depth_to_image, geometry.depth[i], stamp_ns=s, frame_id=fr.camera_frame,
                       types=types)
            self._send(prefix + "depth_info", s, calib_to_camera_info, geometry.K[i], "plumb_bob", np.zeros(5), (w, h),
                       stamp_ns=s, frame_id=fr.camera_frame, types=types)
        frames = np.arange(geometry.n) if out.points_frames == "all" else np.array([geometry.n - 1])
        pts, conf = cloud_points(geometry, frames, stride=out.points_stride, conf_quantile=out.points_conf_quantile,
                                 max_depth=out.points_max_depth)
        if T_OC1 is not None:
            pts = (pts.astype(np.float64) @ T_OC1[:3, :3].T + T_OC1[:3, 3]).astype(np.float32)
        self._send(prefix + "points", stamp, point_cloud2, pts, confidence=conf, stamp_ns=stamp, frame_id=frame,
                   types=types)
        if fr.publish_tf and not prefix:
            T_last_clip = np.linalg.inv(geometry.T_wc[-1])
            self._send("tf", stamp, tf_message, [(T_last_clip, fr.camera_frame, fr.clip_frame, stamp)], types=types)

    def odom(self, clip: Clip, outcome: ClipOutcome, trajectory: Trajectory) -> Anchor | None:
        """~/odom (pose and twist of base_frame at the last frame of ``clip``, with ``chained_covariances``), ~/path
        (the latest ``path_max_poses`` poses of the odom trajectory) and, with ``publish_odom_tf``, TF odom_frame ->
        base_frame; the flight controllers' odometry of the clip (``flight_odom_source`` clip). Returns the clip's
        flight Anchor (None without flight odometry)."""
        fr, types = self.settings.frames, self.types
        stamp = int(clip.stamps_ns[-1])
        chained = outcome.chained
        T, v_O = chained.T_OB[-1], chained.v_O[-1]
        omega = np.array([np.interp(clip.stamps[-1], clip.imu.t, clip.imu.gyro[:, a]) for a in range(3)]) \
            - outcome.state.bg
        sample_dt = float(np.median(np.diff(clip.imu.t)))
        zero = start_covariances(outcome.state, options=self.settings.init, sample_dt=sample_dt)
        pose_cov, twist_cov = chained_covariances(zero, trajectory)
        self._send("odom", stamp, odometry, T, T[:3, :3].T @ v_O, omega, stamp_ns=stamp, frame_id=fr.odom_frame,
                   child_frame_id=fr.base_frame, types=types, pose_cov=pose_cov, twist_cov=twist_cov)
        keep = slice(max(len(trajectory.stamps) - self.settings.outputs.path_max_poses, 0), None)
        # The header stamps of the frames (exact ns), kept for the poses the path still shows.
        self._path_ns.update(zip(clip.stamps.tolist(), clip.stamps_ns.tolist()))
        self._path_ns = {t: self._path_ns[t] for t in trajectory.stamps[keep].tolist()}
        stamps_ns = list(self._path_ns.values())
        self._send("path", stamp, path, trajectory.T_OB[keep], stamp_ns=stamp, frame_id=fr.odom_frame, types=types,
                   stamps_ns=stamps_ns)
        if fr.publish_odom_tf:
            self._send("tf", stamp, tf_message, [(T, fr.odom_frame, fr.base_frame, stamp)], types=types)
        if self.flight is None:
            return None
        anchor = self.flight.anchor(outcome, pose_cov=pose_cov, twist_cov=twist_cov, zero=zero)
        self.flight.chained(anchor, float(outcome.state.stamps[-1]), T, v_O, omega)  # on the IMU clock
        return anchor


def clip_status(index: int, clip: Clip, init: InitResult, kind: str, latency_s: float, *, drops: str,
                clip_frame: str, result: AnchorResult | None = None, decision: OnlineDecision | None = None,
                trajectory: Trajectory | None = None, rig: RigEstimate | None = None, rig_note: str = "",
                output_errors: Sequence[tuple[str, str]] = (), front_end: dict | None = None,
                in_odom: InOdom | None = None) -> DiagStatus:
    """The ``~/status`` entry of one result of the node's clip ``index``, processed as ``clip`` (the frames it spans:
    ``t_first``, ``t_last``): ``kind`` (init | cond | ttr | none), its initialisation ``init``, the
    wall-clock ``latency_s``, the input drops since the previous status (``drops``, "reason:count, ..."); with the
    ``result`` of the anchoring (None: the data checks rejected the clip before the backbone), with the online
    window's ``decision`` and the odom ``trajectory`` (online) the window's decision and the odom segment, and the
    ``rig``'s self-calibration (key ``rig``; ``rig_note``: why the clip did not add to it or take all of it); the
    outputs of the clip that could not be built (``ClipPublisher.take_errors``: key ``output_errors``, level ERROR);
    ``front_end``: where the backbone's front end lost the tracks into the frames this clip tracked (the ``classical``
    backbone's ``front_end.FrameLosses`` as a dict; key ``front_end``); ``in_odom``: how the clip went into odom
    (key ``odom``: ``claimed``, ``window scale, not claimed`` (``odom_max_scale_sigma``) or ``not placed``; None: not
    known, no key)."""
    level = Level.OK if init.ok else (Level.WARN if init.status is InitStatus.UNOBSERVABLE else Level.ERROR)
    if drops and level is Level.OK:
        level = Level.WARN
    reason = result_reason(init, result)
    alpha = result.alpha if result is not None else float("nan")
    fit = init.fit
    rel = fit.scale_rel_sigma if fit is not None else float("nan")
    values = {"clip": index, "result": kind, "init_status": init.status.value, "reason": reason,
              "scale": f"{init.scale:.6g}", "scale_sigma": f"{init.scale_sigma:.3g}", "scale_rel_sigma": f"{rel:.3g}",
              "alpha": f"{alpha:.6g}", "gravity_source": init.gravity_source,
              "consensus_deg": f"{init.consensus_deg:.4g}", "g": _vec(init.g), "v1": _vec(init.v1),
              "bg": _vec(init.bg), "ba": _vec(init.ba), "t_first": f"{clip.stamps[0]:.9f}",
              "t_last": f"{clip.stamps[-1]:.9f}", "input_drops": drops, "latency_ms": f"{latency_s * 1e3:.1f}"}
    if fit is not None:  # the time offset the fit found beyond the configured one
        values["time_offset_residual_ms"] = f"{1e3 * fit.time_offset:.2f} +- {1e3 * fit.time_offset_sigma:.2f}"
    if decision is not None and trajectory is not None:
        values["online"] = decision.describe()
        if decision.joined:  # how the window earned the clip's scale, and the scale link to the clip before it
            values["scale_earned"] = decision.earned
            values["scale_link"] = decision.link.describe() if decision.link is not None else decision.link_note
        if np.isfinite(decision.scale_p):  # the clip's own scale against the window's (the window's guard)
            values["scale_consistency_p"] = f"{decision.scale_p:.3g}"
        if decision.traj_depth_sigma > 0:
            values["traj_depth_sigma"] = f"{decision.traj_depth_sigma:.3g}"
        values["odom_segment"] = len(trajectory.resets)  # 0: the first; each reset starts one (its first frame)
        if in_odom is not None:
            values["odom"] = in_odom.value
        if trajectory.resets:
            values["odom_segment_start"] = f"{trajectory.resets[-1]:.9f}"
    if rig is not None:
        values["rig"] = rig.describe()
    if rig_note:
        values["rig_note"] = rig_note
    if front_end:
        f = FrameLosses(**front_end)
        values["front_end"] = (f"{f.frames} frames ({f.starts} started afresh), {f.followed} tracks followed; "
                               f"lost: {f.lost_no_flow} no flow, {f.lost_round_trip} round trip, "
                               f"{f.lost_border} border, {f.lost_epipolar} epipolar; {f.new} new corners; "
                               f"{f.new_lost} new corners lost at their first step; {f.ended} tracks ended, "
                               f"seen in {f.ended_frames} frames in all")
    if result is not None and kind != "init":
        values.update({f"loss_{k}": f"{float(np.asarray(a).reshape(-1)[-1]):.6g}"
                       for k, a in sorted(result.losses.items()) if np.asarray(a).size})
    if result is not None:
        values.update({f"timing_{k}": f"{s:.4g}" for k, s in sorted(result.timings.items())})  # units in k
    message = f"{kind}: {reason}"
    if output_errors:
        level = Level.ERROR
        values["output_errors"] = "; ".join(f"{key}: {what}" for key, what in output_errors)
        message += f"; outputs not built (a bug, please report): {', '.join(key for key, _ in output_errors)}"
    return DiagStatus(level, STATUS_NAME, message, clip_frame, values)


def result_reason(init: InitResult, result: AnchorResult | None) -> str:
    """Why a clip's result is what it is: the initialisation's reason, or the anchoring's status when it is ok."""
    return init.reason if not init.ok else (result.status or "ok")


def _vec(v: np.ndarray) -> str:
    return " ".join(f"{x:.6g}" for x in np.asarray(v, dtype=np.float64).reshape(-1))


__all__ = ["DIAG_NAME", "FLIGHT_TYPES", "OUTPUTS", "STATUS_NAME", "ClipPublisher", "Output", "OutputSink",
           "clip_status", "cloud_points", "published_outputs", "result_reason", "stream_keys"]
