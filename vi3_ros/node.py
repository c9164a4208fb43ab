"""``vi3_node``: the thin rclpy shell around ``vi3_ros.pipeline``.

Only wiring lives here: parameters declared with descriptors from ``vi3_ros.params``, subscriptions with the
sensor-data QoS (best effort) and queues that hold ``CALLBACK_DELAY_S`` of input, reliable publishers for
``vi3_ros.outputs.published_outputs`` (px4_msgs is imported only with ``px4_odom``), a timer for the Pipeline's
periodic diagnostics (stamped, as all /diagnostics, with the node's clock), and callbacks that hand messages to the
Pipeline (images and IMU converted with ``msg_adapters``; CameraInfo and /tf_static as they are, the Pipeline decodes
them as replay does). A message that cannot be decoded is
dropped and counted by the Pipeline (``drop_input``) like every other drop; one that never arrived is counted from the
gap it leaves in the stamps (``image_lost``, ``imu_lost``).

Parameters are declared with dynamic typing and their range or choices written into the descriptor's
``additional_constraints``, so that rclpy itself refuses nothing: ``vi3_ros.params.resolve`` checks every value (an
integer where a float is declared is taken, as users type it) and a bad one ends the node at start with one line
naming the parameter, the value and the range (exit status 2). A parameter given that the node does not declare (a
typo in a parameter file or ``-p``) is named in a warning with the closest known name.
This is the only module that imports rclpy; it uses the API that ROS 2 Humble and Jazzy share.
Run: ``ros2 run vi3_ros vi3_node --ros-args --params-file config/euroc.yaml`` or ``launch/vi3.launch.py``.

Shutdown (SIGINT, SIGTERM, also with SIGINT inherited as ignored, and with a second signal during the shutdown, as
when Ctrl-C reaches a node under ``ros2 launch`` both from the terminal and from launch): exit code 0 within ~1 s, even
while a clip is in the backbone: the clip's outputs are discarded and the worker thread is not waited for beyond
``SHUTDOWN_WAIT_S``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import signal
import sys
from collections.abc import Callable
from typing import Any

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from msg_adapters.errors import UnknownMessageType, drop_reason
from msg_adapters.image import camera_frame
from msg_adapters.imu import imu_to_sample
from msg_adapters.stamps import stamp_to_ns
from msg_adapters.types import MessageTypes
from vi3_core.dataset.calib import load_calib
from vi3_core.errors import DataError, Vi3Error
from vi3_ros import interrupts
from vi3_ros.io.topics import IMAGE_TRANSPORTS, TF_TYPE
from vi3_ros.outputs import published_outputs
from vi3_ros.params import NODE_NAME, PARAMS, Param, resolve, unknown_parameter
from vi3_ros.pipeline import MAX_IMU_RATE_HZ, Pipeline, make_pipeline
from vi3_ros.settings import Settings
from vi3_ros.time_offset import resolve_time_offset

RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
TF_STATIC = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
SHUTDOWN_WAIT_S = 0.5  # s the worker may take to finish its clip at shutdown
IMAGE_TYPE_POLL_S = 0.5  # s between looks at the ROS graph for the image topic's type (image_transport auto)
#: s; the longest the executor may fall behind the input without losing a message: the input queues hold this much.
#: The worker's backbone shares the interpreter lock with the callbacks: on two cores under ``ros2 launch`` beside a
#: busy process (load average 3-15) IMU callbacks ran up to 1.4 s behind the samples' schedule, 37 % of them more than
#: the 25 ms that the sensor-data QoS's queue of 5 holds at 200 Hz.
CALLBACK_DELAY_S = 5.0
MAX_CAMERA_RATE_HZ = 30.0  # Hz; the fastest camera the image queue is sized for (a faster one gets less time)


def sensor_qos(rate_hz: float) -> QoSProfile:
    """The sensor-data QoS (best effort, volatile) with a queue of ``CALLBACK_DELAY_S`` of messages at ``rate_hz``."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=math.ceil(rate_hz * CALLBACK_DELAY_S),
                      reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)


def descriptor(p: Param) -> ParameterDescriptor:
    """The ROS ParameterDescriptor of one parameter declaration: description, read-only, and its type and range or
    choices as text in ``additional_constraints`` (dynamically typed: ``resolve`` checks the value, not rclpy)."""
    allowed = f"range [{p.range[0]}, {p.range[1]}]" if p.range is not None else \
        f"one of: {', '.join(p.choices)}" if p.choices else ""
    return ParameterDescriptor(name=p.name, description=p.description, read_only=True, dynamic_typing=True,
                               additional_constraints="; ".join(x for x in (p.type.__name__, allowed) if x))


class _PublisherSink:
    """OutputSink over rclpy publishers of the outputs ``settings`` turn on (thread-safe: rclpy publishers may be used
    from the worker thread). After the context has shut down nothing is published (a publish would raise). px4_msgs is
    imported only here, when ``px4_odom`` is on; DataError when it is not installed."""

    def __init__(self, node: Node, types: MessageTypes, settings: Settings) -> None:
        self.context = node.context
        self.publishers = {key: node.create_publisher(_message_class(types, out.msgtype, key), out.topic, RELIABLE)
                           for key, out in published_outputs(settings).items()}

    def publish(self, key: str, msg: Any, stamp_ns: int) -> None:
        if self.context.ok():
            self.publishers[key].publish(msg)


def _without_missing_tf(settings: Settings, types: MessageTypes) -> tuple[Settings, str]:
    """``settings`` with ``publish_tf`` and ``publish_odom_tf`` off, and a warning naming why, where tf2_msgs (which
    no PyPI wheel provides) is not installed; else ``settings`` and ""."""
    frames = settings.frames
    if not (frames.publish_tf or frames.publish_odom_tf):
        return settings, ""
    try:
        types.get(TF_TYPE)
    except UnknownMessageType:
        off = dataclasses.replace(frames, publish_tf=False, publish_odom_tf=False)
        return dataclasses.replace(settings, frames=off), (
            f"publish_tf / publish_odom_tf: /tf is not published, {_not_installed(TF_TYPE)}; ~/odom, ~/poses and "
            "~/points carry the same poses")
    return settings, ""


def _not_installed(msgtype: str) -> str:
    return f"{msgtype} is unknown: the package {msgtype.split('/')[0]} is not installed or not sourced"


#: What to do about a message package that is not installed, by the parameter that needs it.
_INSTALL_HINT = {"px4_odom": "px4_odom needs PX4's px4_msgs, built in the workspace from the branch of your PX4 "
                             "release",
                 "use_tf_static": "use_tf_static needs tf2_msgs, which no PyPI wheel provides: source a ROS 2 that has "
                                  "it, or give the camera pose in calib_file"}


def _message_class(types: MessageTypes, msgtype: str, key: str) -> type:
    """The class of ``msgtype`` (for output or input ``key``); a message package that is not installed (px4_msgs) is
    a DataError saying so and what needs it."""
    try:
        return types.get(msgtype)
    except UnknownMessageType:
        hint = _INSTALL_HINT.get(key)
        raise DataError(_not_installed(msgtype) + (f"; {hint}" if hint else "")) from None


def _stamp_or_none(msg: Any) -> int | None:
    try:
        return stamp_to_ns(msg.header.stamp)
    except (DataError, AttributeError):
        return None


class Vi3Node(Node):
    """Parameters, subscriptions, publishers and a diagnostics timer around one Pipeline."""

    def __init__(self, **node_kwargs: Any) -> None:
        self.pipeline: Pipeline | None = None  # until built: rclpy may destroy a node whose start failed
        super().__init__(NODE_NAME, **node_kwargs)
        for p in PARAMS:
            self.declare_parameter(p.name, p.default, descriptor(p))
        for name in sorted(self._parameter_overrides):  # from -p, parameter files and parameter_overrides
            if not self.has_parameter(name):
                self.get_logger().warning(f"{unknown_parameter(name)} is ignored")
        self.settings = resolve({p.name: self.get_parameter(p.name).value for p in PARAMS})
        if self.settings.inputs.calib_file:  # its timeshift_cam_imu: time_offset unless the parameter says
            self.settings, note = resolve_time_offset(self.settings, load_calib(self.settings.inputs.calib_file))
            if note:
                self.get_logger().warning(note)
        self.types = types = MessageTypes.from_rclpy()
        tf_static_type = _message_class(types, TF_TYPE, "use_tf_static") if self.settings.inputs.use_tf_static \
            else None
        self.settings, note = _without_missing_tf(self.settings, types)
        if note:
            self.get_logger().warning(note)
        self.sink = _PublisherSink(self, types, self.settings)
        self.pipeline = make_pipeline(self.settings, sink=self.sink, types=types,
                                      clock=lambda: self.get_clock().now().nanoseconds)
        inputs = self.settings.inputs
        self.image_topic = self.resolve_topic_name(inputs.image_topic)
        self._image_sub = None
        self._image_timer = None
        self._waiting_logged = False
        if inputs.image_transport == "auto":
            self._image_timer = self.create_timer(IMAGE_TYPE_POLL_S, self._learn_image_type)
            self._learn_image_type()
        else:
            self._subscribe_images(IMAGE_TRANSPORTS[inputs.image_transport][0])
        self.create_subscription(types.get("sensor_msgs/msg/Imu"), inputs.imu_topic, self._on_imu,
                                 sensor_qos(MAX_IMU_RATE_HZ))
        if inputs.camera_info_topic:
            self.create_subscription(types.get("sensor_msgs/msg/CameraInfo"), inputs.camera_info_topic,
                                     self._on_camera_info, sensor_qos(MAX_CAMERA_RATE_HZ))
        if tf_static_type is not None:
            self.create_subscription(tf_static_type, "/tf_static", self._on_tf_static, TF_STATIC)
        self.create_timer(self.settings.outputs.diagnostics_period, self._on_timer)
        model = self.settings.model
        self.get_logger().info(f"vi3_node: backbone {model.backbone} on {model.device}, mode "
                               f"{self.settings.stream.mode}, images {self.image_topic} ({inputs.image_transport}), "
                               f"IMU {inputs.imu_topic}")

    # ---- image subscription ----------------------------------------------------------------------------------

    def _subscribe_images(self, msgtype: str) -> None:
        self._image_sub = self.create_subscription(self.types.get(msgtype), self.image_topic, self._on_image,
                                                   sensor_qos(MAX_CAMERA_RATE_HZ))
        self.image_type = msgtype

    def _learn_image_type(self) -> None:
        """image_transport auto: subscribe with the type the image topic's publishers have, once the graph shows
        exactly one of sensor_msgs/Image and sensor_msgs/CompressedImage on it."""
        if self._image_sub is not None:
            return
        offered = dict(self.get_topic_names_and_types()).get(self.image_topic, [])
        found = [t for t in offered if t in IMAGE_TRANSPORTS["auto"]]
        if len(found) == 1:
            self._subscribe_images(found[0])
            self.destroy_timer(self._image_timer)
            self.get_logger().info(f"images: {self.image_topic} carries {found[0]}")
        elif not self._waiting_logged:
            self._waiting_logged = True
            why = f"its publishers offer {offered}" if offered else "no publisher yet"
            self.get_logger().warning(f"images: waiting to learn the type of {self.image_topic} ({why}); set "
                                      "image_transport raw or compressed to subscribe at once")

    # ---- callbacks -------------------------------------------------------------------------------------------

    def _guard(self, kind: str, msg: Any, fn: Callable[[], None]) -> None:
        """A message that cannot be decoded is dropped and counted by the Pipeline, never fatal."""
        try:
            fn()
        except DataError as exc:
            self.pipeline.drop_input(drop_reason(kind, exc), _stamp_or_none(msg), str(exc))

    def _on_image(self, msg) -> None:
        self._guard("image", msg, lambda: self.pipeline.add_image(stamp_to_ns(msg.header.stamp), camera_frame(msg)))

    def _on_imu(self, msg) -> None:
        def add() -> None:
            s = imu_to_sample(msg)
            self.pipeline.add_imu(s.t_ns, s.gyro, s.accel, s.orientation)
        self._guard("imu", msg, add)

    def _on_camera_info(self, msg) -> None:
        self._guard("camera_info", msg, lambda: self.pipeline.add_camera_info(msg))

    def _on_tf_static(self, msg) -> None:
        self._guard("tf_static", msg, lambda: self.pipeline.add_tf_static(msg))

    def _on_timer(self) -> None:
        self.pipeline.publish_diagnostics(self.get_clock().now().nanoseconds)

    def destroy_node(self) -> None:
        if self.pipeline is not None:
            self.pipeline.close(timeout=SHUTDOWN_WAIT_S)
        super().destroy_node()


def _start(args: list[str]) -> Vi3Node | None:
    """rclpy and the node, or None when it cannot start: then one log line names the cause (a Vi3Error says it
    itself; anything else, such as a broken message package, by its type and message), never a traceback."""
    try:
        rclpy.init(args=args)
        # The executor spin uses, built before the node says it is up: a signal while rclpy built it lazily
        # inside spin left a half-built executor whose __del__ printed a traceback.
        rclpy.get_global_executor()
        return Vi3Node()
    except (KeyboardInterrupt, ExternalShutdownException):
        raise
    except Exception as exc:  # every start failure is one line and exit status 2
        why = str(exc) if isinstance(exc, Vi3Error) else f"{type(exc).__name__}: {exc}"
        rclpy.logging.get_logger(NODE_NAME).fatal("cannot start: " + " ".join(why.split()))
        return None


def main(args: list[str] | None = None) -> int:
    """Run the node until SIGINT or SIGTERM, then end the process at once with status 0; 2 when a configuration
    it cannot run with stops it at start (one log line names the cause)."""
    status = 0
    # Python handlers first: rclpy.init chains its own (which wake the executor and shut the context down) to them.
    # The first SIGINT/SIGTERM ends spin with KeyboardInterrupt; later ones (a launcher passes the terminal's SIGINT
    # on to its children, which got it too) are only recorded, so that the shutdown below runs to its end.
    with interrupts.trapped((signal.SIGINT, signal.SIGTERM)):
        node = None
        try:
            node = _start(args if args is not None else sys.argv)
            if node is None:
                status = 2
            else:
                rclpy.spin(node)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass  # SIGINT / SIGTERM, also while starting: a normal end
        finally:
            interrupts.hold()
            if node is not None:
                node.destroy_node()
            # rclpy's own handler may shut the context down between a check and a shutdown here (a SIGTERM just
            # after start): "already shut down" raised RCLError at exit; try_shutdown checks under the context's lock
            rclpy.try_shutdown()
        # Leave now: nothing is left to publish or write, a clip may still be in the backbone (which cannot be
        # interrupted; its outputs are discarded), and the interpreter's teardown of torch alone took over a second
        # on a loaded machine.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)


if __name__ == "__main__":
    sys.exit(main())
