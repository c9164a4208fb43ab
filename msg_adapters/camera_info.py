"""``sensor_msgs/CameraInfo`` <-> intrinsics K [3,3] (pixels), distortion model and coefficients, image size.

Distortion models and their coefficients (OpenCV order):
``plumb_bob``: k1, k2, p1, p2, k3 (5); ``rational_polynomial``: k1, k2, p1, p2, k3, k4, k5, k6 (8, or 12/14
with OpenCV's thin-prism and tilt terms); ``equidistant`` (fisheye): k1, k2, k3, k4 (4).

ROS 2 names the arrays ``d``, ``k``, ``r``, ``p``; ROS 1 (and bags converted from ROS 1, whose message definitions
keep the ROS 1 names) ``D``, ``K``, ``R``, ``P``. Reading accepts both; building writes the ROS 2 names.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from msg_adapters.errors import MalformedMessage
from msg_adapters.fields import float_array, str_field, uint_field
from msg_adapters.stamps import make_header
from msg_adapters.types import MessageTypes
from vi3_core.errors import CalibrationError

DIST_COEFF_COUNTS: dict[str, tuple[int, ...]] = {
    "plumb_bob": (5,),
    "rational_polynomial": (8, 12, 14),
    "equidistant": (4,),
}


def _check_calib(K: Any, dist_model: Any, dist: Any) -> tuple[np.ndarray, str, np.ndarray]:
    """Validated (K [3,3] float64, model, dist [k] float64) or ``CalibrationError`` saying what is wrong."""
    try:
        K = np.asarray(K, dtype=np.float64)
        dist = np.asarray(dist, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"intrinsics or distortion are not numeric: {exc}") from exc
    if K.shape != (3, 3):
        raise CalibrationError(f"K has shape {K.shape}, expected [3,3]")
    if not np.isfinite(K).all() or not np.isfinite(dist).all():
        raise CalibrationError(f"K or distortion is not finite: K = {K.tolist()}, d = {dist.tolist()}")
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.array_equal(K[2], [0.0, 0.0, 1.0]) and K[1, 0] == 0):
        raise CalibrationError(f"K = {K.tolist()} is not an intrinsic matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] "
                               "with fx, fy > 0 (all zero means the camera is uncalibrated)")
    model = str_field(dist_model, "distortion_model")
    counts = DIST_COEFF_COUNTS.get(model)
    if counts is None:
        raise CalibrationError(f"distortion_model = {model!r} is not supported ({', '.join(DIST_COEFF_COUNTS)})")
    if dist.size not in counts:
        raise CalibrationError(f"distortion_model {model} needs {' or '.join(map(str, counts))} coefficients, "
                               f"d has {dist.size}")
    return K, model, dist


def _array(msg: Any, name: str) -> Any:
    """The CameraInfo array ``name`` ("d" or "k") under its ROS 2 name, else its ROS 1 name (upper case)."""
    value = getattr(msg, name, None)
    return getattr(msg, name.upper(), None) if value is None else value


def camera_info_to_calib(msg: Any) -> tuple[np.ndarray, str, np.ndarray, tuple[int, int]]:
    """``sensor_msgs/CameraInfo`` (ROS 2 or ROS 1 field names) -> (K [3,3] px, distortion model, d [k],
    (width, height) px)."""
    K = float_array(_array(msg, "k"), "k", size=9).reshape(3, 3)
    K, model, dist = _check_calib(K, msg.distortion_model, float_array(_array(msg, "d"), "d"))
    width, height = uint_field(msg.width, "width"), uint_field(msg.height, "height")
    if width == 0 or height == 0:
        raise MalformedMessage(f"image size width x height = {width} x {height} is empty")
    return K, model, dist, (width, height)


def calib_to_camera_info(K: np.ndarray, dist_model: str, dist: np.ndarray, size: tuple[int, int], *,
                         stamp_ns: int, frame_id: str, types: MessageTypes, R: np.ndarray | None = None,
                         P: np.ndarray | None = None) -> Any:
    """(K [3,3], model, d [k], (width, height)) -> ``sensor_msgs/CameraInfo``.

    R [3,3] is the rectification rotation (identity for a monocular camera), P [3,4] the projection of the
    rectified image (default [K | 0]).
    """
    K, model, dist = _check_calib(K, dist_model, dist)
    if len(size) != 2:
        raise MalformedMessage(f"size = {size!r} is not (width, height)")
    width, height = uint_field(size[0], "width"), uint_field(size[1], "height")
    R = np.eye(3) if R is None else np.asarray(R, dtype=np.float64)
    P = np.hstack([K, np.zeros((3, 1))]) if P is None else np.asarray(P, dtype=np.float64)
    if R.shape != (3, 3) or P.shape != (3, 4):
        raise CalibrationError(f"R has shape {R.shape} and P {P.shape}, expected [3,3] and [3,4]")
    roi = types.make("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                     do_rectify=False)
    return types.make("sensor_msgs/msg/CameraInfo",
                      header=make_header(stamp_ns=stamp_ns, frame_id=frame_id, types=types),
                      height=height, width=width, distortion_model=model, d=types.float64_seq(dist),
                      k=K.reshape(9).copy(), r=R.reshape(9).copy(), p=P.reshape(12).copy(),
                      binning_x=0, binning_y=0, roi=roi)
