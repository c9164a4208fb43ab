"""Resolve ROS message classes by type name, for a rosbags typestore or for rclpy, and smooth over the
differences between the two backends in how array fields are stored.

Builders take a ``MessageTypes`` (keyword ``types=``) and construct every message with keyword arguments for all
fields, which both backends accept. Only the array and ``byte`` fields differ:

=====================  ===============================  ==================================
field type             rosbags dataclass                rclpy message
=====================  ===============================  ==================================
``uint8[]``            ``np.ndarray`` uint8             ``array.array('B')``
``float64[]``          ``np.ndarray`` float64           ``array.array('d')``
``float64[N]``         ``np.ndarray`` float64           ``np.ndarray`` float64
``byte``               ``int``                          ``bytes`` of length 1
=====================  ===============================  ==================================
"""

from __future__ import annotations

import abc
import array
import functools
import importlib
from collections.abc import Callable
from typing import Any

import numpy as np

from msg_adapters.errors import UnknownMessageType


def full_name(name: str) -> str:
    """``"sensor_msgs/Image"`` (ROS 1 style) or ``"sensor_msgs/msg/Image"`` -> ``"sensor_msgs/msg/Image"``; any other
    shape raises ``UnknownMessageType``."""
    parts = name.split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and all(parts):
        return name
    raise UnknownMessageType(f"message type name {name!r} is not 'package/Name' or 'package/msg/Name'")


class MessageTypes(abc.ABC):
    """Message classes by ROS type name plus the conversions of array fields that the backend expects.

    Build with :meth:`from_typestore` or :meth:`from_rclpy`; do not instantiate directly.
    """

    backend: str = ""

    def __init__(self, lookup: Callable[[str], type]) -> None:
        self._lookup = lookup
        self._classes: dict[str, type] = {}

    @classmethod
    def from_typestore(cls, typestore: Any) -> MessageTypes:
        """Resolver over a rosbags ``Typestore`` (pin ``Stores.ROS2_JAZZY``); keeps it as ``.typestore``."""
        return _RosbagsTypes(typestore)

    @classmethod
    def from_rclpy(cls) -> MessageTypes:
        """Resolver over the installed ROS 2 message packages: ``"pkg/msg/Name"`` is ``Name`` of the generated module
        ``pkg.msg``, imported on first use (what ``rosidl_runtime_py.utilities.get_message`` does, without that
        package, which no PyPI wheel provides)."""
        return _RclpyTypes(_generated_message)

    def get(self, name: str) -> type:
        """The message class of ``name`` ("sensor_msgs/msg/Image" or "sensor_msgs/Image"), cached."""
        full = full_name(name)
        cls = self._classes.get(full)
        if cls is None:
            try:
                cls = self._lookup(full)
            except (KeyError, AttributeError, ModuleNotFoundError, ValueError) as exc:
                raise UnknownMessageType(f"message type {full!r} is unknown to the {self.backend} backend") from exc
            self._classes[full] = cls
        return cls

    def make(self, name: str, /, **fields: Any) -> Any:
        """A message of type ``name`` from keyword fields (rosbags needs all of them)."""
        return self.get(name)(**fields)

    @abc.abstractmethod
    def uint8_seq(self, buf: np.ndarray | bytes) -> Any:
        """A ``uint8[]`` field value from a buffer (any dtype; its raw bytes in C order are used)."""

    @abc.abstractmethod
    def float64_seq(self, values: Any) -> Any:
        """A ``float64[]`` (unbounded sequence) field value from numbers."""

    @abc.abstractmethod
    def byte(self, value: int) -> Any:
        """A ``byte`` field value from an int in [0, 255]."""


class _RosbagsTypes(MessageTypes):
    backend = "rosbags"

    def __init__(self, typestore: Any) -> None:
        super().__init__(lambda full: typestore.types[full])
        self.typestore = typestore

    def uint8_seq(self, buf: np.ndarray | bytes) -> np.ndarray:
        if isinstance(buf, np.ndarray):
            return np.ascontiguousarray(buf).reshape(-1).view(np.uint8)
        return np.frombuffer(buf, dtype=np.uint8)

    def float64_seq(self, values: Any) -> np.ndarray:
        return np.array(values, dtype=np.float64).reshape(-1)

    def byte(self, value: int) -> int:
        return int(value)


def _generated_message(full: str) -> type:
    """The rclpy class of ``"pkg/msg/Name"`` from the package's generated Python module. ModuleNotFoundError only
    where the package is not installed; an installed one missing a module it imports is an ImportError."""
    package, _, name = full.split("/")
    try:
        module = importlib.import_module(f"{package}.msg")
    except ModuleNotFoundError as exc:
        if exc.name in (package, f"{package}.msg"):
            raise
        raise ImportError(f"{package}.msg is installed but cannot be imported: {exc}") from exc
    cls = getattr(module, name)
    if not isinstance(cls, type):
        raise AttributeError(f"{package}.msg.{name} is not a message class")
    return cls


class _RclpyTypes(MessageTypes):
    """Over the generated Python messages of the ROS 2 packages installed (PyPI wheels or a sourced ROS 2)."""

    backend = "rclpy"

    def uint8_seq(self, buf: np.ndarray | bytes) -> array.array:
        return array.array("B", np.ascontiguousarray(buf).tobytes() if isinstance(buf, np.ndarray) else bytes(buf))

    def float64_seq(self, values: Any) -> array.array:
        return array.array("d", np.asarray(values, dtype=np.float64).reshape(-1).tobytes())

    def byte(self, value: int) -> bytes:
        return bytes([int(value)])


@functools.cache
def jazzy_types() -> MessageTypes:
    """The cached resolver over the rosbags ROS 2 Jazzy typestore (for tests, replay and bag writing), with the one
    message the node may publish that Jazzy does not ship: PX4's VehicleOdometry (``msg_adapters.px4``)."""
    from rosbags.typesys import Stores, get_typestore

    from msg_adapters import px4

    typestore = get_typestore(Stores.ROS2_JAZZY)
    px4.register(typestore)
    return MessageTypes.from_typestore(typestore)
