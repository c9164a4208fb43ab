"""``vi3_node``: the thin rclpy shell around ``vi3_ros.pipeline``.

Only wiring lives here: parameters declared with descriptors from ``vi3_ros.params``, subscriptions with the
sensor-data QoS (best effort), reliable publishers for ``vi3_ros.pipeline.OUTPUTS``, a timer for the Pipeline's
periodic diagnostics, and callbacks that hand messages to the Pipeline (images and IMU converted with
``msg_adapters``; CameraInfo and /tf_static as they are, the Pipeline decodes them as replay does).
This is the only module that imports rclpy; it uses the API that ROS 2 Humble and Jazzy share.
Run: ``ros2 run vi3_ros vi3_node --ros-args --params-file config/euroc.yaml`` or ``launch/vi3.launch.py``.
"""

from __future__ import annotations

import sys
from typing import Any

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from msg_adapters.image import image_to_numpy
from msg_adapters.imu import imu_to_sample
from msg_adapters.stamps import stamp_to_ns
from msg_adapters.types import MessageTypes
from vi3_core.errors import DataError
from vi3_ros.params import NODE_NAME, PARAMS, Param, resolve
from vi3_ros.pipeline import OUTPUTS, Pipeline, make_pipeline

RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
TF_STATIC = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
_PARAM_TYPES = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
                float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING}


def descriptor(p: Param) -> ParameterDescriptor:
    """The ROS ParameterDescriptor of one parameter declaration (type, description, range, choices)."""
    d = ParameterDescriptor(name=p.name, type=_PARAM_TYPES[p.type], description=p.description, read_only=True)
    if p.range is not None and p.type is float:
        d.floating_point_range = [FloatingPointRange(from_value=float(p.range[0]), to_value=float(p.range[1]))]
    elif p.range is not None and p.type is int:
        d.integer_range = [IntegerRange(from_value=int(p.range[0]), to_value=int(p.range[1]), step=1)]
    if p.choices:
        d.additional_constraints = "one of: " + ", ".join(p.choices)
    return d


class _PublisherSink:
    """OutputSink over rclpy publishers (thread-safe: rclpy publishers may be used from the worker thread)."""

    def __init__(self, node: Node, types: MessageTypes) -> None:
        self.publishers = {key: node.create_publisher(types.get(out.msgtype), out.topic, RELIABLE)
                           for key, out in OUTPUTS.items()}

    def publish(self, key: str, msg: Any, stamp_ns: int) -> None:
        self.publishers[key].publish(msg)


class Vi3Node(Node):
    """Parameters, subscriptions, publishers and a diagnostics timer around one Pipeline."""

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__(NODE_NAME, **node_kwargs)
        for p in PARAMS:
            self.declare_parameter(p.name, p.default, descriptor(p))
        self.values = resolve({p.name: self.get_parameter(p.name).value for p in PARAMS})
        types = MessageTypes.from_rclpy()
        self.sink = _PublisherSink(self, types)
        self.pipeline: Pipeline = make_pipeline(self.values, sink=self.sink, types=types)
        v = self.values
        self.create_subscription(types.get("sensor_msgs/msg/Image"), v["image_topic"], self._on_image,
                                 qos_profile_sensor_data)
        self.create_subscription(types.get("sensor_msgs/msg/Imu"), v["imu_topic"], self._on_imu,
                                 qos_profile_sensor_data)
        if v["camera_info_topic"]:
            self.create_subscription(types.get("sensor_msgs/msg/CameraInfo"), v["camera_info_topic"],
                                     self._on_camera_info, qos_profile_sensor_data)
        if v["use_tf_static"]:
            self.create_subscription(types.get("tf2_msgs/msg/TFMessage"), "/tf_static", self._on_tf_static,
                                     TF_STATIC)
        self.create_timer(v["diagnostics_period"], self._on_timer)
        self.get_logger().info(f"vi3_node: backbone {v['backbone']} on {v['device']}, mode {v['mode']}, "
                               f"images {v['image_topic']}, IMU {v['imu_topic']}")

    def _guard(self, what: str, fn, *args) -> None:
        """A malformed message is dropped with a (throttled) warning, never fatal."""
        try:
            fn(*args)
        except DataError as exc:
            self.get_logger().warning(f"dropped a malformed {what} message: {exc}", throttle_duration_sec=5.0)

    def _on_image(self, msg) -> None:
        self._guard("image", lambda: self.pipeline.add_image(stamp_to_ns(msg.header.stamp), image_to_numpy(msg)))

    def _on_imu(self, msg) -> None:
        def add() -> None:
            s = imu_to_sample(msg)
            self.pipeline.add_imu(s.t_ns, s.gyro, s.accel, s.orientation)
        self._guard("IMU", add)

    def _on_camera_info(self, msg) -> None:
        self._guard("CameraInfo", self.pipeline.add_camera_info, msg)

    def _on_tf_static(self, msg) -> None:
        self._guard("/tf_static", self.pipeline.add_tf_static, msg)

    def _on_timer(self) -> None:
        self.pipeline.publish_diagnostics(self.get_clock().now().nanoseconds)

    def destroy_node(self) -> None:
        self.pipeline.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args if args is not None else sys.argv)
    node = Vi3Node()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
