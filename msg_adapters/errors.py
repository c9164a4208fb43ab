"""Exception types of ``msg_adapters``; both are ``ValueError`` subclasses (via ``vi3_core.errors.DataError``)."""

from __future__ import annotations

from vi3_core.errors import DataError


class MalformedMessage(DataError):
    """A ROS message (or a value meant for one) breaks its layout: the text names the field and the values."""


class UnknownMessageType(DataError):
    """A ROS type name is not known to the message backend (typestore or ROS installation)."""
