"""Whose frame is this: the bus's reply matching, without I/O.

Pure (no asyncio, no clock): the time a frame was seen and its offset in the received
stream are passed in, and the answer is a verdict.  ``BusEngine``
(``motorbus.bus.engine``) is the asyncio shell that feeds it frames from the
reassembler and acts on the verdict; table tests drive it with plain numbers
(tests/bus/test_matching.py).

What it remembers:

* the pending request (at most one: a request that expects a reply holds the bus);
* the requests that timed out in the last ``LATE_WINDOW_S``, to recognise their late
  answers;
* the "done" replies still to come (quad stepper run and LED commands), at most
  ``MAX_DONE_WATCHES``;
* from those, the checksum-less stepper reply shapes the reassembler may cut now
  (``on_shapes`` is told each time they change).

A frame is the pending request's reply by causality and shape: its first byte must sit
at or after the request's ``rx_mark`` (the stream offset when the request was handed to
the OS: a frame whose bytes were already buffered before the write is older traffic)
and ``Command.matches_reply`` must accept it.  It is accepted until the request's
deadline is *decided* (``timed_out``), not until the deadline's time: the shell decides
when its deadline callback runs, after reading whatever the OS already holds, so a reply
that was there when the bus looked is taken whichever callback a late loop runs first
(the loop, not the device, was late).  A reply that comes after the decision is the
timed-out request's late reply, and is never given to a later request: it either began
before that request's write, or a per-device late guard (``motorbus.bus.schedule``)
kept a same-device request from being sent while it could still arrive.
"""

from __future__ import annotations

import collections
import enum
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Generic, TypeVar

from motorbus.bus.schedule import Job
from motorbus.protocol.base import Command, Family, FrameShape, wire_time

__all__ = [
    "LATE_WINDOW_S",
    "MAX_DONE_WATCHES",
    "WIRE_FLOOR_FACTOR",
    "DoneWatch",
    "Matcher",
    "TimedOut",
    "Verdict",
    "wire_floor",
]

#: Quad stepper "done" replies awaited at once, at most: more outstanding runs than
#: this means done replies are being lost (four motors and the LEDs fit easily).
MAX_DONE_WATCHES = 16
#: How long a timed-out request is remembered to recognise its late reply.
LATE_WINDOW_S = 2.0
#: With ``wire_floor=True`` (a real UART that paces bytes at the baud), a reply cannot
#: complete before its request and itself have crossed the wire; 10 % is allowed for
#: baud-rate tolerance before a frame is called "too early to be ours".  Off by default:
#: ptys, USB-CDC devices and TCP bridges deliver far sooner than the wire would.
WIRE_FLOOR_FACTOR = 0.9


class Verdict(enum.Enum):
    """What a frame is, for the bus."""

    ACCEPTED = "accepted"  # the pending request's reply (its deadline not yet decided)
    EARLY = "early"  # sooner than the wire allows (wire_floor=True only): refused
    DONE = "done"  # a watched "done" reply (the watch is given and forgotten)
    LATE = "late"  # the answer to a request that already timed out
    UNEXPECTED = "unexpected"  # nobody's


@dataclass(slots=True)
class TimedOut:
    """A request whose deadline ran out, remembered to recognise its late reply."""

    cmd: Command[object]
    key: str
    until: float  # remembered until then
    deadline: float  # the deadline it missed


@dataclass(slots=True)
class DoneWatch:
    """A quad stepper command whose "done" reply is still to come."""

    shapes: tuple[FrameShape, ...]
    kind: str  # "led" or "run"
    led: int | None
    cmd: Command[object]

    @classmethod
    def of(cls, cmd: Command[object]) -> DoneWatch:
        """The watch for ``cmd``'s done reply (``cmd.done_shapes()`` is not empty)."""
        led = getattr(cmd, "led", None)
        return cls(cmd.done_shapes(), "led" if led is not None else "run", led, cmd)


#: A verdict and what it concerns: the watch (DONE) or the timed-out request (LATE).
Match = tuple[Verdict, "DoneWatch | TimedOut | None"]

_ACCEPTED: Match = (Verdict.ACCEPTED, None)
_EARLY: Match = (Verdict.EARLY, None)
_UNEXPECTED: Match = (Verdict.UNEXPECTED, None)


def wire_floor(written: float, request_size: int, reply_size: int, baud: int) -> float:
    """The earliest a reply of ``reply_size`` bytes can complete on a link that paces
    bytes at ``baud``, for a request of ``request_size`` bytes whose write began at
    ``written`` (less ``WIRE_FLOOR_FACTOR``'s tolerance)."""
    return written + WIRE_FLOOR_FACTOR * (
        wire_time(request_size, baud) + wire_time(reply_size, baud)
    )


def _no_shapes(shapes: tuple[FrameShape, ...]) -> None:
    pass


#: The job record a shell keeps (``Job`` or a subclass of it).
J = TypeVar("J", bound=Job)


class Matcher(Generic[J]):
    """Reply matching for one bus (see the module docstring).

    Args:
        families: the device families on the bus (LA frames carry their own length and
            checksum: a bus of LAs only tells the reassembler no shapes).
        wire_floor: refuse (``EARLY``) a pending request's reply seen before its job's
            ``earliest``.
        on_shapes: told the reply shapes the reassembler may cut, each time they change.
    """

    __slots__ = (
        "_stepper",
        "done_watches",
        "expected",
        "on_shapes",
        "pending",
        "timeouts",
        "wire_floor",
    )

    def __init__(
        self,
        families: Iterable[Family],
        *,
        wire_floor: bool = False,
        on_shapes: Callable[[tuple[FrameShape, ...]], None] = _no_shapes,
    ) -> None:
        self._stepper = set(families) != {Family.LA}
        self.wire_floor = wire_floor
        self.on_shapes = on_shapes
        self.pending: J | None = None
        self.timeouts: collections.deque[TimedOut] = collections.deque()
        self.done_watches: list[DoneWatch] = []
        self.expected: tuple[FrameShape, ...] | None = None

    # -- what the bus awaits ---------------------------------------------------------

    def sent(self, job: J) -> None:
        """``job`` is about to be written and awaits its reply."""
        self.pending = job
        if self._stepper:  # (an LA bus cuts every frame by its checksum: no shapes)
            self.update_shapes()

    def written(self, job: J, before: float, after: float, baud: int) -> None:
        """``job`` (``sent``) was written: the call began at ``before`` and returned at
        ``after``.  Its deadline counts from the completed write, ``after + timeout``,
        never from earlier; with ``wire_floor``, its reply cannot complete before
        ``earliest`` (counted from the start of the write)."""
        if self.wire_floor:
            job.earliest = wire_floor(before, len(job.raw), min(job.cmd.reply_lengths()), baud)
        job.deadline = after + job.timeout

    def release(self, job: J) -> bool:
        """``job`` no longer holds the bus (answered, failed or to be retried); False
        if it was not the pending request."""
        if self.pending is not job:
            return False
        self.pending = None
        if self._stepper:
            self.update_shapes()
        return True

    def timed_out(self, job: J, now: float) -> None:
        """``job``'s deadline ran out (decided at ``now``): remember it for
        ``LATE_WINDOW_S`` to recognise its late reply.  It still holds the bus until
        ``release``."""
        self.timeouts.append(TimedOut(job.cmd, job.key, now + LATE_WINDOW_S, job.deadline))

    def watch_done(self, cmd: Command[object]) -> bool:
        """Await ``cmd``'s "done" reply, keeping at most ``MAX_DONE_WATCHES``.

        A done reply that is lost on the line would otherwise be awaited forever, and
        the list (and the reply shapes the reassembler is given) would grow with every
        run.  Past the bound the oldest is forgotten: returns True then (to be counted).
        """
        watches = self.done_watches
        watches.append(DoneWatch.of(cmd))
        dropped = len(watches) > MAX_DONE_WATCHES
        if dropped:
            del watches[0]
        self.update_shapes()
        return dropped

    def update_shapes(self, *, force: bool = False) -> None:
        """Tell ``on_shapes`` which checksum-less stepper replies may be cut now, if
        that changed (``force``: a new reassembler, tell it anyway).

        Exactly what the bus awaits: the pending request's replies (and its "done"
        reply, which may follow its ack in the same read), the "done" replies still to
        come, and the replies of requests that timed out recently (so that
        their late answers are recognised and counted).  Nothing else: stray ``FF AA``
        bytes are then discarded, never taken for a frame.
        """
        if force:
            self.expected = None
        if not self._stepper:
            return
        shapes: list[FrameShape] = []
        job = self.pending
        if job is not None:
            shapes.extend(job.cmd.reply_shapes())
            # Its "done" reply too: a short run's done can come in the same read as the
            # ack, and the reassembler cuts a read with the shapes expected when it came
            # (the watch itself starts when the ack is taken, ``watch_done``).
            shapes.extend(job.cmd.done_shapes())
        for watch in self.done_watches:
            shapes.extend(watch.shapes)
        for t in self.timeouts:
            shapes.extend(t.cmd.reply_shapes())
        expected = tuple(dict.fromkeys(shapes))
        if expected != self.expected:
            self.expected = expected
            self.on_shapes(expected)

    # -- a frame -----------------------------------------------------------------------

    def classify(self, raw: bytes, start: int, now: float) -> Match:
        """What the complete frame ``raw``, whose first byte is at stream offset
        ``start``, seen at ``now``, is.

        ``DONE`` forgets the watch it returns; ``LATE`` returns the timed-out request.
        The pending request's reply is ``ACCEPTED`` even past its deadline: a request
        is pending until the shell decides its deadline (``timed_out``, then ``release``),
        which it does after reading what the OS holds (module docstring).
        """
        job = self.pending
        if job is not None and start >= job.rx_mark and job.cmd.matches_reply(raw):
            if self.wire_floor and now < job.earliest:
                return _EARLY
            return _ACCEPTED
        watch = self._match_done(raw)
        if watch is not None:
            return (Verdict.DONE, watch)
        late = self._match_late(raw, now)
        if late is not None:
            return (Verdict.LATE, late)
        return _UNEXPECTED

    def _match_done(self, raw: bytes) -> DoneWatch | None:
        for i, watch in enumerate(self.done_watches):
            if watch.cmd.matches_done(raw):
                del self.done_watches[i]
                self.update_shapes()
                return watch
        return None

    def _match_late(self, raw: bytes, now: float) -> TimedOut | None:
        """The timed-out request ``raw`` answers, newest first, if any is remembered."""
        timeouts = self.timeouts
        if timeouts and timeouts[0].until < now:
            while timeouts and timeouts[0].until < now:
                timeouts.popleft()
            self.update_shapes()
        for t in reversed(timeouts):
            if t.cmd.matches_reply(raw):
                return t
        return None
