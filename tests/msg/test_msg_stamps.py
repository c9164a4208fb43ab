"""builtin_interfaces/Time <-> ns / seconds: exact, and strict on bad stamps."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from msg_adapters.errors import MalformedMessage
from msg_adapters.stamps import MAX_NS, MAX_SEC, ns_to_stamp, sec_to_ns, sec_to_stamp, stamp_to_ns, stamp_to_sec
from msg_adapters.types import jazzy_types

TYPES = jazzy_types()
TS = TYPES.typestore


@given(st.integers(min_value=0, max_value=MAX_NS))
def test_ns_round_trip_is_exact_through_cdr(ns):
    stamp = ns_to_stamp(ns, types=TYPES)
    raw = TS.serialize_cdr(stamp, "builtin_interfaces/msg/Time")
    back = TS.deserialize_cdr(raw, "builtin_interfaces/msg/Time")
    assert (back.sec, back.nanosec) == divmod(ns, 10**9)
    assert stamp_to_ns(back) == ns
    assert stamp_to_sec(back) == float(Fraction(ns, 10**9))  # correctly rounded


@given(st.floats(min_value=0.0, max_value=float(MAX_SEC), allow_nan=False, allow_infinity=False))
def test_seconds_round_to_the_nearest_nanosecond(sec):
    ns = sec_to_ns(sec)
    assert abs(Fraction(ns) - Fraction(sec) * 10**9) <= Fraction(1, 2)
    stamp = sec_to_stamp(sec, types=TYPES)
    assert stamp_to_ns(stamp) == ns
    if sec >= 1e7:  # float spacing > 1 ns: seconds -> ns -> seconds is the identity
        assert stamp_to_sec(stamp) == sec


def test_numpy_scalars_and_ints_are_accepted():
    assert sec_to_ns(np.float32(0.5)) == 500_000_000
    assert sec_to_ns(np.float64(1403636579.7585554)) == sec_to_ns(1403636579.7585554)
    assert sec_to_ns(3) == 3 * 10**9
    assert stamp_to_ns(ns_to_stamp(np.int64(1403636579758555392), types=TYPES)) == 1403636579758555392


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, -1e-9, -3, float(MAX_SEC) + 1.0, "1.0", None, True])
def test_bad_seconds_raise_value_error_naming_the_value(bad):
    with pytest.raises(MalformedMessage, match="stamp"):
        sec_to_stamp(bad, types=TYPES)


@pytest.mark.parametrize("bad", [-1, MAX_NS + 1, 1.5e9, math.nan, "5", False])
def test_bad_nanoseconds_raise_value_error(bad):
    with pytest.raises(ValueError, match="stamp"):
        ns_to_stamp(bad, types=TYPES)


@pytest.mark.parametrize(("sec", "nanosec", "field"), [
    (math.nan, 0, "stamp.sec"), (1.0, 0, "stamp.sec"), (-1, 0, "stamp.sec"), (1, 10**9, "stamp.nanosec"),
    (1, -1, "stamp.nanosec"), (1, math.inf, "stamp.nanosec"), (None, 0, "stamp.sec"),
])
def test_malformed_stamps_name_the_field(sec, nanosec, field):
    stamp = TYPES.make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)
    with pytest.raises(MalformedMessage, match=field):
        stamp_to_ns(stamp)
