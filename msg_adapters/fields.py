"""Strict readers of message field values: each returns a clean Python/numpy value or raises
``MalformedMessage`` naming the field and the value. They accept both backends' representations
(rosbags: numpy arrays and ints; rclpy: ``array.array``, numpy arrays and ints)."""

from __future__ import annotations

import array
import numbers
from typing import Any

import numpy as np

from msg_adapters.errors import MalformedMessage


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def uint_field(value: Any, name: str, *, bits: int = 32) -> int:
    """An unsigned integer field ``name`` in [0, 2**bits)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise MalformedMessage(f"{name} = {_short(value)} ({type(value).__name__}) is not an integer")
    if not 0 <= int(value) < 1 << bits:
        raise MalformedMessage(f"{name} = {int(value)} is outside [0, {(1 << bits) - 1}]")
    return int(value)


def str_field(value: Any, name: str) -> str:
    """A string field ``name``."""
    if not isinstance(value, str):
        raise MalformedMessage(f"{name} = {_short(value)} ({type(value).__name__}) is not a string")
    return value


def real_field(value: Any, name: str) -> float:
    """A float64 field ``name`` (NaN and inf are passed through: they are data, judged downstream)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise MalformedMessage(f"{name} = {_short(value)} ({type(value).__name__}) is not a real number")
    return float(value)


def vector_field(msg: Any, name: str, keys: str = "xyz") -> np.ndarray:
    """Float64 [len(keys)] from the scalar fields ``keys`` of a sub-message (Vector3, Point, Quaternion: "xyzw")."""
    return np.array([real_field(getattr(msg, k, None), f"{name}.{k}") for k in keys])


def message_list(value: Any, name: str) -> list[Any]:
    """A sequence-of-messages field ``name`` (a list in both backends)."""
    if not isinstance(value, list | tuple):
        raise MalformedMessage(f"{name} = {_short(value)} ({type(value).__name__}) is not a list of messages")
    return list(value)


def float_array(value: Any, name: str, *, size: int | None = None) -> np.ndarray:
    """A float64 array/sequence field ``name`` as a 1-D float64 array, of exactly ``size`` elements if given."""
    if isinstance(value, str | bytes):
        raise MalformedMessage(f"{name} = {_short(value)} is not a sequence of numbers")
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise MalformedMessage(f"{name} = {_short(value)} is not a sequence of numbers ({exc})") from exc
    if arr.ndim != 1 or arr.dtype.kind not in "iuf":
        raise MalformedMessage(f"{name} = {_short(value)} is not a flat sequence of numbers "
                               f"(dtype {arr.dtype}, shape {arr.shape})")
    if size is not None and arr.size != size:
        raise MalformedMessage(f"{name} has {arr.size} elements, expected {size}")
    return arr.astype(np.float64, copy=False)


def uint8_buffer(value: Any, name: str) -> np.ndarray:
    """A ``uint8[]`` field ``name`` as a 1-D uint8 array, a view of the message's buffer where possible."""
    if isinstance(value, np.ndarray):
        if value.dtype == np.uint8 and value.ndim == 1:
            return value
    elif isinstance(value, bytes | bytearray | memoryview) or (isinstance(value, array.array)
                                                                and value.typecode == "B"):
        return np.frombuffer(value, dtype=np.uint8)
    elif isinstance(value, list | tuple):
        try:
            arr = np.asarray(value)
        except (TypeError, ValueError):
            arr = np.zeros(0, dtype=object)
        if arr.ndim == 1 and (arr.size == 0 or (arr.dtype.kind in "iu" and arr.min() >= 0 and arr.max() <= 255)):
            return arr.astype(np.uint8)
    raise MalformedMessage(f"{name} = {_short(value)} ({type(value).__name__}) is not a uint8 buffer")
