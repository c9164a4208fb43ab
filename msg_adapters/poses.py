"""Poses as [4,4] transforms <-> ``geometry_msgs``/``nav_msgs``/``tf2_msgs`` messages.

A transform ``T_XY`` maps points from frame Y to frame X (the pose of Y in X): a message with
``header.frame_id = X`` carrying the pose (or ``child_frame_id``) Y. Translations in metres.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from msg_adapters.errors import MalformedMessage
from msg_adapters.fields import float_array, str_field, vector_field
from msg_adapters.stamps import make_header, stamp_parts, stamp_to_ns
from msg_adapters.types import MessageTypes
from vi3_core.so3 import R_to_quat, make_T, orthonormality_error, quat_to_R

_RIGID_TOL = 1e-4


def _transforms(T: Any, name: str, *, single: bool) -> np.ndarray:
    """Validated rigid transforms: [4,4] when ``single`` else [n,4,4], float64."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MalformedMessage(f"{name} is not a numeric array: {exc}") from exc
    if T.shape[-2:] != (4, 4) or T.ndim != (2 if single else 3):
        raise MalformedMessage(f"{name} has shape {T.shape}, expected {'[4,4]' if single else '[n,4,4]'}")
    if not np.isfinite(T).all():
        raise MalformedMessage(f"{name} has non-finite entries")
    if np.abs(T[..., 3, :] - [0.0, 0.0, 0.0, 1.0]).max(initial=0.0) > _RIGID_TOL:
        raise MalformedMessage(f"{name} bottom row is not [0, 0, 0, 1]")
    R = T[..., :3, :3]
    err = orthonormality_error(R)
    if err > _RIGID_TOL or (np.linalg.det(R) <= 0).any():
        raise MalformedMessage(f"{name} rotation block is not a rotation (|R^T R - I| = {err:.2g})")
    return T


_RIGID_KINDS = {"Pose": ("position", "orientation", "Point"), "Transform": ("translation", "rotation", "Vector3")}


def _rigid_msgs(T: np.ndarray, types: MessageTypes, *, kind: str = "Pose") -> list[Any]:
    """[n,4,4] -> ``geometry_msgs/Pose`` (or ``/Transform``) messages, quaternions computed in one batch."""
    where, how, point_type = _RIGID_KINDS[kind]
    quats, points = R_to_quat(T[:, :3, :3]).tolist(), T[:, :3, 3].tolist()
    return [types.make(f"geometry_msgs/msg/{kind}", **{
        where: types.make(f"geometry_msgs/msg/{point_type}", x=p[0], y=p[1], z=p[2]),
        how: types.make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3])})
        for q, p in zip(quats, points)]


def _T_from(translation: Any, rotation: Any, name: str) -> np.ndarray:
    """[4,4] from a Point/Vector3 and a Quaternion message (any non-zero quaternion norm)."""
    p, q = vector_field(translation, f"{name} translation"), vector_field(rotation, f"{name} rotation", "xyzw")
    if not (np.isfinite(p).all() and np.isfinite(q).all() and np.linalg.norm(q) > 0):
        raise MalformedMessage(f"{name}: position {p.tolist()} / quaternion {q.tolist()} is not a valid pose")
    return make_T(quat_to_R(q), p)


def pose_to_T(pose: Any) -> np.ndarray:
    """``geometry_msgs/Pose`` -> [4,4]."""
    return _T_from(pose.position, pose.orientation, "pose")


def transform_to_T(transform: Any) -> np.ndarray:
    """``geometry_msgs/Transform`` -> [4,4]."""
    return _T_from(transform.translation, transform.rotation, "transform")


def poses_to_T(poses: Sequence[Any]) -> np.ndarray:
    """``geometry_msgs/Pose`` sequence (e.g. ``PoseArray.poses``) -> [n,4,4]."""
    return np.stack([pose_to_T(p) for p in poses]) if len(poses) else np.zeros((0, 4, 4))


def pose_array(T: np.ndarray, *, stamp_ns: int, frame_id: str, types: MessageTypes) -> Any:
    """[n,4,4] poses in ``frame_id`` -> ``geometry_msgs/PoseArray``."""
    T = _transforms(T, "T", single=False)
    return types.make("geometry_msgs/msg/PoseArray", header=make_header(stamp_ns=stamp_ns, frame_id=frame_id,
                                                                          types=types), poses=_rigid_msgs(T, types))


def pose_stamped(T: np.ndarray, *, stamp_ns: int, frame_id: str, types: MessageTypes) -> Any:
    """[4,4] pose in ``frame_id`` -> ``geometry_msgs/PoseStamped``."""
    T = _transforms(T, "T", single=True)
    return types.make("geometry_msgs/msg/PoseStamped", header=make_header(stamp_ns=stamp_ns, frame_id=frame_id,
                                                                            types=types),
                      pose=_rigid_msgs(T[None], types)[0])


def path(T: np.ndarray, *, stamp_ns: int, frame_id: str, types: MessageTypes,
         stamps_ns: Sequence[int] | None = None) -> Any:
    """[n,4,4] poses in ``frame_id`` -> ``nav_msgs/Path``; pose i is stamped ``stamps_ns[i]`` (default ``stamp_ns``)."""
    T = _transforms(T, "T", single=False)
    stamps = [stamp_ns] * len(T) if stamps_ns is None else list(stamps_ns)
    if len(stamps) != len(T):
        raise MalformedMessage(f"path: {len(stamps)} stamps for {len(T)} poses")
    poses = [types.make("geometry_msgs/msg/PoseStamped", header=make_header(stamp_ns=s, frame_id=frame_id, types=types),
                        pose=p) for s, p in zip(stamps, _rigid_msgs(T, types))]
    return types.make("nav_msgs/msg/Path", header=make_header(stamp_ns=stamp_ns, frame_id=frame_id, types=types),
                      poses=poses)


def _covariance(cov: Any, name: str) -> np.ndarray:
    """[6,6] or [36] covariance -> [36] float64 (row-major); None -> zeros."""
    if cov is None:
        return np.zeros(36)
    try:
        cov = np.asarray(cov, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MalformedMessage(f"{name} is not numeric: {exc}") from exc
    if cov.size != 36 or cov.shape not in ((6, 6), (36,)):
        raise MalformedMessage(f"{name} has shape {cov.shape}, expected [6,6] or [36]")
    return cov.reshape(36).copy()


def _vector3(v: Any, name: str) -> list[float]:
    try:
        v = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MalformedMessage(f"{name} is not numeric: {exc}") from exc
    if v.shape != (3,):
        raise MalformedMessage(f"{name} has shape {v.shape}, expected [3]")
    return v.tolist()


class OdometryMessages:
    """``nav_msgs/Odometry`` of one frame pair (``child_frame_id``'s pose in ``frame_id``), built cheaply enough for
    every IMU sample: the frame ids are checked once, the pose comes as a position and a unit quaternion, the
    covariances as [36] arrays, and nothing is validated again (``odometry`` validates). With rosbags classes a
    message costs about 4 us; rclpy's constructors check every keyword, so there a default message (about 11 us) is
    filled field by field."""

    def __init__(self, *, frame_id: str, child_frame_id: str, types: MessageTypes) -> None:
        self.frame_id = str_field(frame_id, "frame_id")
        self.child_frame_id = str_field(child_frame_id, "child_frame_id")
        self.types = types
        g = types.get
        self._odometry = g("nav_msgs/msg/Odometry")
        if types.backend != "rclpy":
            self._classes = [g(f"{pkg}/msg/{name}") for pkg, name in (
                ("builtin_interfaces", "Time"), ("std_msgs", "Header"), ("geometry_msgs", "PoseWithCovariance"),
                ("geometry_msgs", "Pose"), ("geometry_msgs", "Point"), ("geometry_msgs", "Quaternion"),
                ("geometry_msgs", "TwistWithCovariance"), ("geometry_msgs", "Twist"), ("geometry_msgs", "Vector3"))]

    def make(self, stamp_ns: int, p: Sequence[float], q: Sequence[float], v: Sequence[float], w: Sequence[float],
             pose_cov: np.ndarray, twist_cov: np.ndarray) -> Any:
        """The message stamped ``stamp_ns`` (int ns): position ``p`` [3] m, attitude ``q`` (x, y, z, w), linear ``v``
        [3] m/s and angular ``w`` [3] rad/s velocity in the child frame, covariances [36] float64 (row-major over x,
        y, z, rot x, rot y, rot z)."""
        sec, nanosec = stamp_parts(stamp_ns)
        if self.types.backend == "rclpy":
            msg = self._odometry()
            msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id = sec, nanosec, self.frame_id
            msg.child_frame_id = self.child_frame_id
            pose, twist = msg.pose.pose, msg.twist.twist
            pose.position.x, pose.position.y, pose.position.z = p
            pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = q
            twist.linear.x, twist.linear.y, twist.linear.z = v
            twist.angular.x, twist.angular.y, twist.angular.z = w
            msg.pose.covariance, msg.twist.covariance = pose_cov, twist_cov
            return msg
        Time, Header, PoseCov, Pose, Point, Quaternion, TwistCov, Twist, Vector3 = self._classes
        return self._odometry(
            header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=self.frame_id),
            child_frame_id=self.child_frame_id,
            pose=PoseCov(pose=Pose(position=Point(x=p[0], y=p[1], z=p[2]),
                                   orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])), covariance=pose_cov),
            twist=TwistCov(twist=Twist(linear=Vector3(x=v[0], y=v[1], z=v[2]), angular=Vector3(x=w[0], y=w[1], z=w[2])),
                           covariance=twist_cov))


def odometry(T: np.ndarray, v_linear: np.ndarray, v_angular: np.ndarray, *, stamp_ns: int, frame_id: str,
             child_frame_id: str, types: MessageTypes, pose_cov: np.ndarray | None = None,
             twist_cov: np.ndarray | None = None) -> Any:
    """Pose [4,4] of ``child_frame_id`` in ``frame_id`` and its twist -> ``nav_msgs/Odometry``, validated.

    v_linear [3] m/s and v_angular [3] rad/s are expressed in ``child_frame_id`` (nav_msgs convention).
    Covariances [6,6] or [36] over (x, y, z, rot x, rot y, rot z); default all zero.
    """
    T = _transforms(T, "T", single=True)
    return OdometryMessages(frame_id=frame_id, child_frame_id=child_frame_id, types=types).make(
        stamp_ns, T[:3, 3].tolist(), R_to_quat(T[:3, :3]).tolist(), _vector3(v_linear, "v_linear"),
        _vector3(v_angular, "v_angular"), _covariance(pose_cov, "pose_cov"), _covariance(twist_cov, "twist_cov"))


def odometry_to_numpy(msg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``nav_msgs/Odometry`` -> (T [4,4], v_linear [3], v_angular [3], pose_cov [6,6], twist_cov [6,6])."""
    twist = msg.twist.twist
    return (pose_to_T(msg.pose.pose), vector_field(twist.linear, "twist.linear"),
            vector_field(twist.angular, "twist.angular"),
            float_array(msg.pose.covariance, "pose.covariance", size=36).reshape(6, 6),
            float_array(msg.twist.covariance, "twist.covariance", size=36).reshape(6, 6))


def transform_stamped(T: np.ndarray, *, parent: str, child: str, stamp_ns: int, types: MessageTypes,
                      name: str = "T") -> Any:
    """[4,4] T_parent_child (translation in metres) -> ``geometry_msgs/TransformStamped`` with ``header.frame_id =
    parent``, ``child_frame_id = child`` and the stamp ``stamp_ns`` (integer ns); ``name`` labels errors."""
    tr = _rigid_msgs(_transforms(T, name, single=True)[None], types, kind="Transform")[0]
    return types.make("geometry_msgs/msg/TransformStamped",
                      header=make_header(stamp_ns=stamp_ns, frame_id=parent, types=types),
                      child_frame_id=str_field(child, f"{name} child"), transform=tr)


def tf_message(transforms: Sequence[tuple[np.ndarray, str, str, int]], *, types: MessageTypes) -> Any:
    """[(T_parent_child [4,4], parent, child, stamp_ns), ...] -> ``tf2_msgs/TFMessage``."""
    return types.make("tf2_msgs/msg/TFMessage", transforms=[
        transform_stamped(T, parent=parent, child=child, stamp_ns=stamp_ns, types=types, name=f"transforms[{i}]")
        for i, (T, parent, child, stamp_ns) in enumerate(transforms)])


def tf_message_to_list(msg: Any) -> list[tuple[np.ndarray, str, str, int]]:
    """``tf2_msgs/TFMessage`` -> [(T_parent_child [4,4], parent, child, stamp_ns), ...]."""
    return [(transform_to_T(t.transform), str_field(t.header.frame_id, "header.frame_id"),
             str_field(t.child_frame_id, "child_frame_id"), stamp_to_ns(t.header.stamp)) for t in msg.transforms]
