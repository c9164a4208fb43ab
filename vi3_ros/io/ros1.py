"""Write an EuRoC ASL folder as a ROS 1 bag the way EuRoC ships its bags, with rosbags (Noetic message types).

Topics: ``/cam0/image_raw`` (``sensor_msgs/Image`` mono8), ``/imu0`` (``sensor_msgs/Imu``, no orientation) and,
when the folder has ground truth, ``/vicon/firefly_sbx/firefly_sbx`` (``geometry_msgs/TransformStamped``, the
body pose in the world, as in EuRoC's Vicon-room bags). No CameraInfo (EuRoC bags carry none). Every message's
header stamp and record time is the ASL nanosecond stamp, unchanged.
"""

from __future__ import annotations

import functools
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_typestore

from msg_adapters.image import numpy_to_image
from msg_adapters.imu import samples_to_imus
from msg_adapters.poses import transform_stamped
from msg_adapters.types import MessageTypes
from vi3_core.dataset.asl import read_asl
from vi3_core.errors import DataError
from vi3_core.types import ImuSamples
from vi3_ros.io import topics
from vi3_ros.io.reader import merge_by_time


@functools.cache
def noetic_typestore():
    """The rosbags ROS 1 Noetic typestore (message classes and ROS 1 serialisation)."""
    return get_typestore(Stores.ROS1_NOETIC)


@functools.cache
def ros1_types() -> MessageTypes:
    """``MessageTypes`` over the Noetic classes; ROS 1 headers get ``seq = 0`` (msg_adapters builds ROS 2 headers)."""
    store = noetic_typestore()
    classes = dict(store.types)
    classes["std_msgs/msg/Header"] = functools.partial(store.types["std_msgs/msg/Header"], seq=0)
    return MessageTypes.from_typestore(SimpleNamespace(types=classes))


def write_ros1_bag(asl_path, bag_path, *, compression: str | None = None) -> Path:
    """Write the ASL folder ``asl_path`` (``mav0`` or its parent) as the ROS 1 bag ``bag_path``.

    ``compression``: None (as EuRoC), "lz4" or "bz2" (rosbag1 chunk compression). Returns ``bag_path``.
    """
    seq = read_asl(asl_path)
    bag_path = Path(bag_path)
    if bag_path.exists():
        raise DataError(f"{bag_path}: already exists; not overwriting a bag")
    bag_path.parent.mkdir(parents=True, exist_ok=True)
    types, store = ros1_types(), noetic_typestore()
    imu_msgs = samples_to_imus(ImuSamples(seq.imu.t, seq.imu.gyro, seq.imu.accel), frame_id=topics.IMU_FRAME,
                               types=types, stamps_ns=seq.imu_ns.tolist())
    gt_ns = seq.gt.t_ns if seq.gt is not None else np.zeros(0, np.int64)
    writer = Writer(bag_path)
    if compression is not None:
        writer.set_compression(Writer.CompressionFormat[compression.upper()])
    with writer:
        conns = [writer.add_connection(topics.IMAGE_TOPIC, topics.IMAGE_TYPE, typestore=store),
                 writer.add_connection(topics.IMU_TOPIC, topics.IMU_TYPE, typestore=store)]
        if len(gt_ns):
            conns.append(writer.add_connection(topics.GT_TOPIC, topics.GT_TYPE, typestore=store))
        for ns, stream, i in merge_by_time(seq.stamps_ns, seq.imu_ns, gt_ns):  # one time-ordered stream, as recorded
            if stream == 0:
                msg = numpy_to_image(seq.image(i), encoding="mono8", stamp_ns=ns, frame_id=topics.CAM_FRAME,
                                     types=types)
            elif stream == 1:
                msg = imu_msgs[i]
            else:  # the body pose in the world, as EuRoC's Vicon topic
                msg = transform_stamped(seq.gt.T_WB[i], parent=topics.WORLD_FRAME, child=topics.GT_CHILD_FRAME,
                                        stamp_ns=ns, types=types)
            writer.write(conns[stream], ns, store.serialize_ros1(msg, conns[stream].msgtype))
    return bag_path
