"""What the reassembler hands out, and the frame sizes and command bytes it cuts by.

* :class:`Frame`, :class:`Discarded` and ``Item`` are the items
  ``Reassembler.feed`` returns (``ProjectFinishedMarker``, the ``EE DD`` event, lives in
  ``protocol/base.py``); :class:`ReassemblerStats` counts them.
* The sizes and command bytes below are the facts of each family's framing that the
  reassembler relies on (docs/protocols.md A2-01, C.3, doc 000 A.2/A.4/A.5, doc 001 B.2/B.3).

The reassembler itself is ``protocol/reassembler.py`` (walking the stream),
``protocol/frame_judge.py`` (what lies at a position in it) and
``protocol/candidates.py`` (where a frame may start).  Pure data, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

from motorbus.protocol.base import Direction, Family, ProjectFinishedMarker

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

#: The CMD byte (byte 4) of every LA frame is one of the nine command codes of doc 002
#: (docs/protocols.md C.3); a reply carries 01 (read), 02 (write ack), 04 (status) or
#: echoes its request's (A2-04).  The reassembler takes no LA frame with another CMD.
LA_COMMANDS = frozenset((0x01, 0x02, 0x03, 0x04, 0x19, 0x20, 0x21, 0xF2, 0xF3))
#: Reads and writes (CMD 01, 02) carry up to 253 table bytes: Len up to 255 (A2-01) ...
LA_ANY_LENGTH_COMMANDS = frozenset((0x01, 0x02))
#: ... every other frame is at most a 15-entry broadcast, Len 1 + 3 x 15 = 0x2E (a status
#: is Len 0x11, a motion request 4, a control request 3; C.3, C.4).
LA_SHORT_MAX_LEN = 0x2E
#: Per CMD byte, the largest Len an LA frame with it has; -1 if no frame has that CMD.
LA_MAX_LEN = tuple(
    0xFF if cmd in LA_ANY_LENGTH_COMMANDS else LA_SHORT_MAX_LEN if cmd in LA_COMMANDS else -1
    for cmd in range(256)
)
#: Byte 3 of every ``FF AA`` request and 6-byte reply the manuals define is at most 0x0F:
#: a motor command 01..0F, a project 1..4, a step-loop start 0..10, a value 0..2, an I/O
#: command 0B/0C, or 00 (doc 000 A.4, doc 001 B.3) ...
STEPPER_B3_MAX = 0x0F
#: ... but for one request: the project stepper's 0x8E, whose byte 3 is the repeat count
#: 0..255 (its reply, ``8E P 00 00``, keeps the rule).
STEPPER_FREE_B3_OPCODE = 0x8E
#: Byte 9 of every project request is the step, 1..10, or 00 (doc 000 A.2, A.4).
PROJECT_B9_MAX = 0x0A
#: Byte 2 of every quad request is an address: motor 1..4, 0x09 all motors, 0x00 I/O
#: (the LEDs) or 0xBC save (doc 001 B.2).
QUAD_ADDRESSES = frozenset((0x00, 0x01, 0x02, 0x03, 0x04, 0x09, 0xBC))


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
