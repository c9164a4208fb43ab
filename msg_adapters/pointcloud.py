"""``sensor_msgs/PointCloud2`` <-> numpy structured arrays.

Clouds are built as float32 x, y, z (metres, in ``frame_id``) plus optional float32 ``intensity`` and
``confidence``, interleaved in one structured array whose bytes become ``data``; the ``PointField`` list is
derived from that array's dtype, and decoding derives the dtype from the ``PointField`` list.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

from msg_adapters.errors import MalformedMessage
from msg_adapters.fields import message_list, str_field, uint8_buffer, uint_field
from msg_adapters.stamps import make_header
from msg_adapters.types import MessageTypes

# sensor_msgs/PointField datatype constants -> numpy type codes
POINTFIELD_DTYPES: dict[int, str] = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_DATATYPE_OF = {np.dtype(code): datatype for datatype, code in POINTFIELD_DTYPES.items()}
_HOST_BIG_ENDIAN = sys.byteorder == "big"


def _float32(arr: Any, name: str) -> np.ndarray:
    try:
        return np.asarray(arr, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise MalformedMessage(f"{name} is not a numeric array: {exc}") from exc


def _point_fields(dtype: np.dtype, types: MessageTypes) -> list[Any]:
    """``sensor_msgs/PointField`` list describing the (flat, scalar-field) structured ``dtype``."""
    return [types.make("sensor_msgs/msg/PointField", name=name, offset=offset, datatype=_DATATYPE_OF[sub], count=1)
            for name, (sub, offset) in dtype.fields.items()]


def point_cloud2(points: np.ndarray, *, intensity: np.ndarray | None = None, confidence: np.ndarray | None = None,
                 stamp_ns: int, frame_id: str, types: MessageTypes) -> Any:
    """Points [N,3] (unorganised) or [H,W,3] (organised), metres -> ``sensor_msgs/PointCloud2``.

    ``intensity`` / ``confidence``: optional [N] or [H,W] (any real dtype, stored as float32). ``is_dense`` is
    true when every point is finite. Vectorised: one interleaving copy, no per-point work.
    """
    pts = _float32(points, "points")
    if pts.ndim not in (2, 3) or pts.shape[-1] != 3:
        raise MalformedMessage(f"points has shape {pts.shape}, expected [N,3] or [H,W,3]")
    extras = {name: _float32(a, name) for name, a in (("intensity", intensity), ("confidence", confidence))
              if a is not None}
    for name, a in extras.items():
        if a.shape != pts.shape[:-1]:
            raise MalformedMessage(f"{name} has shape {a.shape}, expected {pts.shape[:-1]} to match points")
    dtype = np.dtype([(name, np.float32) for name in ("x", "y", "z", *extras)])
    cloud = np.empty(pts.shape[:-1], dtype=dtype)
    columns = cloud.view(np.float32).reshape(pts.shape[:-1] + (len(dtype.names),))  # same bytes, one column a field
    columns[..., :3] = pts
    for j, a in enumerate(extras.values()):
        columns[..., 3 + j] = a
    height, width = pts.shape[:2] if pts.ndim == 3 else (1, pts.shape[0])
    return types.make("sensor_msgs/msg/PointCloud2",
                      header=make_header(stamp_ns=stamp_ns, frame_id=frame_id, types=types),
                      height=height, width=width, fields=_point_fields(dtype, types), is_bigendian=_HOST_BIG_ENDIAN,
                      point_step=dtype.itemsize, row_step=dtype.itemsize * width, data=types.uint8_seq(cloud),
                      is_dense=bool(np.isfinite(pts).all()))


def _dtype_from_fields(msg: Any, point_step: int, big_endian: bool) -> np.dtype:
    names, formats, offsets = [], [], []
    for i, f in enumerate(message_list(msg.fields, "fields")):
        name = str_field(getattr(f, "name", None), f"fields[{i}].name")
        offset = uint_field(getattr(f, "offset", None), f"fields[{i}].offset")
        datatype = uint_field(getattr(f, "datatype", None), f"fields[{i}].datatype", bits=8)
        count = uint_field(getattr(f, "count", None), f"fields[{i}].count")
        if datatype not in POINTFIELD_DTYPES:
            raise MalformedMessage(f"fields[{i}] ({name!r}).datatype = {datatype} is not a PointField type (1..8)")
        if not name or name in names:
            raise MalformedMessage(f"fields[{i}].name = {name!r} is empty or repeated")
        base = np.dtype(POINTFIELD_DTYPES[datatype]).newbyteorder(">" if big_endian else "<")
        if count == 0 or offset + base.itemsize * count > point_step:
            raise MalformedMessage(f"fields[{i}] ({name!r}) with offset {offset}, count {count} of "
                                   f"{base.itemsize}-byte values does not fit point_step = {point_step}")
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(offset)
    if not names:
        raise MalformedMessage("fields is empty")
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})


def point_cloud2_to_numpy(msg: Any) -> np.ndarray:
    """``sensor_msgs/PointCloud2`` -> structured array [N] (height 1) or [H,W], one numpy field per PointField.

    A read-only view of ``msg.data`` when the cloud is in host byte order, else a native-order copy.
    """
    height, width, point_step, row_step = (uint_field(getattr(msg, k), k)
                                           for k in ("height", "width", "point_step", "row_step"))
    if not isinstance(msg.is_bigendian, bool | int | np.integer):
        raise MalformedMessage(f"is_bigendian = {msg.is_bigendian!r} is not a bool")
    big_endian = bool(msg.is_bigendian)
    dtype = _dtype_from_fields(msg, point_step, big_endian)
    if row_step < width * point_step:
        raise MalformedMessage(f"row_step = {row_step} is smaller than width * point_step = {width} * {point_step}")
    data = uint8_buffer(msg.data, "data")
    if data.size != row_step * height:
        raise MalformedMessage(f"data has {data.size} bytes, expected row_step * height = {row_step} * {height} = "
                               f"{row_step * height}")
    cloud = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row_step, point_step))
    if big_endian != _HOST_BIG_ENDIAN:
        cloud = cloud.astype(dtype.newbyteorder("="))
    else:
        cloud.flags.writeable = False
    return cloud[0] if height == 1 else cloud
