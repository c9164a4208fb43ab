"""``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` <-> numpy arrays.

Arrays are [H,W] for one channel and [H,W,C] otherwise; colour is always in RGB(A) order on the numpy side:
``bgr8``/``bgra8`` are reordered on read and on write, ``8UC3`` is passed through untouched (its channel
order is not specified). dtypes: uint8 for 8-bit encodings, uint16 for ``mono16``/``16UC1``, float32 for
``32FC1`` (depth in metres, NaN where invalid, REP-118).
"""

from __future__ import annotations

import sys
from typing import Any, NamedTuple

import cv2
import numpy as np
import simplejpeg

from msg_adapters.errors import MalformedMessage, UnsupportedEncoding
from msg_adapters.fields import str_field, uint8_buffer, uint_field
from msg_adapters.stamps import make_header
from msg_adapters.types import MessageTypes


class _Layout(NamedTuple):
    dtype: np.dtype  # native byte order
    channels: int
    to_rgb: tuple[int, ...] | None  # channel permutation between the message and RGB(A); its own inverse


ENCODINGS: dict[str, _Layout] = {
    "mono8": _Layout(np.dtype(np.uint8), 1, None),
    "8UC1": _Layout(np.dtype(np.uint8), 1, None),
    "mono16": _Layout(np.dtype(np.uint16), 1, None),
    "16UC1": _Layout(np.dtype(np.uint16), 1, None),
    "32FC1": _Layout(np.dtype(np.float32), 1, None),
    "rgb8": _Layout(np.dtype(np.uint8), 3, None),
    "8UC3": _Layout(np.dtype(np.uint8), 3, None),
    "bgr8": _Layout(np.dtype(np.uint8), 3, (2, 1, 0)),
    "rgba8": _Layout(np.dtype(np.uint8), 4, None),
    "bgra8": _Layout(np.dtype(np.uint8), 4, (2, 1, 0, 3)),
}

_HOST_BIG_ENDIAN = sys.byteorder == "big"
JPEG_SOI = b"\xff\xd8"  # the first two bytes of every JPEG file (start of image)


def _layout(encoding: Any) -> _Layout:
    layout = ENCODINGS.get(str_field(encoding, "encoding"))
    if layout is None:
        raise UnsupportedEncoding(f"encoding = {encoding!r} is not supported (supported: {', '.join(ENCODINGS)})")
    return layout


def image_to_numpy(msg: Any) -> np.ndarray:
    """``sensor_msgs/Image`` -> [H,W] or [H,W,C] array (RGB(A) order for colour; see the module docstring).

    Honours ``step`` (row padding) and ``is_bigendian``. The result is a read-only view of ``msg.data`` when
    no reordering, byte swap or realignment is needed, else a fresh writable array.
    """
    layout = _layout(msg.encoding)
    height, width, step = (uint_field(getattr(msg, k), k) for k in ("height", "width", "step"))
    big_endian = uint_field(msg.is_bigendian, "is_bigendian", bits=8) != 0
    data = uint8_buffer(msg.data, "data")
    pixel = layout.channels * layout.dtype.itemsize
    if step < width * pixel:
        raise MalformedMessage(f"step = {step} is smaller than width * bytes per pixel = {width} * {pixel} "
                               f"for encoding {msg.encoding}")
    if data.size != step * height:
        raise MalformedMessage(f"data has {data.size} bytes, expected step * height = {step} * {height} = "
                               f"{step * height}")
    shape = (height, width, layout.channels) if layout.channels > 1 else (height, width)
    strides = (step, pixel, layout.dtype.itemsize)[:len(shape)]
    dtype = layout.dtype.newbyteorder(">" if big_endian else "<")
    arr = np.ndarray(shape, dtype=dtype, buffer=data, strides=strides)
    if layout.to_rgb is not None:
        arr = arr[..., layout.to_rgb]
    if arr.dtype != layout.dtype or not arr.flags.aligned:
        arr = arr.astype(layout.dtype)
    if np.shares_memory(arr, data):
        arr.flags.writeable = False
    return arr


def compressed_to_numpy(msg: Any) -> np.ndarray:
    """``sensor_msgs/CompressedImage`` (jpeg or png) -> [H,W] or [H,W,C] array, RGB(A) order.

    uint8, or uint16 for 16-bit PNG. ``compressedDepth`` (a header before the PNG) is not supported. A JPEG (told by
    its first bytes) is decoded strictly (``decode_jpeg``): one the decoder finds truncated or corrupt is malformed,
    even where a lenient decoder would fill the rest in grey.
    """
    fmt = str_field(msg.format, "format")
    low = fmt.lower()
    if "compresseddepth" in low or not any(k in low for k in ("jpeg", "jpg", "png")):
        raise UnsupportedEncoding(f"format = {fmt!r} is not a supported compression (jpeg or png)")
    data = uint8_buffer(msg.data, "data")
    if data.size == 0:
        raise MalformedMessage(f"data is empty for format {fmt!r}")
    if data[:2].tobytes() == JPEG_SOI:
        return decode_jpeg(data)
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise MalformedMessage(f"data ({data.size} bytes) could not be decoded as {fmt!r}: {exc}") from exc
    if img is None:
        raise MalformedMessage(f"data ({data.size} bytes) could not be decoded as {fmt!r}")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)
    return img


def decode_jpeg(data: np.ndarray) -> np.ndarray:
    """JPEG bytes [N] uint8 -> [H,W] (one channel) or [H,W,3] RGB uint8, by libjpeg-turbo (``simplejpeg``) in strict
    mode: every warning of the decoder (truncated file, corrupt data, ...) is a MalformedMessage quoting it."""
    buf = data.tobytes()
    try:
        channels = simplejpeg.decode_jpeg_header(buf)[2]
        img = simplejpeg.decode_jpeg(buf, colorspace="GRAY" if channels == "Gray" else "RGB", strict=True)
    except ValueError as exc:
        raise MalformedMessage(f"data ({data.size} bytes) is not a sound JPEG: the decoder says {exc}") from exc
    return img[..., 0] if img.shape[2] == 1 else img


def camera_frame(msg: Any) -> np.ndarray:
    """A camera frame from a ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage`` (told apart by the
    ``format`` field that only the latter has): [H,W] for one channel, else [H,W,3] RGB (alpha dropped), in the
    message's dtype. Raises UnsupportedEncoding / MalformedMessage as the two decoders do."""
    img = compressed_to_numpy(msg) if hasattr(msg, "format") else image_to_numpy(msg)
    if img.ndim == 3 and img.shape[2] == 1:
        return img[..., 0]
    return img[..., :3] if img.ndim == 3 and img.shape[2] == 4 else img


def numpy_to_image(arr: np.ndarray, *, encoding: str, stamp_ns: int, frame_id: str, types: MessageTypes) -> Any:
    """[H,W] or [H,W,C] array (RGB(A) order for colour) -> ``sensor_msgs/Image`` in host byte order.

    ``arr.dtype`` must be the encoding's dtype (see the module docstring); nothing is cast silently.
    """
    layout = _layout(encoding)
    arr = np.asarray(arr)
    if arr.ndim == 2 and layout.channels == 1:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[2] != layout.channels:
        raise MalformedMessage(f"image of shape {arr.shape} does not fit encoding {encoding} "
                               f"({layout.channels} channel(s))")
    if arr.dtype.newbyteorder("=") != layout.dtype:
        raise MalformedMessage(f"image dtype {arr.dtype} does not fit encoding {encoding} (needs {layout.dtype})")
    if layout.to_rgb is not None:
        arr = arr[..., layout.to_rgb]
    arr = np.array(arr, dtype=layout.dtype, order="C")  # a copy: the message must not alias the caller's buffer
    height, width = arr.shape[:2]
    return types.make("sensor_msgs/msg/Image", header=make_header(stamp_ns=stamp_ns, frame_id=frame_id, types=types),
                      height=height, width=width, encoding=encoding, is_bigendian=int(_HOST_BIG_ENDIAN),
                      step=width * layout.channels * layout.dtype.itemsize, data=types.uint8_seq(arr))


def depth_to_image(depth_m: np.ndarray, *, stamp_ns: int, frame_id: str, types: MessageTypes) -> Any:
    """[H,W] z-depth in metres -> ``32FC1`` ``sensor_msgs/Image``, NaN where invalid (non-finite or <= 0)."""
    try:
        depth = np.asarray(depth_m, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise MalformedMessage(f"depth is not a numeric array: {exc}") from exc
    if depth.ndim != 2:
        raise MalformedMessage(f"depth has shape {depth.shape}, expected [H,W]")
    with np.errstate(invalid="ignore"):
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(np.nan))
    return numpy_to_image(depth, encoding="32FC1", stamp_ns=stamp_ns, frame_id=frame_id, types=types)
