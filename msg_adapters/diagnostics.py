"""``diagnostic_msgs/DiagnosticArray`` <-> a list of typed ``DiagStatus`` records."""

from __future__ import annotations

import enum
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from msg_adapters.errors import MalformedMessage
from msg_adapters.fields import str_field, uint_field
from msg_adapters.stamps import make_header
from msg_adapters.types import MessageTypes


class Level(enum.IntEnum):
    """``diagnostic_msgs/DiagnosticStatus`` levels."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


@dataclass(frozen=True)
class DiagStatus:
    """One component's status; ``values`` are key/value pairs, values formatted with ``str()`` when built."""

    level: Level
    name: str
    message: str
    hardware_id: str = ""
    values: Mapping[str, Any] = field(default_factory=dict)


def _level(value: Any, name: str) -> Level:
    """A level from an int (rosbags) or a 1-byte ``bytes`` (rclpy)."""
    level = uint_field(value[0] if isinstance(value, bytes) and len(value) == 1 else value, name, bits=8)
    if level > max(Level):
        raise MalformedMessage(f"{name} = {value!r} is not a diagnostic level {[lv.value for lv in Level]}")
    return Level(level)


def diagnostic_array(statuses: Sequence[DiagStatus], *, stamp_ns: int, types: MessageTypes) -> Any:
    """``DiagStatus`` records -> ``diagnostic_msgs/DiagnosticArray`` (header frame_id empty)."""
    msgs = []
    for i, s in enumerate(statuses):
        values = [types.make("diagnostic_msgs/msg/KeyValue", key=str_field(k, f"statuses[{i}].values key"),
                             value=str(v)) for k, v in s.values.items()]
        msgs.append(types.make("diagnostic_msgs/msg/DiagnosticStatus",
                               level=types.byte(_level(s.level, f"statuses[{i}].level")),
                               name=str_field(s.name, f"statuses[{i}].name"),
                               message=str_field(s.message, f"statuses[{i}].message"),
                               hardware_id=str_field(s.hardware_id, f"statuses[{i}].hardware_id"), values=values))
    return types.make("diagnostic_msgs/msg/DiagnosticArray",
                      header=make_header(stamp_ns=stamp_ns, frame_id="", types=types), status=msgs)


def diagnostic_array_to_statuses(msg: Any) -> list[DiagStatus]:
    """``diagnostic_msgs/DiagnosticArray`` -> ``DiagStatus`` records (values as strings)."""
    return [DiagStatus(level=_level(s.level, f"status[{i}].level"), name=str_field(s.name, f"status[{i}].name"),
                       message=str_field(s.message, f"status[{i}].message"),
                       hardware_id=str_field(s.hardware_id, f"status[{i}].hardware_id"),
                       values={str_field(kv.key, f"status[{i}].key"): str_field(kv.value, f"status[{i}].value")
                               for kv in s.values})
            for i, s in enumerate(msg.status)]
