"""``builtin_interfaces/Time`` <-> float64 seconds and int nanoseconds, exact, and ``std_msgs/Header``.

Stamps are non-negative (``sec`` is int32 in ROS 2, so the last representable stamp is 2**31 - 1 s plus
999999999 ns). Integer nanoseconds round-trip exactly; seconds are rounded once, correctly: float -> ns to the
nearest nanosecond (ties to even), ns -> float to the nearest float64.
"""

from __future__ import annotations

import math
import numbers
from fractions import Fraction
from typing import Any

from msg_adapters.errors import MalformedMessage
from msg_adapters.fields import str_field, uint_field
from msg_adapters.types import MessageTypes

NS_PER_S = 1_000_000_000
MAX_SEC = (1 << 31) - 1
MAX_NS = MAX_SEC * NS_PER_S + NS_PER_S - 1


def stamp_to_ns(stamp: Any, *, name: str = "stamp") -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds since the epoch; ``name`` labels errors."""
    sec = uint_field(getattr(stamp, "sec", None), f"{name}.sec", bits=31)
    nanosec = uint_field(getattr(stamp, "nanosec", None), f"{name}.nanosec")
    if nanosec >= NS_PER_S:
        raise MalformedMessage(f"{name}.nanosec = {nanosec} is not below 1e9 (sec = {sec})")
    return sec * NS_PER_S + nanosec


def stamp_to_sec(stamp: Any, *, name: str = "stamp") -> float:
    """``builtin_interfaces/Time`` -> float64 seconds (the float nearest to the exact value)."""
    return stamp_to_ns(stamp, name=name) / NS_PER_S  # int / int is correctly rounded in Python


def _check_ns(ns: int, what: str) -> int:
    if not 0 <= ns <= MAX_NS:
        raise MalformedMessage(f"{what} is outside the ROS 2 Time range [0, {MAX_NS}] ns")
    return ns


def stamp_parts(ns: int) -> tuple[int, int]:
    """Integer nanoseconds (int or numpy integer, >= 0) -> (sec, nanosec) of a ``builtin_interfaces/Time``. Called
    for every ``~/odom/imu`` message: a plain int takes the short path."""
    if type(ns) is not int:
        if isinstance(ns, bool) or not isinstance(ns, numbers.Integral):
            raise MalformedMessage(f"stamp {ns!r} ({type(ns).__name__}) is not an integer number of nanoseconds")
        ns = int(ns)
    if not 0 <= ns <= MAX_NS:
        _check_ns(ns, f"stamp {ns} ns")
    return divmod(ns, NS_PER_S)


def ns_to_stamp(ns: int, *, types: MessageTypes) -> Any:
    """Integer nanoseconds (int or numpy integer, >= 0) -> ``builtin_interfaces/Time``."""
    sec, nanosec = stamp_parts(ns)
    return types.make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)


def sec_to_ns(sec: float) -> int:
    """Seconds (finite, >= 0; float, int or numpy scalar) -> nanoseconds, the nearest to the exact value."""
    if isinstance(sec, bool) or not isinstance(sec, numbers.Real):
        raise MalformedMessage(f"stamp {sec!r} ({type(sec).__name__}) is not a number of seconds")
    if isinstance(sec, numbers.Integral):
        ns = int(sec) * NS_PER_S
    else:
        sec = float(sec)  # numpy float32/float64 -> float exactly
        if not math.isfinite(sec):
            raise MalformedMessage(f"stamp {sec} s is not finite")
        ns = round(Fraction(sec) * NS_PER_S)
    return _check_ns(ns, f"stamp {sec} s")


def sec_to_stamp(sec: float, *, types: MessageTypes) -> Any:
    """Seconds (finite, >= 0) -> ``builtin_interfaces/Time``, rounded to the nearest nanosecond."""
    return ns_to_stamp(sec_to_ns(sec), types=types)


def make_header(*, stamp_ns: int, frame_id: str, types: MessageTypes) -> Any:
    """``std_msgs/Header`` with the stamp ``stamp_ns`` (integer ns) and ``frame_id``."""
    return types.make("std_msgs/msg/Header", stamp=ns_to_stamp(stamp_ns, types=types),
                      frame_id=str_field(frame_id, "frame_id"))
