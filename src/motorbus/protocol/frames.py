"""What the reassembler hands out.

:class:`Frame`, :class:`Discarded` and ``Item`` are the items ``Reassembler.feed`` returns
(``ProjectFinishedMarker``, the ``EE DD`` event, lives in ``protocol/base.py``);
:class:`ReassemblerStats` counts them.  The frame sizes and command bytes the reassembler
cuts by are the rulebook's (``protocol/rulebook.py``); they stay importable from here.
Pure data, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

from motorbus.protocol.base import Direction, Family, ProjectFinishedMarker
from motorbus.protocol.rulebook import (
    LA_ANY_LENGTH_COMMANDS,
    LA_COMMANDS,
    LA_MAX_FRAME,
    LA_MAX_LEN,
    LA_MIN_LEN,
    LA_SHORT_MAX_LEN,
    PROJECT_B9_MAX,
    PROJECT_DUMP_SIZE,
    PROJECT_REQUEST_SIZE,
    QUAD_ADDRESSES,
    QUAD_REQUEST_SIZE,
    STEPPER_B3_MAX,
    STEPPER_FREE_B3_OPCODE,
    STEPPER_REPLY_SIZE,
)

__all__ = [
    "LA_ANY_LENGTH_COMMANDS",
    "LA_COMMANDS",
    "LA_MAX_FRAME",
    "LA_MAX_LEN",
    "LA_MIN_LEN",
    "LA_SHORT_MAX_LEN",
    "PROJECT_B9_MAX",
    "PROJECT_DUMP_SIZE",
    "PROJECT_REQUEST_SIZE",
    "QUAD_ADDRESSES",
    "QUAD_REQUEST_SIZE",
    "STEPPER_B3_MAX",
    "STEPPER_FREE_B3_OPCODE",
    "STEPPER_REPLY_SIZE",
    "Discarded",
    "Frame",
    "Item",
    "ReassemblerStats",
]


class Frame(NamedTuple):
    """A complete frame cut from the stream.

    A NamedTuple rather than a dataclass: it is immutable all the same, and the
    reassembler builds one per frame on the hot path, where a tuple is ~3x cheaper.
    """

    family: Family
    direction: Direction
    raw: bytes


class Discarded(NamedTuple):
    """A run of bytes that belonged to no frame, and why they were dropped."""

    raw: bytes
    reason: str


Item = Frame | ProjectFinishedMarker | Discarded


@dataclass(slots=True)
class ReassemblerStats:
    """Counters; every byte fed ends up in a frame, an event, a discard, or the buffer."""

    frames: int = 0
    events: int = 0
    discarded_bytes: int = 0
    #: Number of discarded runs: times the stream had to be resynchronised.
    resyncs: int = 0
    #: Discarded bytes by reason.
    by_reason: dict[str, int] = field(default_factory=dict)
