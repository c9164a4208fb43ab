"""The rclpy node, end to end against a real ROS 2 graph (rclpy with any RMW): a generated sequence is published on
the EuRoC topics at recording speed with the sensor-data QoS, and the node's outputs are received.

Where rclpy is not installed the module skips with the reason; everything the node calls besides rclpy
(pipeline, buffer, worker, msg_adapters, parameters) is covered by tests/test_replay*.py.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy", reason="rclpy is not installed (needs ROS 2 Jazzy or Humble); the node's "
                            "shared code is covered by tests/test_replay*.py")

from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402

from msg_adapters.diagnostics import diagnostic_array_to_statuses  # noqa: E402
from msg_adapters.image import numpy_to_image  # noqa: E402
from msg_adapters.imu import samples_to_imus  # noqa: E402
from msg_adapters.types import MessageTypes  # noqa: E402
from vi3_core.dataset.calib import write_euroc_sensor_yaml  # noqa: E402
from vi3_core.dataset.generate import EUROC_CAM0, cached_sequence  # noqa: E402
from vi3_core.types import ImuSamples  # noqa: E402
from vi3_ros.io.reader import ImageEvent, iter_events  # noqa: E402
from vi3_ros.node import RELIABLE, Vi3Node  # noqa: E402


def test_node_publishes_metric_outputs(cache_dir, tmp_path):
    asl = cached_sequence(cache_dir, seconds=2.5, seed=1, with_depth=False)
    calib = tmp_path / "cam0.yaml"
    write_euroc_sensor_yaml(EUROC_CAM0, calib)
    rclpy.init()
    try:
        types = MessageTypes.from_rclpy()
        node = Vi3Node(parameter_overrides=[Parameter("calib_file", value=str(calib)),
                                            Parameter("depth_frames", value="all")])
        feeder = rclpy.create_node("vi3_test_feeder")
        pub_img = feeder.create_publisher(types.get("sensor_msgs/msg/Image"), "/cam0/image_raw",
                                          qos_profile_sensor_data)
        pub_imu = feeder.create_publisher(types.get("sensor_msgs/msg/Imu"), "/imu0", qos_profile_sensor_data)
        got: dict[str, list] = {"poses": [], "status": [], "depth": [], "points": []}
        outputs = (("poses", "geometry_msgs/msg/PoseArray"), ("status", "diagnostic_msgs/msg/DiagnosticArray"),
                   ("depth", "sensor_msgs/msg/Image"), ("points", "sensor_msgs/msg/PointCloud2"))
        for key, msgtype in outputs:
            feeder.create_subscription(types.get(msgtype), f"/vi3_node/{key}", got[key].append, RELIABLE)
        executor = MultiThreadedExecutor(num_threads=2)
        executor.add_node(node)
        executor.add_node(feeder)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()

        # parameters are declared with descriptors from vi3_ros.params
        desc = node.describe_parameters(["clip_length", "mode"])
        assert desc[0].integer_range[0].from_value == 2 and "ttr" in desc[1].additional_constraints
        time.sleep(1.0)  # discovery
        start, t0 = time.monotonic(), None
        for ev in iter_events(asl):
            t0 = ev.t if t0 is None else t0
            delay = (ev.t - t0) - (time.monotonic() - start)
            if delay > 0:
                time.sleep(delay)  # recording speed
            if isinstance(ev, ImageEvent):
                pub_img.publish(numpy_to_image(ev.image, encoding="mono8", stamp_ns=ev.t_ns, frame_id="cam0",
                                               types=types))
            else:
                (msg,) = samples_to_imus(ImuSamples(np.array([ev.t_ns * 1e-9]), ev.gyro[None], ev.accel[None]),
                                         frame_id="imu0", types=types)
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ev.t_ns, 1_000_000_000)
                pub_imu.publish(msg)
        deadline = time.monotonic() + 120.0
        while time.monotonic() < deadline and len(got["status"]) < 3:
            time.sleep(0.2)
        statuses = [s for m in got["status"] for s in diagnostic_array_to_statuses(m)]
        results = [s.values["result"] for s in statuses]
        assert len(results) == 3, results  # every clip accounted for (published, or replaced by a newer one)
        assert set(results) <= {"init", "skipped"} and "init" in results
        assert all(s.values["reason"] == "worker_busy" for s in statuses if s.values["result"] == "skipped")
        assert len(got["poses"]) == results.count("init")
        pa = got["poses"][0]
        assert pa.header.frame_id == "vi3_clip" and len(pa.poses) == 8
        assert {d.encoding for d in got["depth"]} == {"32FC1"} and len(got["depth"]) == 8 * len(got["poses"])
        assert [f.name for f in got["points"][0].fields] == ["x", "y", "z", "confidence"]
        executor.shutdown()
        node.destroy_node()
        feeder.destroy_node()
    finally:
        rclpy.shutdown()
