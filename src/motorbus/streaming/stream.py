"""One running follow-mode stream: its targets, its state, and how it ends.

A :class:`Stream` is created by ``motorbus.streams.Streamer.follow`` and served by that
streamer's tick loop; this module holds the handle the program keeps (``stop``,
``wait``, ``pause``, ``set_targets``, ``gaps``) and what ending means: however it ends,
its safe action goes to its actuators once, unless it is ended with ``hold``.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
from collections.abc import Awaitable, Mapping, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Protocol

from motorbus.bus.bus import Bus, Priority
from motorbus.bus.events import BusEvent, Subscription
from motorbus.bus.leases import Lease
from motorbus.devices.la import InspireLA
from motorbus.errors import LocalProtocolError, MotorbusError, NotSentError, StreamEnded
from motorbus.lifecycle import deferred_interrupts
from motorbus.protocol import la
from motorbus.protocol.base import Command
from motorbus.streaming.model import (
    DEFAULT_MAX_SPEED,
    GapPolicy,
    SafeAction,
    StreamStats,
    hold_flag,
    while_sending,
)
from motorbus.streaming.targets import TargetAdapter, TargetSource

__all__ = [
    "Stream",
    "StreamGap",
    "StreamOwner",
    "actuator_group",
    "earliest_tick",
    "poll_statuses",
    "round_trips",
    "stop_together",
]

log = logging.getLogger("motorbus.streams")


def _stop_name(cmd: Command[object]) -> str:
    """``Control(3, PAUSE)`` as ``"PAUSE"``; another stop by its class's name."""
    action = getattr(cmd, "action", None)
    return action.name if isinstance(action, la.ControlAction) else type(cmd).__name__


class StreamOwner(Protocol):
    """What a stream needs of the streamer that serves it."""

    @property
    def bus(self) -> Bus: ...

    @property
    def lease(self) -> Lease | None:
        """The lease the stream's actuators are held by (its ``stopped`` ends it)."""

    def discard(self, stream: Stream) -> None:
        """Forget ``stream``: it has ended."""

    async def let_go(self, stream: Stream, *, hold: bool) -> None:
        """``stream`` ended: its actuators leave the streamer's lease."""


@dataclass(frozen=True, slots=True)
class StreamGap(BusEvent):
    """A stream had a gap: its targets stopped reaching its actuators for a while.

    Attributes:
        stream: the stream's ``number`` (``Stream.number``).
        ids: the stream's actuators.
        cause: ``"outage"`` (the bus lost its port and came back) or ``"behind"`` (the
            stream fell ``GAP_TICKS`` or more ticks behind).
        missed: ticks not sent since the last tick that was.
        positions: where the ramp starts (``"ramp"``): each actuator's reported
            position after an outage; after falling behind, the last target it was sent
            (read only if it had none).
        action: ``"ramp"`` (ramping from ``positions``) or ``"stop"`` (safe action
            applied, stream ended; also when a position could not be read).
    """

    stream: int
    ids: tuple[int, ...]
    cause: str
    missed: int
    positions: Mapping[int, int]
    action: str


class Stream:
    """A running (or finished) follow-mode stream; create it with ``Streamer.follow``.

    Targets, per tick ``k`` at time ``t = k * period`` since the stream started, come
    from ``source``, one of:

    * a sequence (list, tuple, array): item ``k`` each tick; the stream ends after the
      last item.  It is checked whole when it is given (a bad row refuses the stream,
      nothing sent), and its last row goes out even if the ticks before were skipped;
    * an iterator or generator: the next item each tick, ending with it;
    * an async iterator: awaited each tick;
    * a callable ``f(t, statuses)``, where ``statuses`` maps ID to the latest
      ``la.Status`` (feedback replies and polls): its return value each tick; return
      ``None`` to end the stream.  An ``async def`` (or one returning an awaitable) is
      awaited each tick.

    A plain source (not awaited) is asked for tick ``k + 1``'s targets by the bus's timer
    callback right after tick ``k``'s write, with no task in between (there
    ``asyncio.current_task()`` is None): keep it quick (every stream and bus of the
    event loop waits for it), and write a source that must wait for something as an
    async one.  Every source runs in the context of the bus's streamer task
    (``contextvars``, copied where its first stream started), from the task or its timer
    callbacks alike.

    An item is a position 0..2000 for a single actuator, a sequence with one position
    per actuator (in the order given), or a mapping ``{id: position}``.

    However the stream ends, its ``safe_action`` goes to its actuators once, unless it
    is ended with ``stop(hold=True)``.  ``gaps`` queues its ``StreamGap`` events
    (``await stream.gaps.next(timeout)``); it closes when the stream ends.
    """

    _numbers = itertools.count(1)

    def __init__(
        self,
        streamer: StreamOwner,
        actuators: Sequence[InspireLA],
        source: TargetSource,
        *,
        period: float,
        feedback: bool,
        poll_status: bool,
        safe_action: SafeAction,
        on_gap: GapPolicy = GapPolicy.RAMP,
        max_speed: float = DEFAULT_MAX_SPEED,
        max_missed: int | None = None,
    ) -> None:
        self.streamer = streamer
        self.actuators = tuple(actuators)
        self.ids = tuple(a.id for a in self.actuators)
        #: The target source, adapted to this stream's actuators (``streaming.targets``):
        #: first, so that a sequence with a bad row refuses the stream before it is made.
        self.source = TargetAdapter(self.ids, source)
        #: The actuators as lease keys (``"la:3"``).
        self.keys = frozenset(f"la:{i}" for i in self.ids)
        self.number = next(Stream._numbers)
        self.period = period
        self.feedback = feedback
        self.poll_status = poll_status
        self.safe_action = safe_action
        self.on_gap = on_gap
        self.max_speed = max_speed
        self.max_missed = max_missed
        #: Status replies each actuator missed in a row (polls or feedback round trips).
        self.missed_in_row: dict[int, int] = {}
        #: True once the safe action was sent: no later end sends it again.
        self.safe_applied = False
        self.gaps: Subscription[StreamGap] = streamer.bus.events.subscribe(
            StreamGap, lambda e: e.stream == self.number
        )
        #: While ramping after a gap: the position each ramping actuator was last sent.
        self.ramp: dict[int, float] | None = None
        #: The bus's disconnect count when this stream last had it up (an outage since?).
        self.disconnects_seen = streamer.bus.stats.disconnects
        #: ``stats.skipped`` when the last tick went out (the ticks a gap missed).
        self.skipped_mark = 0
        self.stats = StreamStats()
        self.statuses: dict[int, la.Status] = {}
        self.last_targets: dict[int, int] = {}
        self.error: BaseException | None = None
        self.origin = 0.0
        self.next_tick = 0
        self.paused = False
        #: True from the moment the stream starts to stop: nothing more of it is written.
        self.stopping = False
        self.done = False
        self._finished = asyncio.get_running_loop().create_future()
        self._poll_cursor = 0

    async def recover_from_gap(self, cause: str) -> None:
        """Handle a gap of this stream by its ``on_gap``: find where each actuator is and ramp
        from there, or apply the safe action and end it.  Publishes ``StreamGap``.

        After an outage each position is read (the actuators may have been moved, or
        power-cycled).  After falling behind, an actuator that got targets is where the
        last of them sent it (follow mode tracks it, and nothing else moved it): the ramp
        starts there, without reads that would load a host already too slow.  An
        actuator whose position cannot be read cannot be ramped: that ends the stream as
        "stop" does.
        """
        s, bus = self, self.streamer.bus
        s.disconnects_seen = bus.stats.disconnects
        s.stats.gaps += 1
        missed = s.stats.skipped - s.skipped_mark
        s.skipped_mark = s.stats.skipped
        positions: dict[int, int] = {}
        unread: list[int] = []
        if s.on_gap is GapPolicy.RAMP:
            known = s.last_targets if cause == "behind" else {}
            for ident in s.ids:
                if ident in known:
                    positions[ident] = known[ident]
                    continue
                try:
                    status = await bus.request(
                        la.Control(ident, la.ControlAction.QUERY_STATUS), priority=Priority.HIGH
                    )
                except MotorbusError as err:
                    log.warning("stream to %s: la:%d position unread: %s", list(s.ids), ident, err)
                    unread.append(ident)
                    continue
                s.statuses[ident] = status
                positions[ident] = min(max(status.position, la.POSITION_MIN), la.POSITION_MAX)
        ramp = s.on_gap is GapPolicy.RAMP and not unread and s.sending
        action = "ramp" if ramp else "stop"
        bus.events.publish(
            StreamGap(bus.name, bus.timer.now(), s.number, s.ids, cause, missed, positions, action)
        )
        log.log(
            logging.WARNING if cause == "outage" or not ramp else logging.INFO,
            "stream to %s: gap (%s, %d ticks missed): %s",
            list(s.ids),
            cause,
            missed,
            f"ramping from {positions}" if ramp else "safe action, stream ended",
        )
        if not ramp:
            if s.sending:
                why = f"la:{', la:'.join(map(str, unread))} unread" if unread else 'on_gap="stop"'
                await s.end(StreamEnded(f"gap ({cause}, {missed} ticks missed; {why})"))
            return
        s.ramp = {i: float(p) for i, p in positions.items()}
        # The reads took time: the stream goes on from the next slot still ahead.
        upcoming = math.ceil((bus.timer.now() - s.origin) / s.period)
        if upcoming > s.next_tick:
            s.stats.skipped += upcoming - s.next_tick
            s.next_tick = upcoming
        s.skipped_mark = s.stats.skipped

    # -- control ----------------------------------------------------------------

    def set_targets(self, source: TargetSource) -> None:
        """Replace the target source on the fly; it starts at its own index 0 next tick."""
        self.source.bind(source)
        self.index_base = self.next_tick

    #: The tick the target source's index 0 falls on (``set_targets`` moves it).
    index_base = 0

    def pause(self) -> None:
        """Stop sending targets (the tick grid keeps running, so resume is on the grid)."""
        self.paused = True

    def resume(self) -> None:
        """Send targets again from the next tick."""
        self.paused = False

    @property
    def sending(self) -> bool:
        """True while the stream may still write targets: not paused, stopping or done,
        and none of its actuators stopped since it started (``Lease.stopped``: a frame
        built before the stop, written after it, is dropped at its write)."""
        if self.paused or self.stopping or self.done:
            return False
        lease = self.streamer.lease
        return lease is None or not lease.stopped or self.keys.isdisjoint(lease.stopped)

    def stopped_by(self) -> dict[str, Command[object]]:
        """The stops written to this stream's actuators while it drove them, by device
        (``Lease.stopped``): a pause or an e-stop from anyone."""
        lease = self.streamer.lease
        if lease is None or not lease.stopped:
            return {}
        return {k: c for k, c in lease.stopped.items() if k in self.keys}

    def stop_error(self) -> MotorbusError:
        """What the stream ends with when its actuators were stopped (``stopped_by``)."""
        stops = self.stopped_by()
        what = ", ".join(f"{k} ({_stop_name(stops[k])})" for k in sorted(stops))
        return MotorbusError(
            f"{what or 'an actuator'} stopped while the stream drove it; no target "
            "follows a stop (start a new stream to go on)"
        )

    async def stop(self, *, hold: bool = False, safe: bool | None = None) -> None:
        """End the stream and apply its safe action; with ``hold``, send none.  Idempotent.

        From the moment this is called, nothing more of the stream is written: a tick
        being built or queued is dropped, so the safe action is the last word.  A stream
        that already ended (its targets ran out, an error) applied its safe action then;
        one ended with ``hold`` gets it now.  ``hold=True`` leaves the actuators holding
        their last target: say so where you rely on it.  ``safe=False`` is the older
        spelling of ``hold=True`` (``safe=True`` is the default).
        """
        hold = hold_flag(hold, safe)
        self.stopping = True
        try:
            with deferred_interrupts():
                if not hold:
                    await self.apply_safe_action()
                await self.streamer.let_go(self, hold=hold)
        finally:
            self._finish(None)

    async def wait(self) -> None:
        """Wait until the stream ends; raises ``StreamEnded`` if it ended on an error."""
        await asyncio.shield(self._finished)
        if self.error is not None:
            raise StreamEnded(f"stream to {list(self.ids)} ended: {self.error}") from self.error

    async def apply_safe_action(self) -> None:
        """Bring every actuator of the stream to the configured safe state, once.

        The stream stops sending first (``stopping``), so no target follows the stop.
        The bus's lease table sends it (``bus.lease_keeper.stop``: its definition of the
        safe action, its way of sending one).
        """
        self.stopping = True
        if self.safe_applied:
            return
        self.safe_applied = True
        if self.safe_action is SafeAction.HOLD:
            return
        keys = [f"la:{i}" for i in self.ids]
        bus = self.streamer.bus
        # (Also after a stop from outside, which ended the stream: the device may have
        # been enabled again since, so the safe action goes out whatever came before.)
        await bus.lease_keeper.stop(keys, self.safe_action.value, who=f"stream to {keys}")

    def answered(self, ident: int, status: la.Status | None) -> None:
        """``ident``'s status reply came (None: its frame was dropped unsent)."""
        if status is not None:
            self.statuses[ident] = status
            self.missed_in_row[ident] = 0

    def reply_missed(self, ident: int) -> StreamEnded | None:
        """Note that ``ident`` missed a status reply (a poll, or a feedback round trip:
        counted in ``stats`` by the caller).  Returns the error to end the stream with
        once it missed ``max_missed`` in a row, where the program asked for that; else
        None: a missed reply is counted, never raised (the next one may come)."""
        missed = self.missed_in_row[ident] = self.missed_in_row.get(ident, 0) + 1
        if self.max_missed is None or missed < self.max_missed or not self.sending:
            return None
        return StreamEnded(
            f"la:{ident} missed {missed} status replies in a row (max_missed={self.max_missed})"
        )

    async def end(self, error: BaseException | None = None) -> None:
        """End with the safe action, then mark done with ``error`` (the tick loop's end:
        the targets ran out, the source failed, a gap with ``on_gap="stop"``)."""
        self.stopping = True
        try:
            with deferred_interrupts():
                await self.apply_safe_action()
                await self.streamer.let_go(self, hold=False)
        finally:
            self._finish(error)

    def _finish(self, error: BaseException | None) -> None:
        if self.done:
            return
        self.stopping = True
        self.done = True
        self.error = error
        self.gaps.close()
        if not self._finished.done():
            self._finished.set_result(None)
        self.streamer.discard(self)

    async def __aenter__(self) -> Stream:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        # However the block is left, the safe action goes out (a ``stop(hold=True)``
        # inside the block is the way to leave the actuators holding).
        await self.stop()

    # -- targets ------------------------------------------------------------------

    @property
    def poll_id(self) -> int:
        """The actuator whose status the round robin polls next."""
        return self.ids[self._poll_cursor % len(self.ids)]

    def poll_done(self) -> None:
        """Move the round robin on (the poll was answered, or failed on the line)."""
        self._poll_cursor += 1


async def round_trips(
    bus: Bus, feedback: Sequence[tuple[Stream, int, int]], lease: Lease | None
) -> None:
    """A tick's 0x20 frames of feedback streams, ``(stream, id, position)``, one after
    another, each with its status reply; one of a stream no longer sending is dropped."""
    for s, ident, pos in feedback:
        if not s.sending:
            continue
        follow = la.Follow(ident, pos, True)
        try:
            status = await bus.submit(
                follow,
                priority=Priority.HIGH,
                reserved=True,
                refresh=while_sending(s, follow),
                lease=lease,
            )
        except MotorbusError:
            s.stats.feedback_timeouts += 1
            if (ended := s.reply_missed(ident)) is not None:
                await s.end(ended)
        else:
            s.answered(ident, status)
        s.stats.frames += 1


async def poll_statuses(bus: Bus, due: Sequence[Stream], before: float) -> None:
    """Use the bus's slots left until ``before`` (the next tick's preparation) to poll
    the statuses of ``due``'s streams that ask for it (``poll_status``), round-robin.

    A poll is queued only if even its timeout, and the spacing after it, would end
    before then, with a ``start_by`` past which it is dropped unsent: user requests take
    the slot first (they queue ahead of polls), and a poll that cannot get one is
    counted in ``polls_skipped``; it never holds the next tick.
    """
    pollers = [s for s in due if s.poll_status and s.sending]
    if not pollers:
        return
    timer = bus.timer
    poll = bus.occupancy(la.control_frame(1, la.ControlAction.QUERY_STATUS))
    start_by = before - (poll.worst + poll.spacing)
    for s in pollers:
        polled = 0
        for _ in range(len(s.ids)):
            # No room left in this tick (the spacing alone would pass start_by): the
            # round robin goes on next tick; that is not a skipped poll.
            if max(timer.now(), bus.next_write_at) > start_by or not s.sending:
                break
            ident = s.poll_id
            try:
                status = await bus.submit(
                    la.control_frame(ident, la.ControlAction.QUERY_STATUS),
                    retries=0,
                    priority=Priority.BACKGROUND,
                    start_by=start_by,
                )
            except NotSentError:
                s.stats.polls_skipped += 1
                polled = -1  # counted already
                break
            except MotorbusError:  # counted; raised only past max_missed
                s.poll_done()
                s.stats.poll_timeouts += 1
                if (ended := s.reply_missed(ident)) is not None:
                    await s.end(ended)
                continue
            s.poll_done()
            polled += 1
            s.answered(ident, status)
            s.stats.polls += 1
        if polled == 0:
            s.stats.polls_skipped += 1


async def stop_together(streams: list[Stream], hold: bool, *more: Awaitable[None]) -> None:
    """Stop ``streams`` (and await ``more``) together: each stops sending before the
    first safe action goes, and a silent actuator holds up no other's (the first error
    is raised after)."""
    for s in streams:
        s.stopping = True
    with deferred_interrupts():
        stopped = await asyncio.gather(
            *(s.stop(hold=hold) for s in streams), *more, return_exceptions=True
        )
    for outcome in stopped:
        if isinstance(outcome, BaseException):
            raise outcome


def earliest_tick(streams: Sequence[Stream], *, sending: bool = False) -> float:
    """The earliest next tick deadline of ``streams`` (of those sending, with
    ``sending``: a paused stream needs no slot); infinity if none.  A loop: no list and
    no ``min`` call on every tick (issue 40 counts the calls of a tick)."""
    earliest = math.inf
    for s in streams:
        at = s.origin + s.next_tick * s.period
        if at < earliest and (not sending or s.sending):
            earliest = at
    return earliest


def actuator_group(actuators: object, bus: object) -> list[InspireLA]:
    """``follow``'s actuators as a list, checked: one ``InspireLA`` or a non-empty
    sequence of them, all on ``bus`` (``LocalProtocolError`` names the field)."""
    if isinstance(actuators, InspireLA):
        group = [actuators]
    elif isinstance(actuators, Sequence) and all(isinstance(a, InspireLA) for a in actuators):
        group = list(actuators)
    else:
        raise LocalProtocolError(
            f"actuators must be an InspireLA or a sequence of them, got {actuators!r}",
            field="actuators",
        )
    if not group:
        raise LocalProtocolError("actuators must name at least one actuator", field="actuators")
    for a in group:
        if a.bus is not bus:
            raise LocalProtocolError(
                f"actuator la:{a.id} is on bus {a.bus.name}, not {getattr(bus, 'name', bus)}",
                field="actuators",
            )
    return group
