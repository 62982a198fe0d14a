"""What the reassembler hands out, and the frame sizes it cuts by.

* :class:`Frame`, :class:`Discarded` and ``Item`` are the items
  ``Reassembler.feed`` returns (``ProjectFinishedMarker``, the ``EE DD`` event, lives in
  ``protocol/base.py``); :class:`ReassemblerStats` counts them.
* The sizes below are the facts of each family's framing that the reassembler relies on
  (docs/protocols.md A2-01, doc 000 A.2/A.5, doc 001 B.2).

The reassembler itself is ``protocol/reassembler.py`` (walking the stream) and
``protocol/frame_judge.py`` (what lies at a position in it).  Pure data, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

from motorbus.protocol.base import Direction, Family, ProjectFinishedMarker

__all__ = [
    "LA_MAX_FRAME",
    "LA_MIN_LEN",
    "PROJECT_DUMP_SIZE",
    "PROJECT_REQUEST_SIZE",
    "QUAD_REQUEST_SIZE",
    "STEPPER_REPLY_SIZE",
    "Discarded",
    "Frame",
    "Item",
    "ReassemblerStats",
]

#: Longest LA frame: the Len byte is at most 255 and a frame is Len + 5 bytes (A2-01).
LA_MAX_FRAME = 255 + 5
#: Smallest valid LA Len: CMD and IDX with no data (a read request, Len 3, has one data byte;
#: a Len of 2 is the least a frame can say about itself).
LA_MIN_LEN = 2
#: The project stepper's parameter dump answering 0x3E (doc 000 A.5).
PROJECT_DUMP_SIZE = 226
#: Every stepper reply but the dump is 6 bytes (doc 000 A.2, doc 001 B.2).
STEPPER_REPLY_SIZE = 6
PROJECT_REQUEST_SIZE = 11  # doc 000 A.2
QUAD_REQUEST_SIZE = 9  # doc 001 B.2


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
