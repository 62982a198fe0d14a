"""One tick of a streamer: which streams it serves, with which targets, and its counts.

Pure (no asyncio, no clock): the streamer (``motorbus.streams``) hands in the time and
the bus's state.  ``plan_tick`` calls the streams' target sources and never awaits:
what must be awaited (an async source, a gap to recover from, a stream whose targets
ran out or whose source failed) is left in ``Tick.later`` for the streamer's task.  A
tick of plain sources (a list, an iterator, a function) is therefore planned, sent and
counted from the timer callback of the tick before it, without a task turn.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from motorbus.streaming.model import GAP_TICKS, LATE_AFTER_S
from motorbus.streaming.targets import Pending, Targets, ramp_step

if TYPE_CHECKING:
    from motorbus.streaming.stream import Stream

__all__ = [
    "AWAIT",
    "COALESCE_WINDOW_S",
    "ENDED",
    "FAILED",
    "GAP",
    "STOPPED",
    "Handed",
    "Tick",
    "abandon",
    "accept",
    "plan_tick",
    "record_sent",
    "record_unsent",
]

#: Ticks within this of each other are served together (and coalesced).
COALESCE_WINDOW_S = 200e-6
#: ``plan_tick``'s ``stopped`` when nothing was stopped.
_NONE_STOPPED: Mapping[str, object] = MappingProxyType({})

#: What ``Tick.later`` asks of the task, for one stream: recover from a gap (the cause),
GAP = "gap"
#: end it with the error its source raised,
FAILED = "failed"
#: end it normally (its targets ran out),
ENDED = "ended"
#: or await its targets (a ``Pending``) and then serve it,
AWAIT = "await"
#: or end it: one of its actuators was stopped (a pause or an e-stop, ``Lease.stopped``).
STOPPED = "stopped"


class Tick:
    """The streams one deadline serves and what is left to do for it."""

    __slots__ = ("deadline", "feedback", "later", "polls", "prepared", "served")

    def __init__(self, deadline: float) -> None:
        self.deadline = deadline
        #: Streams with targets this tick (``Stream.last_targets``), in order.
        self.served: list[Stream] = []
        #: The 0x20 round trips of feedback streams: (stream, id, position).
        self.feedback: list[tuple[Stream, int, int]] = []
        #: Whether a served stream polls statuses after the tick (``poll_status``).
        self.polls = False
        #: What the task must await before the tick is sent: (stream, kind, value).
        self.later: list[tuple[Stream, str, Any]] = []
        #: The tick's frames as bus jobs, once prepared (``Streamer``); None before.
        self.prepared: list[Any] | None = None


class Handed:
    """What ``Streamer._fire`` hands its task: the ``tick`` it wrote (its ``jobs``, when
    the first left if at once, or the ``error`` that refused it) for the task to finish;
    or, ``tick`` None, having served the ticks to the end, the one it planned and did
    not send (``ahead``, None if it planned none)."""

    __slots__ = ("ahead", "error", "jobs", "sent_at", "tick")

    def __init__(
        self,
        tick: Tick | None,
        jobs: Sequence[Any] = (),
        sent_at: float | None = None,
        error: Exception | None = None,
        *,
        ahead: Tick | None = None,
    ) -> None:
        self.tick, self.jobs, self.sent_at = tick, jobs, sent_at
        self.error, self.ahead = error, ahead


def plan_tick(
    streams: Sequence[Stream],
    deadline: float,
    now: float,
    *,
    bus_up: bool,
    disconnects: int,
    stopped: Mapping[str, object] = _NONE_STOPPED,
) -> Tick:
    """Plan the tick at ``deadline`` of the ``streams`` due then (within
    ``COALESCE_WINDOW_S``), at ``now``: move each on to its next slot (skipping, never
    bursting, the slots already past), and take its targets.

    ``bus_up``: the bus is open (else the grid runs on and the ticks are skipped);
    ``disconnects``: the bus's outage count (a stream that has not seen it has a gap);
    ``stopped``: the devices stopped while the streams' lease held them
    (``Lease.stopped``): a stream driving one of them ends, with no target after the stop.
    """
    tick = Tick(deadline)
    window = deadline + COALESCE_WINDOW_S
    for s in streams:
        k = s.next_tick
        period = s.period
        if s.origin + k * period > window:
            continue  # not due this tick
        behind = int((now - (s.origin + k * period)) // period)
        if behind >= 1:  # overrun: skip to the current slot instead of bursting
            s.stats.skipped += behind
            k += behind
        s.next_tick = k + 1
        if not bus_up:  # the port is gone: the grid runs on, the ticks are skipped
            s.stats.skipped += 1
            continue
        if stopped and not s.stopping and not s.keys.isdisjoint(stopped):
            tick.later.append((s, STOPPED, None))  # (its ``sending`` is False from the stop)
            continue
        if not s.sending:
            continue
        if disconnects != s.disconnects_seen or behind >= GAP_TICKS:
            s.stats.skipped += 1  # this tick goes to reading the positions
            tick.later.append((s, GAP, "outage" if disconnects != s.disconnects_seen else "behind"))
            continue  # the ramp (or nothing, after a stop) starts next tick
        try:
            targets = s.source.fetch(k * period, s.statuses, k - s.index_base)
        except Exception as err:  # the user's target source failed: the task ends it
            tick.later.append((s, FAILED, err))
            continue
        if targets is None:  # a normal end: still a safe one (the task's)
            tick.later.append((s, ENDED, None))
        elif isinstance(targets, Pending):
            tick.later.append((s, AWAIT, targets))
        else:
            accept(tick, s, targets)
    return tick


def accept(tick: Tick, s: Stream, targets: Targets) -> None:
    """Serve ``s`` in ``tick`` with ``targets`` (ramped, while it ramps after a gap)."""
    if s.ramp is not None:
        targets = ramp_step(s.ramp, targets, s.max_speed * s.period)
        if not s.ramp:
            s.ramp = None  # every actuator is back on the trajectory
    s.skipped_mark = s.stats.skipped
    s.last_targets.update(targets)
    tick.served.append(s)
    if s.poll_status:
        tick.polls = True
    if s.feedback:
        tick.feedback.extend([(s, i, p) for i, p in targets.items()])


def record_sent(tick: Tick, sent_at: float, slipped: bool, frames: int) -> None:
    """Count a tick whose first frame went out at ``sent_at`` (``slipped``: it could not
    be written at the deadline itself), of ``frames`` broadcast frames, in each served
    stream's statistics (a feedback stream counts its own frames)."""
    for s in tick.served:
        if not s.feedback:
            s.stats.frames += frames
        lateness = s.origin + (s.next_tick - 1) * s.period
        lateness = sent_at - lateness if sent_at > lateness else 0.0
        s.stats.ticks += 1
        s.stats.jitter.record(lateness)
        if slipped:
            s.stats.slipped += 1
        if lateness > LATE_AFTER_S:
            s.stats.late += 1


def record_unsent(tick: Tick) -> None:
    """Count a tick whose frames were refused (the port away, the bus closing)."""
    for s in tick.served:
        if s.sending:
            s.stats.skipped += 1


def abandon(tick: Tick) -> None:
    """Close what ``tick`` left to await and never will be (its task was cancelled): a
    coroutine a target function returned would otherwise warn that it was never awaited."""
    later, tick.later = tick.later, []
    for _, kind, value in later:
        close = getattr(value.awaitable, "close", None) if kind == AWAIT else None
        if close is not None:
            close()
