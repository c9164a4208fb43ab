"""The rclpy node, end to end against a real ROS 2 graph (rclpy with any RMW): a generated sequence is published on
the EuRoC topics at recording speed with the sensor-data QoS, and the node's outputs are received.

Where rclpy is not installed the module skips with the reason; everything the node calls besides rclpy
(pipeline, buffer, worker, msg_adapters, parameters) is covered by tests/test_replay*.py.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
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

pytestmark = pytest.mark.slow  # every test here runs a node, replays, evaluations or generated sequences


def test_node_publishes_metric_outputs(cache_dir, tmp_path):
    asl = cached_sequence(cache_dir, seconds=2.5, seed=1, with_depth=False)
    calib = tmp_path / "cam0.yaml"
    write_euroc_sensor_yaml(EUROC_CAM0, calib)
    rclpy.init()
    try:
        types = MessageTypes.from_rclpy()
        # the gate is open (as OPEN_GATE in test_replay): this checks the plumbing, not which clips may claim a scale
        node = Vi3Node(parameter_overrides=[Parameter("calib_file", value=str(calib)),
                                            Parameter("depth_frames", value="all"),
                                            Parameter("max_scale_sigma", value=10.0)])
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


@pytest.fixture()
def node_process():
    """Start ``vi3_node`` as its own process (``python -m vi3_ros.node``), as ros2 run starts it:
    ``node_process(calib, *ros_args, preexec_fn=None)``. A node a failed test leaves running is killed."""
    procs: list[subprocess.Popen] = []

    def start(calib, *extra: str, preexec_fn=None) -> subprocess.Popen:
        procs.append(subprocess.Popen([sys.executable, "-m", "vi3_ros.node", "--ros-args", "-p",
                                       f"calib_file:={calib}", *extra], stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT, text=True, preexec_fn=preexec_fn))
        return procs[-1]
    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def _feed(asl, types, pub_img, pub_imu, *, seconds: float, speed: float = 1.0, corrupt_every: int = 0,
          compress: str = "") -> None:
    """Publish the sequence at ``speed`` x recording speed for at most ``seconds`` (looping); every
    ``corrupt_every``-th image with a wrong step (malformed); with ``compress`` ("jpeg", "png") the images as
    ``sensor_msgs/CompressedImage``."""
    start, k = time.monotonic(), 0
    while time.monotonic() - start < seconds:
        t0, loop_start = None, time.monotonic()
        offset = int((loop_start - start) * 1e9 * speed) + 10**9 * k
        for ev in iter_events(asl):
            t0 = ev.t if t0 is None else t0
            delay = (ev.t - t0) / speed - (time.monotonic() - loop_start)
            if delay > 0:
                time.sleep(delay)
            if time.monotonic() - start >= seconds:
                return
            stamp = ev.t_ns + offset
            if isinstance(ev, ImageEvent):
                msg = numpy_to_image(ev.image, encoding="mono8", stamp_ns=stamp, frame_id="cam0", types=types)
                if compress:
                    ok, buf = cv2.imencode(f".{compress}", ev.image)
                    assert ok
                    msg = types.make("sensor_msgs/msg/CompressedImage", header=msg.header,
                                     format=f"mono8; {compress} compressed", data=types.uint8_seq(buf.reshape(-1)))
                k += 1
                if corrupt_every and k % corrupt_every == 0:
                    msg.step += 1
                pub_img.publish(msg)
            else:
                (msg,) = samples_to_imus(ImuSamples(np.array([stamp * 1e-9]), ev.gyro[None], ev.accel[None]),
                                         frame_id="imu0", types=types, stamps_ns=[stamp])
                pub_imu.publish(msg)
        k += 1


@contextlib.contextmanager
def _feeder(image_type: str = "sensor_msgs/msg/Image", image_topic: str = "/cam0/image_raw"):
    """A ROS context with a feeder node publishing images of ``image_type`` on ``image_topic`` and IMU on /imu0
    (sensor-data QoS) and collecting /diagnostics: yields (types, image publisher, IMU publisher, diagnostics)."""
    rclpy.init()
    try:
        types = MessageTypes.from_rclpy()
        feeder = rclpy.create_node("vi3_test_feeder")
        pub_img = feeder.create_publisher(types.get(image_type), image_topic, qos_profile_sensor_data)
        pub_imu = feeder.create_publisher(types.get("sensor_msgs/msg/Imu"), "/imu0", qos_profile_sensor_data)
        diag: list = []
        feeder.create_subscription(types.get("diagnostic_msgs/msg/DiagnosticArray"), "/diagnostics", diag.append,
                                   RELIABLE)
        executor = MultiThreadedExecutor(num_threads=2)
        executor.add_node(feeder)
        threading.Thread(target=executor.spin, daemon=True).start()
        yield types, pub_img, pub_imu, diag
        executor.shutdown()
        feeder.destroy_node()
    finally:
        rclpy.shutdown()


@pytest.fixture()
def feeder_graph():
    with _feeder() as graph:
        yield graph


@pytest.mark.parametrize("case", ["sigterm", "ignored_sigint", "sigint_twice"])
def test_signal_mid_clip_exits_zero_within_two_seconds(cache_dir, tmp_path, feeder_graph, node_process, case):
    """SIGTERM; SIGINT inherited as ignored (as under a script's background job); SIGINT twice, as Ctrl-C reaches a
    node under ``ros2 launch`` from the terminal and again from launch, the second during the shutdown: each while
    the worker is in the backbone, exit 0 within 2 s, no traceback."""
    types, pub_img, pub_imu, _ = feeder_graph
    asl = cached_sequence(cache_dir, seconds=2.5, seed=1, with_depth=False)
    calib = tmp_path / "cam0.yaml"
    write_euroc_sensor_yaml(EUROC_CAM0, calib)
    ignore = (lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if case == "ignored_sigint" else None
    proc = node_process(calib, preexec_fn=ignore)
    time.sleep(6.0)  # start-up and discovery
    _feed(asl, types, pub_img, pub_imu, seconds=1.0)  # the first clip is complete: the worker is busy with it
    time.sleep(0.1)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM if case == "sigterm" else signal.SIGINT)
    if case == "sigint_twice":
        time.sleep(0.2)  # the node is shutting down: waiting for its worker
        proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0 and time.monotonic() - t0 < 2.0, out
    assert "Traceback" not in out


def test_malformed_images_are_counted_on_diagnostics_and_a_flood_keeps_memory_bounded(cache_dir, tmp_path,
                                                                                     feeder_graph, node_process):
    """A 5x flood for 10 s with every 40th image malformed: drops named on /diagnostics (image_malformed counted,
    worker_busy for clips the busy worker replaced), resident memory bounded, the node alive and exiting 0. (A
    malformed frame is a dropped frame, which restarts the clip being collected: a clip spans 15 input frames.)"""
    types, pub_img, pub_imu, diag = feeder_graph
    asl = cached_sequence(cache_dir, seconds=2.5, seed=1, with_depth=False)
    calib = tmp_path / "cam0.yaml"
    write_euroc_sensor_yaml(EUROC_CAM0, calib)
    proc = node_process(calib)
    time.sleep(6.0)
    rss = []
    start = time.monotonic()
    feeding = threading.Thread(target=_feed, args=(asl, types, pub_img, pub_imu),
                               kwargs={"seconds": 10.0, "speed": 5.0, "corrupt_every": 40})
    feeding.start()
    while feeding.is_alive():
        rss.append(int(Path(f"/proc/{proc.pid}/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20)
        time.sleep(0.5)
    time.sleep(3.0)
    statuses = [s for m in diag for s in diagnostic_array_to_statuses(m) if s.name == "vi3: pipeline"]
    last = statuses[-1].values
    assert int(last.get("drop_image_malformed", 0)) > 10 and "image_malformed" in " ".join(s.message for s in statuses)
    assert int(last["clips_emitted"]) > 5 and int(last["worker_replaced"]) > 0 and proc.poll() is None
    half = len(rss) // 2
    assert max(rss[half:]) < 1.1 * max(rss[:half]) + 50, rss  # no growth over the second half of the flood
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    print(f"flood: {time.monotonic() - start:.0f} s, RSS MB first half max {max(rss[:half]):.0f}, second half max "
          f"{max(rss[half:]):.0f}; drops {({k: v for k, v in last.items() if k.startswith('drop_')})}")


def test_compressed_images_are_learnt_from_the_graph_and_processed(cache_dir, tmp_path, node_process):
    """image_transport auto: the node finds sensor_msgs/CompressedImage on its image topic in the ROS graph,
    subscribes with that type and decodes the JPEG frames into results (the gate open: this checks decoding)."""
    topic = "/cam0/image_raw/compressed"
    with _feeder("sensor_msgs/msg/CompressedImage", topic) as (types, pub_img, pub_imu, diag):
        asl = cached_sequence(cache_dir, seconds=2.5, seed=1, with_depth=False)
        calib = tmp_path / "cam0.yaml"
        write_euroc_sensor_yaml(EUROC_CAM0, calib)
        proc = node_process(calib, "-p", f"image_topic:={topic}", "-p", "max_scale_sigma:=10.0")
        time.sleep(6.0)
        _feed(asl, types, pub_img, pub_imu, seconds=2.5, compress="jpeg")
        time.sleep(3.0)
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
        assert proc.returncode == 0 and f"images: {topic} carries sensor_msgs/msg/CompressedImage" in out, out
        last = [s for m in diag for s in diagnostic_array_to_statuses(m) if s.name == "vi3: pipeline"][-1].values
        assert int(last.get("outcome_init", 0)) >= 1, last
        assert not any(k.startswith("drop_image") for k in last), last


def test_cond_with_a_backbone_that_cannot_condition_is_a_clear_start_error(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "vi3_ros.node", "--ros-args", "-p", "mode:=cond"],
                          capture_output=True, text=True, timeout=120)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 2 and "backbones that can: pi3x, da3" in out and "Traceback" not in out
