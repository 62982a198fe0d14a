"""Wire-time arithmetic for simulated serial links.

A pseudo-terminal or an in-memory link delivers bytes instantly, whatever the baud
rate (docs/platform.md section 3), so the simulator computes how long bytes would have
taken on a real UART and delivers them then.
"""

from __future__ import annotations

from motorbus.errors import LocalProtocolError
from motorbus.protocol import base
from motorbus.protocol.base import BITS_PER_BYTE

__all__ = ["BITS_PER_BYTE", "byte_time", "wire_time"]


def _check_baud(baud: object) -> int:
    if isinstance(baud, bool) or not isinstance(baud, int) or baud <= 0:
        raise LocalProtocolError(
            f"baud must be a positive integer (bit/s), got {baud!r}", field="baud", value=baud
        )
    return baud


def byte_time(baud: int) -> float:
    """Return the seconds one 8N1 byte occupies on the wire at ``baud`` bit/s.

    Raises:
        LocalProtocolError: ``baud`` is not a positive integer.
    """
    return BITS_PER_BYTE / _check_baud(baud)


def wire_time(nbytes: int, baud: int) -> float:
    """Return the seconds ``nbytes`` back-to-back 8N1 bytes take at ``baud`` bit/s.

    Example: a 22-byte LA status reply at 921600 bit/s takes 22 * 10 / 921600 = 239 us.

    Raises:
        LocalProtocolError: ``nbytes`` is negative or ``baud`` is not a positive integer.
    """
    if isinstance(nbytes, bool) or not isinstance(nbytes, int) or nbytes < 0:
        raise LocalProtocolError(
            f"nbytes must be a non-negative integer, got {nbytes!r}", field="nbytes", value=nbytes
        )
    return base.wire_time(nbytes, _check_baud(baud))
