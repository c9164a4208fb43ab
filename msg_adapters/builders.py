"""Builders of the messages the node publishes, gathered from their per-family modules (one import for callers).

Every builder takes the message classes as ``types=`` (a ``MessageTypes``) and stamps as integer nanoseconds.
"""

from msg_adapters.diagnostics import DiagStatus, Level, diagnostic_array, diagnostic_array_to_statuses
from msg_adapters.pointcloud import point_cloud2, point_cloud2_to_numpy
from msg_adapters.poses import (
    odometry,
    odometry_to_numpy,
    path,
    pose_array,
    pose_stamped,
    pose_to_T,
    poses_to_T,
    tf_message,
    tf_message_to_list,
    transform_stamped,
    transform_to_T,
)

__all__ = [
    "DiagStatus",
    "Level",
    "diagnostic_array",
    "diagnostic_array_to_statuses",
    "odometry",
    "odometry_to_numpy",
    "path",
    "point_cloud2",
    "point_cloud2_to_numpy",
    "pose_array",
    "pose_stamped",
    "pose_to_T",
    "poses_to_T",
    "tf_message",
    "tf_message_to_list",
    "transform_stamped",
    "transform_to_T",
]
