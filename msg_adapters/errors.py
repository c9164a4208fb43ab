"""Exception types of ``msg_adapters``; all are ``ValueError`` subclasses (via ``vi3_core.errors.DataError``)."""

from __future__ import annotations

from vi3_core.errors import DataError


class MalformedMessage(DataError):
    """A ROS message (or a value meant for one) breaks its layout: the text names the field and the values."""


class UnsupportedEncoding(MalformedMessage):
    """A well-formed message in an encoding or compression format that is not supported (the text names it and
    the supported ones)."""


class UnknownMessageType(DataError):
    """A ROS type name is not known to the message backend (typestore or ROS installation)."""


def drop_reason(kind: str, exc: Exception) -> str:
    """The drop reason of a ``kind`` message ("image", "imu", "camera_info", ...) that raised ``exc`` when decoded:
    ``<kind>_unsupported`` for an UnsupportedEncoding, else ``<kind>_malformed``."""
    return f"{kind}_unsupported" if isinstance(exc, UnsupportedEncoding) else f"{kind}_malformed"
