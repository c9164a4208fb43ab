"""Write an EuRoC ASL folder as a ROS 1 bag the way EuRoC ships its bags, with rosbags (Noetic message types).

Topics: ``/cam0/image_raw`` (``sensor_msgs/Image`` mono8), ``/imu0`` (``sensor_msgs/Imu``, no orientation) and,
when the folder has ground truth, ``/vicon/firefly_sbx/firefly_sbx`` (``geometry_msgs/TransformStamped``, the
body pose in the world, as in EuRoC's Vicon-room bags). No CameraInfo (EuRoC bags carry none). Every message's
header stamp and record time is the ASL nanosecond stamp, unchanged.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
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


class Ros1BagWriter:
    """A ROS 1 bag of EuRoC's topics written a block of time at a time (``write``; blocks in time order), so that a
    sequence of any length streams through. A context manager: closed (index written) on success, aborted on error.

    ``with_gt``: add the ground-truth topic; ``compression``: None (as EuRoC), "lz4" or "bz2" (chunk compression).
    """

    def __init__(self, bag_path, *, with_gt: bool = True, compression: str | None = None) -> None:
        self.path = Path(bag_path)
        if self.path.exists():
            raise DataError(f"{self.path}: already exists; not overwriting a bag")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._types, self._store = ros1_types(), noetic_typestore()
        self._writer = Writer(self.path)
        if compression is not None:
            self._writer.set_compression(Writer.CompressionFormat[compression.upper()])
        self._writer.open()
        streams = [(topics.IMAGE_TOPIC, topics.IMAGE_TYPE), (topics.IMU_TOPIC, topics.IMU_TYPE)]
        if with_gt:
            streams.append((topics.GT_TOPIC, topics.GT_TYPE))
        self._conns = [self._writer.add_connection(topic, msgtype, typestore=self._store) for topic, msgtype in streams]

    def write(self, cam_ns: np.ndarray, image: Callable[[int], np.ndarray], imu_ns: np.ndarray, imu: ImuSamples,
              gt_ns: np.ndarray, T_WB: np.ndarray) -> None:
        """One block: frames at ``cam_ns`` [n] (``image(i)`` gives frame i, mono8), IMU samples at ``imu_ns`` [m],
        body poses ``T_WB`` [k,4,4] at ``gt_ns`` [k] (ignored without the GT topic), merged by stamp as recorded."""
        types, store = self._types, self._store
        imu_msgs = samples_to_imus(ImuSamples(imu.t, imu.gyro, imu.accel), frame_id=topics.IMU_FRAME, types=types,
                                   stamps_ns=np.asarray(imu_ns).tolist())
        if len(self._conns) < 3:
            gt_ns = np.zeros(0, np.int64)
        for ns, stream, i in merge_by_time(cam_ns, imu_ns, gt_ns):
            if stream == 0:
                msg = numpy_to_image(image(i), encoding="mono8", stamp_ns=ns, frame_id=topics.CAM_FRAME, types=types)
            elif stream == 1:
                msg = imu_msgs[i]
            else:  # the body pose in the world, as EuRoC's Vicon topic
                msg = transform_stamped(T_WB[i], parent=topics.WORLD_FRAME, child=topics.GT_CHILD_FRAME,
                                        stamp_ns=ns, types=types)
            conn = self._conns[stream]
            self._writer.write(conn, ns, store.serialize_ros1(msg, conn.msgtype))

    def close(self) -> None:
        self._writer.close()

    def abort(self) -> None:
        self._writer.abort()

    def __enter__(self) -> Ros1BagWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_ros1_bag(asl_path, bag_path, *, compression: str | None = None) -> Path:
    """Write the ASL folder ``asl_path`` (``mav0`` or its parent) as the ROS 1 bag ``bag_path``.

    ``compression``: None (as EuRoC), "lz4" or "bz2" (rosbag1 chunk compression). Returns ``bag_path``.
    """
    seq = read_asl(asl_path)
    gt_ns, T_WB = (seq.gt.t_ns, seq.gt.T_WB) if seq.gt is not None else (np.zeros(0, np.int64), np.zeros((0, 4, 4)))
    with Ros1BagWriter(bag_path, with_gt=seq.gt is not None, compression=compression) as bag:
        bag.write(seq.stamps_ns, seq.image, seq.imu_ns, seq.imu, gt_ns, T_WB)
    return Path(bag_path)
