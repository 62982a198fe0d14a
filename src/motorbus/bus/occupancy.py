"""How long a frame, and the reply it may get, holds the bus: the one place that says.

Pure arithmetic (numbers in, numbers out; no asyncio, no clock).  Every part of
motorbus that needs a frame's cost asks here: the bus for a reply's deadline, its
spacing and whether a request fits before a reserved stream tick; streams for the cost
of a tick and whether a poll fits before the next one; scan for its per-ID budget; the
adapter check for the slack a reply has; and the tools built on top (``motorbus
doctor``'s cycle budget, the test rig).

The terms, all in seconds, for a request of ``request_bytes`` on a bus at ``baud``:

* ``write``: the request's own wire time (10 bits a byte: 8N1);
* ``reply_wire``: the wire time of its longest possible reply (0 if it expects none);
* ``turnaround``: the family's worst-case device turnaround, request end to reply start
  (LA: 800 us, LA manual 3.4.1);
* ``margin``: the host-latency allowance added to every deadline (the bus's
  ``host_margin``);
* ``spacing``: the minimum start-to-start spacing of two frames (1 ms, LA manual 3.4.2).

From them:

* ``budget``: from the completed write to the reply's deadline,
  ``write + reply_wire + turnaround + margin`` (0 if no reply is expected);
* ``after_write``: from the completed write to the earliest next write,
  ``max(spacing, write)``;
* ``answered``: what the frame holds when the device answers within its turnaround,
  ``max(spacing, write + reply_wire + turnaround)`` (the host margin only matters when
  a reply is missing);
* ``worst``: what it may hold at most, its reply's whole budget run out,
  ``max(spacing, write, budget)``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from motorbus.protocol.base import Command, Family, wire_time

__all__ = [
    "BusTiming",
    "Occupancy",
    "OccupancyTable",
    "answer_window",
    "command_occupancy",
    "occupancy",
    "reply_slack",
]


@dataclass(frozen=True, slots=True)
class BusTiming:
    """The facts about one bus that occupancy depends on (durations in seconds)."""

    baud: int
    min_spacing: float
    host_margin: float
    turnaround: Mapping[Family, float]


@dataclass(frozen=True, slots=True)
class Occupancy:
    """The bus time of one frame and its reply (seconds); see the module docstring."""

    write: float
    reply_wire: float
    turnaround: float
    margin: float
    spacing: float
    expects_reply: bool
    #: From the completed write to the reply's deadline; 0 without a reply.  (Worked
    #: out once, as ``after_write``: a bus reads both for every frame it queues.)
    budget: float = field(init=False, repr=False, compare=False)
    #: From the completed write to the earliest next write.
    after_write: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        budget = self.write + self.reply_wire + self.turnaround + self.margin
        object.__setattr__(self, "budget", budget if self.expects_reply else 0.0)
        object.__setattr__(self, "after_write", max(self.spacing, self.write))

    @property
    def answered(self) -> float:
        """Bus time when the device answers within its turnaround."""
        busy = self.write
        if self.expects_reply:
            busy += self.reply_wire + self.turnaround
        return max(self.spacing, busy)

    @property
    def worst(self) -> float:
        """Bus time at most: the reply's whole budget run out."""
        return max(self.spacing, self.write, self.budget)


def occupancy(
    timing: BusTiming, family: Family, *, request_bytes: int, reply_bytes: int = 0
) -> Occupancy:
    """The occupancy of a ``request_bytes`` frame of ``family`` whose longest reply is
    ``reply_bytes`` long (0: it expects no reply)."""
    expects = reply_bytes > 0
    return Occupancy(
        write=wire_time(request_bytes, timing.baud),
        reply_wire=wire_time(reply_bytes, timing.baud) if expects else 0.0,
        turnaround=timing.turnaround[family] if expects else 0.0,
        margin=timing.host_margin if expects else 0.0,
        spacing=timing.min_spacing,
        expects_reply=expects,
    )


def _shape(cmd: Command[object], request_bytes: int | None) -> tuple[Family, int, int]:
    """What ``cmd``'s occupancy depends on: family, request bytes, longest reply bytes."""
    lengths = cmd.reply_lengths()
    return (
        cmd.family,
        len(cmd.encode()) if request_bytes is None else request_bytes,
        max(lengths) if lengths else 0,
    )


def command_occupancy(
    timing: BusTiming, cmd: Command[object], request_bytes: int | None = None
) -> Occupancy:
    """The occupancy of ``cmd``; ``request_bytes`` saves re-encoding when the caller
    has the bytes already."""
    family, request, reply = _shape(cmd, request_bytes)
    return occupancy(timing, family, request_bytes=request, reply_bytes=reply)


class OccupancyTable:
    """``command_occupancy`` on one bus's timing, remembered per shape of frame (family,
    request and reply sizes): a bus asks for every frame it queues, and a bus sends few
    shapes."""

    #: Shapes remembered at most (a bus with more starts over: far beyond the manuals).
    SHAPES_MAX = 1024

    def __init__(self, timing: BusTiming) -> None:
        self.timing = timing
        self._known: dict[tuple[Family, int, int], Occupancy] = {}

    def of(self, cmd: Command[object], request_bytes: int | None = None) -> Occupancy:
        """The occupancy of ``cmd`` (as ``command_occupancy``)."""
        shape = _shape(cmd, request_bytes)
        known = self._known.get(shape)
        if known is None:
            if len(self._known) >= self.SHAPES_MAX:
                self._known.clear()
            family, request, reply = shape
            known = self._known[shape] = occupancy(
                self.timing, family, request_bytes=request, reply_bytes=reply
            )
        return known


def reply_slack(timing: BusTiming, families: Iterable[Family] | None = None) -> float:
    """How long a reply may be held beyond its own wire time and still meet its deadline
    (``Occupancy.budget``'s terms): the shortest turnaround of ``families`` (every
    family ``timing`` knows if None) plus the host margin.  What a USB adapter's
    latency timer must stay under."""
    chosen = (
        timing.turnaround.values() if families is None else [timing.turnaround[f] for f in families]
    )
    return min(chosen) + timing.host_margin


def answer_window(timing: BusTiming, families: Iterable[Family], reply_bytes: int) -> float:
    """From the end of a request until a device of ``families`` has finished answering
    with ``reply_bytes`` bytes at the latest: the longest turnaround plus the reply's
    wire time.  Until then a half-duplex line may still be busy (the guard waits this
    long for a quiet line before each safe frame)."""
    turnaround = max((timing.turnaround[f] for f in families), default=0.0)
    return turnaround + wire_time(reply_bytes, timing.baud)
