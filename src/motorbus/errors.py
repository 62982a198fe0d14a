"""The motorbus exception tree.

``MotorbusError`` is the root.  Two families follow h11's split:

* ``LocalProtocolError``: *you* asked for something the protocol cannot express
  (a value out of range, a wrong type).  It is also a ``ValueError`` so that
  ordinary ``except ValueError`` code keeps working.  Nothing is ever written to a
  bus when one of these is raised.
* ``RemoteProtocolError``: the *peer* sent bytes that do not make sense for the
  request that was made.  It carries the raw frame.

The bus adds timeouts, closed ports and device faults on top.
"""

from __future__ import annotations

__all__ = [
    "BusClosedError",
    "DeviceFaultError",
    "LocalProtocolError",
    "MotorbusError",
    "NotSentError",
    "RemoteProtocolError",
    "ReplyTimeoutError",
]


class MotorbusError(Exception):
    """Root of every error motorbus raises on purpose."""


class LocalProtocolError(MotorbusError, ValueError):
    """A request could not be built: a field is out of range or of the wrong type.

    The message always names the field, the value given and the allowed range.
    """

    def __init__(self, message: str, *, field: str | None = None, value: object = None) -> None:
        super().__init__(message)
        self.field = field
        self.value = value


class RemoteProtocolError(MotorbusError):
    """A device sent a frame that does not fit the request it answers."""

    def __init__(self, message: str, *, raw: bytes = b"") -> None:
        super().__init__(message)
        self.raw = raw


class ReplyTimeoutError(MotorbusError, TimeoutError):
    """No matching reply arrived before the request's deadline."""


class NotSentError(MotorbusError):
    """A request could not start by its ``start_by`` time and was dropped; nothing was sent."""


class BusClosedError(MotorbusError, ConnectionError):
    """The bus (or its port) is closed or was lost while a request was pending."""


class DeviceFaultError(MotorbusError):
    """A device reported a fault that prevents the requested action."""

    def __init__(self, message: str, *, raw: bytes = b"") -> None:
        super().__init__(message)
        self.raw = raw
