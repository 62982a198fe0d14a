"""What the two ``FF AA`` stepper families share: framing, the direction byte, reply shapes.

The project stepper (doc 000, 11-byte requests) and the quad stepper (doc 001, 9-byte
requests) come from one vendor and frame alike::

    request  FF AA <body> CS     CS = low 8 bits of the sum of every byte before it
    reply    FF AA r2 r3 r4 r5   6 bytes, no length and no checksum

Only the body size differs (8 bytes b2..b9, or 6 bytes b2..b7).  Both families' command
classes use one set of hooks: ``CMD`` (the command byte b3 of a motor command),
``body()`` (the request bytes between the header and the checksum) and ``params()``
(the parameter bytes of a motor command).  Sans-I/O.
"""

from __future__ import annotations

import enum

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import FF_AA, FrameShape, check_choice, sum8

__all__ = [
    "FF_AA",
    "REPLY_SIZE",
    "RotationDirection",
    "check_direction",
    "fits",
    "frame_request",
    "reply_shape",
    "request_is_valid",
]

#: Every ordinary reply of both families: ``FF AA r2 r3 r4 r5`` (doc 000 A.2, doc 001).
REPLY_SIZE = 6


class RotationDirection(enum.IntEnum):
    """The direction byte of command 04 in both families: 0 forward (正转), 1 reverse (反转)
    (doc 000 A.4, doc 001 section 四)."""

    FORWARD = 0
    REVERSE = 1


def check_direction(value: object) -> RotationDirection:
    """Validate a direction given as the enum or as its byte value 0/1."""
    checked = check_choice("direction", value, tuple(RotationDirection), "0 forward, 1 reverse")
    return RotationDirection(checked)


def frame_request(body: bytes, body_size: int, field: str, message: str | None = None) -> bytes:
    """Return ``FF AA body CS`` after checking ``body`` is ``body_size`` bytes.

    Raises:
        LocalProtocolError: naming ``field``, the size given and the size allowed
            (``message`` overrides the wording).
    """
    data = bytes(body)
    if len(data) != body_size:
        raise LocalProtocolError(
            message or f"{field} must be {body_size} bytes, got {len(data)}",
            field=field,
            value=data,
        )
    frame = FF_AA + data
    return frame + bytes((sum8(frame),))


def request_is_valid(raw: bytes | bytearray | memoryview, size: int) -> bool:
    """Return True if ``raw`` is a complete ``size``-byte request: header and checksum right
    (the command itself is not checked)."""
    data = bytes(raw)
    return len(data) == size and data[:2] == FF_AA and sum8(data[: size - 1]) == data[size - 1]


def reply_shape(*r2_to_r5: int | frozenset[int] | None, length: int = REPLY_SIZE) -> FrameShape:
    """The shape ``FF AA r2 r3 r4 r5`` (``None`` = any byte, a set = any of those)."""
    return FrameShape.exact(length, *FF_AA, *r2_to_r5)


def fits(shape: FrameShape, raw: bytes | bytearray | memoryview) -> bool:
    """A complete frame fits ``shape``: the right length and every byte allowed."""
    return len(raw) == shape.length and shape.matches(raw)
