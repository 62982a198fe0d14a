"""Fixed-rate follow-mode streams to LA actuators, coalesced into broadcasts.

A stream sends one target per actuator every ``period`` seconds (10..50 ms, LA manual
3.5.3: "send at a fixed interval of 10-50 ms").  Ticks are scheduled on absolute
deadlines, ``origin + k * period``, on the bus's high-resolution timer, so a stream
never drifts; a tick that cannot be served on time is skipped, never burst.

Per bus, one :class:`Streamer` serves every stream, from one task and its timer callbacks:

* without feedback, the targets of every actuator whose tick falls due together are
  packed into 0xF3 broadcast frames of at most 15 entries (``la.split_broadcast``),
  so 15 actuators at 10 ms cost one frame a tick (15 addressed frames cannot fit: the
  1 ms spacing allows 10 in 10 ms);
* with feedback, each actuator gets a 0x20 frame and its status reply;
* the slots left in a tick poll the status of streamed actuators round-robin
  (``poll_status=True``), without ever delaying the next tick: a poll that cannot
  start in time is dropped unsent and counted (``polls_skipped``).

Ticks never wait behind user requests: each streamer reserves its tick windows on the
bus (``Bus.add_reservation_source``), and the bus does not start a request that could
still hold the line when a tick is due.  A tick whose frame must still wait (a reply
owed, or the 1 ms spacing from the previous write) slips by the time needed and is
counted (``slipped``).

Stop means stop: once a stream starts stopping (``stop``, the end of its ``async with``
block, an error), nothing more of it is written.  Its frames are prepared ahead of the
deadline (``Bus.prepare(refresh=...)``) and re-checked at the write, rebuilt from the
streams still running only if one stopped, so a tick queued or prepared when the stop
began is dropped, not sent after the safe action's pause (a follow target would resume
a paused actuator, LA manual 3.5.4).  A pause or an e-stop of a streamed actuator from
anyone (another client, a dashboard, the program's own code: ``Lease.stopped``) ends its
stream the same way, with an error, and the stream's safe action after it.

Every end is a safe end: however a stream ends (its targets run out, ``stop()``, the end
of its ``async with`` block, an error, a gap it was told to stop on, the bus closing),
its safe action (``safe_action``: "pause" or "estop") goes to its actuators, unless the
owner ends it explicitly with ``stop(hold=True)`` (the actuators then hold their last
target).

After a gap (the port lost and back, or ``GAP_TICKS`` ticks behind), a ramp or an end
(``follow``'s ``on_gap``), a ``StreamGap`` event and a count (``stats.gaps``).  The
streamers of a bus share one time budget (``follow`` refuses what would not fit).
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import gc
import logging
import math
from collections.abc import Sequence
from typing import Any

from motorbus import lifecycle
from motorbus.bus.bus import Bus, BusState, PreparedSubmit, Priority
from motorbus.bus.jobs import BusJob
from motorbus.bus.leases import Lease, lease_for
from motorbus.bus.timer import Timer, TimerHandle
from motorbus.devices.la import InspireLA
from motorbus.errors import LocalProtocolError, MotorbusError, StreamEnded
from motorbus.streaming.budget import stream_budget, tick_cost
from motorbus.streaming.model import (
    DEFAULT_MAX_SPEED,
    LATE_AFTER_S,
    PERIOD_MAX_S,
    PERIOD_MIN_S,
    GapPolicy,
    SafeAction,
    StreamStats,
    broadcast_builder,
    broadcast_parts,
    check_follow_options,
    hold_flag,
)
from motorbus.streaming.stream import (
    Stream,
    StreamGap,
    actuator_group,
    earliest_tick,
    poll_statuses,
    round_trips,
    stop_together,
)
from motorbus.streaming.targets import TargetSource
from motorbus.streaming.tick import (
    AWAIT,
    ENDED,
    FAILED,
    GAP,
    STOPPED,
    Handed,
    Tick,
    abandon,
    accept,
    plan_tick,
    record_sent,
    record_unsent,
)
from motorbus.validation import LEAD_MAX_S, PHASE_MAX_S, check_number

__all__ = [
    "PERIOD_MAX_S",
    "PERIOD_MIN_S",
    "GapPolicy",
    "SafeAction",
    "Stream",
    "StreamEnded",
    "StreamGap",
    "StreamStats",
    "Streamer",
]

log = logging.getLogger("motorbus.streams")

#: A tick's targets are computed once the previous tick's frames, feedback and polls are
#: done, at most this long before its deadline; its frames leave from a timer callback at
#: the deadline.  One wake-up a tick (180-600 us of CPU here, bench_wakeups.py).
PLAN_AHEAD_S = 0.050
#: Polls stop this long before the next tick, to leave time to prepare it.
PREPARE_S = 1e-3


class Streamer:
    """Serves every stream of one bus, on absolute tick deadlines: a tick of plain target
    sources from the timer callback of the tick before it, anything awaited from a task.

    Args:
        bus: an open bus carrying LA actuators, or a served one (``motorbus.connect``).
        phase: offset of this bus's tick grid in seconds (the manager spreads buses).
        lead: served buses only: how far ahead of their ticks the targets go to the
            server (0..5 s, default 0.1); a local bus checks it and has no use for it.
    """

    def __new__(cls, bus: Any, *, phase: float = 0.0, lead: float | None = None) -> Any:
        served = getattr(bus, "served_streamer", None)
        return super().__new__(cls) if served is None else served(phase=phase, lead=lead)

    def __init__(self, bus: Bus, *, phase: float = 0.0, lead: float | None = None) -> None:
        if not isinstance(bus, Bus):
            raise LocalProtocolError(f"bus must be a Bus, got {bus!r}", field="bus", value=bus)
        phase = check_number("phase", phase, 0.0, PHASE_MAX_S, "s")
        if lead is not None:
            check_number("lead", lead, 0.0, LEAD_MAX_S, "s")
        self.bus = bus
        self.phase = phase
        self.streams: list[Stream] = []
        #: This streamer's lease on the actuators of its running streams (one lease,
        #: since one 0xF3 frame carries several streams): made on the first ``follow``.
        self.lease: Lease | None = None
        self._task: asyncio.Task[None] | None = None
        self._wake: asyncio.Future[None] | None = None
        #: Planned bus time of one tick of this streamer's streams (s), kept current.
        self._tick_cost_s = 0.0
        #: The window of a tick prepared or in progress: (deadline, end of its frames).
        self._active: tuple[float, float] | None = None
        #: While the task waits for ``_fire``: what it will be handed, the tick armed
        #: for its deadline and the timer handle of that.
        self._handback: asyncio.Future[Handed] | None = None
        self._armed: Tick | None = None
        self._fire_handle: TimerHandle | None = None
        #: The bus's timer, kept when the task starts (``_run``): read a few times a tick.
        self._timer: Timer
        #: The task's context (copied where it started): target functions are called in
        #: it from the timer callbacks too, as they were in the task.
        self._context = contextvars.Context()
        #: The budget every streamer of this bus shares, held by the bus.
        self.budget = stream_budget(bus)
        #: Streamers of streams started under a lease the calling task held, by lease.
        self._under: dict[int, Streamer] = {}
        #: True for such a streamer: ``lease`` is its starter's, who ends it.
        self._borrowed = False
        self._attached = False
        self._attach()

    def _attach(self) -> None:
        if not self._attached:
            self._attached = True
            self.bus.add_reservation_source(self._reservation)
            # Whatever ends the program closes the bus: the streams stop safely first.
            self.bus.add_close_hook(self._on_bus_close)

    def _detach(self) -> None:
        """A closed streamer leaves the bus (``follow`` attaches it again)."""
        if self._attached:
            self._attached = False
            self.bus.remove_reservation_source(self._reservation)
            self.bus.remove_close_hook(self._on_bus_close)

    async def _on_bus_close(self) -> None:
        await self.close(safe=True)

    def _reservation(self, now: float) -> tuple[float, float] | None:
        """The next window this streamer's ticks need (see ``Bus.add_reservation_source``)."""
        active = self._active
        if active is not None and active[1] > now:
            return active
        deadline = earliest_tick(self.streams, sending=True)
        if deadline == math.inf:
            return None
        return deadline, deadline + self._tick_cost_s

    def _update_tick_cost(self) -> None:
        self._tick_cost_s = sum(tick_cost(self.bus.timing, self.streams).values())

    # -- ownership --------------------------------------------------------------------

    def _take(self, keys: list[str]) -> list[str]:
        """Hold ``keys`` in this streamer's lease; returns those newly taken.

        Raises:
            LeaseConflictError: another explicit lease holds one of them.
        """
        lease = self.lease
        if self._borrowed:
            assert lease is not None
            missing = [key for key in keys if key not in lease.keys]
            if missing:
                raise LocalProtocolError(
                    f"lease: {', '.join(missing)} not held by {lease.owner!r}; a stream "
                    "under a lease streams only what it holds (nothing sent)",
                    field="lease",
                    value=", ".join(missing),
                )
            return []  # nothing newly taken: nothing to give back if the follow fails
        if lease is None or not lease.active:
            self.lease = self.bus.lease(keys, owner=f"stream on {self.bus.name}", bind=False)
            return keys
        new = [k for k in keys if k not in lease.keys]
        if new:
            lease.add(new)
        return new

    async def let_go(self, stream: Stream, *, hold: bool) -> None:
        """``stream`` ended: its actuators leave this streamer's lease.

        ``hold`` (``stop(hold=True)``): let go on purpose, nothing sent, and the bus's
        close will not stop them.  A stream whose safe action is "hold": they pass to the
        bus's implicit lease (they hold their target; the bus's close stops them).  Else
        the stream has applied its safe action; anything it could not send goes now.
        """
        lease = self.lease
        if lease is None or not lease.active or self._borrowed:
            return  # a borrowed lease keeps them: its owner ends it
        keys = sorted(stream.keys & lease.keys)
        if not keys:
            return
        if hold:
            await lease.release(hold=True, keys=keys)
        elif stream.safe_action is SafeAction.HOLD:
            self.bus.hand_over(lease, keys)
        else:
            await lease.release(keys=keys)

    # -- starting and stopping --------------------------------------------------------

    def follow(
        self,
        actuators: InspireLA | Sequence[InspireLA],
        targets: TargetSource,
        *,
        period: float = 0.02,
        feedback: bool = False,
        poll_status: bool = False,
        safe_action: SafeAction | str = SafeAction.HOLD,
        on_gap: GapPolicy | str = GapPolicy.RAMP,
        max_speed: float = DEFAULT_MAX_SPEED,
        max_missed: int | None = None,
    ) -> Stream:
        """Start streaming follow-mode targets; returns the running ``Stream``.

        Args:
            actuators: one actuator or several, all on this streamer's bus.
            targets: where targets come from; see :class:`Stream`.
            period: seconds between ticks, 0.010..0.050 (LA manual 3.5.3).
            feedback: send 0x20 per actuator and decode each status (else 0x19, coalesced
                into 0xF3 broadcasts with the other no-feedback streams of the bus).
            poll_status: in the slots a tick leaves free, query the status of this
                stream's actuators round-robin (no-feedback streams).
            safe_action: "hold", "pause" or "estop"; applied however the stream ends (its
                targets run out, ``stop()``, the end of its ``async with`` block, an
                error, the bus closing), unless it is ended with ``stop(hold=True)``.
            on_gap: after a gap (the bus lost its port and came back, or the stream
                fell ``GAP_TICKS`` ticks behind): "ramp" (default) starts from where
                each actuator is (read after an outage; the last target sent after
                falling behind) and ramps to the trajectory at ``max_speed``; "stop"
                applies the safe action and ends the stream with an error.
            max_speed: the stream's speed limit in position units per second, for the
                ramp after a gap (default 500: the full stroke in 4 s).  A trajectory
                faster than that is caught up with where it turns back.
            max_missed: end the stream with its safe action (``StreamEnded``) once an
                actuator missed this many status replies in a row (polls or feedback
                round trips), 1..1000; None (default): missed replies are counted
                (``poll_timeouts``, ``feedback_timeouts``), never raised.

        Raises:
            LocalProtocolError: a bad period, option, an empty or foreign actuator list,
                an actuator already streamed, or a load that does not fit the bus.
        """
        group = actuator_group(actuators, self.bus)
        options = check_follow_options(
            period=period,
            feedback=feedback,
            poll_status=poll_status,
            safe_action=safe_action,
            on_gap=on_gap,
            max_speed=max_speed,
            max_missed=max_missed,
        )
        self.budget.check_ids([a.id for a in group])
        keys = [f"la:{a.id}" for a in group]
        held = None if self._borrowed else lease_for(self.bus.lease_keeper.table)
        if held is not None and not held.keys.isdisjoint(keys):
            return self.under(held)._start(group, keys, targets, options)
        return self._start(group, keys, targets, options)

    def under(self, lease: Lease) -> Streamer:
        """The streamer of this bus's streams under ``lease`` (made on first use).

        ``follow`` comes here when the calling task holds an explicit lease on its
        actuators (``bus.lease``, bound to the task): the stream runs under that lease,
        which must hold every actuator of it, in frames of its own.  Ending the lease
        (``release``, its ``async with`` block's end) stops such streams first: nothing of
        them follows its safe action.  A stream that ends leaves its actuators in it.
        """
        self._under = {i: c for i, c in self._under.items() if c.lease and c.lease.active}
        child = self._under.get(id(lease))
        if child is None or child.lease is not lease:
            child = self._under[id(lease)] = Streamer.borrowing(self.bus, lease, phase=self.phase)
        return child

    @classmethod
    def borrowing(cls, bus: Bus, lease: Lease, *, phase: float = 0.0) -> Streamer:
        """A streamer whose streams run under ``lease``, which another owner ends (see
        ``under``): it takes no lease of its own and gives nothing back."""
        streamer = cls(bus, phase=phase)
        streamer.lease, streamer._borrowed = lease, True
        lease.enders.append(streamer._lease_ends)
        return streamer

    async def _lease_ends(self, keys: frozenset[str] | None, hold: bool) -> None:
        """The borrowed lease is ending (on ``keys``; None: all): its streams stop."""
        if keys is None:  # all of it: this streamer closes and leaves the bus
            assert self.lease is not None
            with contextlib.suppress(ValueError):
                self.lease.enders.remove(self._lease_ends)
            await self.close(hold=hold)
            return
        await stop_together(
            [s for s in self.streams if keys is None or not keys.isdisjoint(s.keys)], hold
        )

    def _start(
        self, group: list[InspireLA], keys: list[str], targets: TargetSource, options: Any
    ) -> Stream:
        self._attach()
        # The targets first (a sequence is checked whole): a refused stream takes nothing.
        stream = Stream(
            self,
            group,
            targets,
            period=options.period,
            feedback=options.feedback,
            poll_status=options.poll_status,
            safe_action=options.safe_action,
            on_gap=options.on_gap,
            max_speed=options.max_speed,
            max_missed=options.max_missed,
        )
        taken: list[str] = []
        try:  # one owner per motion: another's lease is refused here, nothing sent
            taken = self._take(keys)
            self.budget.admit(self.bus.timing, stream)
            if self.lease is not None:  # a stop before this stream does not end it
                self.lease.forget_stops(keys)
        except BaseException:
            stream.gaps.close()
            if taken and self.lease is not None:
                self.lease.table.release(self.lease, hold=True, keys=taken)
            raise
        starting = self._task is None or self._task.done()
        if starting:
            # What the set-up made is young: the collector's first pass over it (1-2 ms)
            # would be a late tick; pass now (docs/design.md), in real-time mode too (its
            # freeze at enable() misses later set-up; gen-1 passes stay automatic there).
            gc.collect(1)
        now = self.bus.timer.now()
        # Align the origin to this bus's grid so streams of one period coalesce.
        grid = self.phase + math.ceil((now + 0.002 - self.phase) / stream.period) * stream.period
        stream.origin = grid
        self.streams.append(stream)
        self._update_tick_cost()
        if starting:
            self._context = contextvars.copy_context()
            self._task = asyncio.get_running_loop().create_task(
                self._run(), name=f"motorbus streams {self.bus.name}", context=self._context
            )
        else:
            self._ring()
        return stream

    def discard(self, stream: Stream) -> None:
        """Forget an ended stream (``Stream`` calls it as it finishes)."""
        self.budget.release(stream)
        if stream in self.streams:
            self.streams.remove(stream)
            self._update_tick_cost()
            self._ring()

    async def close(self, *, hold: bool = False, safe: bool | None = None) -> None:
        """End every stream with its safe action (none with ``hold``) and stop the task.

        All stop sending at once, then stop together: a silent actuator holds up no other's
        safe action (the first error is raised after).  ``safe=False``: ``hold=True``.
        """
        hold = hold_flag(hold, safe)
        children, self._under = list(self._under.values()), {}
        try:
            await stop_together(
                [s for c in (self, *children) for s in c.streams],
                hold,
                *(c.close(hold=hold) for c in children),
            )
        finally:
            if self._task is not None:
                self._task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await self._task
                self._task = None
            self._detach()

    # -- the tick loop -------------------------------------------------------------------

    def _ring(self) -> None:
        if self._wake is not None and not self._wake.done():
            self._wake.set_result(None)

    async def _sleep_until(self, deadline: float) -> None:
        wake: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._wake = wake
        # Only the preparation wakes here; the frames go out from a precise callback.
        handle = self._timer.call_at(deadline, self._ring, precise=False)
        try:
            await wake
        finally:
            handle.cancel()
            self._wake = None

    async def _run(self) -> None:
        self._timer = timer = self.bus.timer
        tick: Tick | None = None
        try:
            while self.streams:
                if tick is None:
                    deadline = earliest_tick(self.streams)
                    if deadline - PLAN_AHEAD_S > timer.now():
                        await self._sleep_until(deadline - PLAN_AHEAD_S)
                        continue  # re-check: streams may have changed while asleep
                    tick = self._plan(deadline)
                if tick.later:
                    await self._settle(tick)
                tick = await self._serve_tick(tick)
                if tick is None:
                    self._idle()
        finally:
            if tick is not None:
                abandon(tick)

    def _plan(self, deadline: float) -> Tick:
        bus, lease = self.bus, self.lease
        return plan_tick(
            self.streams,
            deadline,
            self._timer.now(),
            bus_up=bus.state is BusState.OPEN,
            disconnects=bus.stats.disconnects,
            stopped=lease.stopped if lease is not None else {},
        )

    def _idle(self) -> float:
        """The idle time until the next tick: where real-time mode runs the garbage
        collector's full collections (a no-op otherwise; ``motorbus.lifecycle.idle``).
        Returns the next tick's deadline (infinity without streams)."""
        deadline = earliest_tick(self.streams)
        idle = deadline - PREPARE_S - self._timer.now()
        if 0 < idle < math.inf:
            lifecycle.idle(idle)
        return deadline

    async def _settle(self, tick: Tick) -> None:
        """Do what planning ``tick`` left to await (``Tick.later``), stream by stream: a
        gap's recovery, a stream's end (its safe action), targets still to come."""
        later, tick.later = tick.later, []
        for index, (s, kind, value) in enumerate(later):
            try:
                if kind == GAP:
                    await s.recover_from_gap(value)
                    continue
                if kind == STOPPED:  # a pause or an e-stop from anyone: no target after it
                    log.warning("stream to %s ended: %s", list(s.ids), err := s.stop_error())
                    await s.end(err)
                    continue
                if kind == AWAIT:
                    try:
                        targets = await s.source.finish(value)
                    except Exception as err:
                        kind, value = FAILED, err
                    else:
                        if targets is not None:
                            accept(tick, s, targets)
                            continue
                        kind = ENDED
                if kind == FAILED:  # the user's target source failed: end that stream
                    log.warning("stream to %s: target source failed: %s", list(s.ids), value)
                    await s.end(value)
                else:  # its targets ran out: a normal end, still a safe one
                    await s.end(None)
            except BaseException:
                tick.later = later[index + 1 :]
                raise

    async def _serve_tick(self, tick: Tick) -> Tick | None:
        """Send ``tick``'s frames at its deadline, then its feedback round trips and polls.

        The frames go out from a timer callback at the deadline (``_fire``), which serves
        the ticks after it too while they need no task.  Returns the tick that callback
        planned and left to this task, if any.
        """
        if not tick.served:
            return None
        if tick.prepared is None:
            self._prepare_tick(tick)
        self._active = (tick.deadline, tick.deadline + self._tick_cost_s)
        timer = self._timer
        try:
            if not tick.prepared:  # feedback frames only; or refused (the port away)
                sent_at, frames, slipped = None, 0, False
            else:
                handed = await self._sent_by_timer(tick)
                if handed.tick is None:
                    return handed.ahead  # served, with the ticks after it
                tick = handed.tick  # written (or refused) and left to this task to finish
                sent_at, frames, slipped = await self._written(handed)
            if tick.feedback:
                # Feedback frames are round trips, sent one after another from this task:
                # the first leaves at the deadline (the tick was prepared a period ahead).
                if timer.now() < tick.deadline:
                    await timer.sleep_until(tick.deadline)
                if sent_at is None:
                    sent_at = timer.now()
                    slipped = sent_at - tick.deadline > LATE_AFTER_S / 10
                await round_trips(self.bus, tick.feedback, self.lease)
        finally:
            self._active = None
        if sent_at is None:  # refused (the port away, the bus closing): nothing left
            record_unsent(tick)
            return None
        record_sent(tick, sent_at, slipped, frames)
        if tick.polls and self.streams:
            # The slots left before the next tick, its preparation apart, poll statuses.
            await poll_statuses(self.bus, tick.served, earliest_tick(self.streams) - PREPARE_S)
        return None

    def _prepare_tick(self, tick: Tick) -> None:
        """Make ``tick``'s 0xF3 frames bus jobs (``Bus.prepare``), ahead of its deadline.

        Built, encoded, checked (the lease rule) and made a job now: at the deadline only
        the cheap re-checks and the write are left.  Each frame's ``refresh`` rebuilds it
        then only if one of its streams stopped or paused since; a frame refused here is
        not sent (no second way).  IDs and positions were checked already (at ``follow``,
        by the target source): the frames are built without checking them again.
        """
        prepared: list[PreparedSubmit[Any]] = []
        prepare, lease, HIGH = self.bus.prepare, self.lease, Priority.HIGH
        parts = [(s, s.last_targets) for s in tick.served if not s.feedback]
        for frame_parts in broadcast_parts(parts) if parts else ():
            build = broadcast_builder(frame_parts)
            frame = build()
            if frame is None:
                continue
            try:
                job = prepare(frame, priority=HIGH, reserved=True, refresh=build, lease=lease)
                prepared.append(job)
            except MotorbusError as err:  # refused (the port away, the bus closing)
                log.debug("stream tick on bus %s not prepared: %s", self.bus.name, err)
        tick.prepared = prepared

    async def _sent_by_timer(self, tick: Tick) -> Handed:
        """Arm ``_fire`` for ``tick``'s deadline and wait for what it hands back.

        A task woken at the deadline would send one event-loop step late (~55 us here,
        bench_wakeups.py), so the frames go out from the timer callback itself.
        """
        handback: asyncio.Future[Handed] = asyncio.get_running_loop().create_future()
        self._handback = handback
        self._arm(tick)
        try:
            return await handback
        except BaseException:
            if handback.done() and not handback.cancelled() and handback.exception() is None:
                ahead = handback.result().ahead
                if ahead is not None:
                    abandon(ahead)  # cancelled as it was handed over
            raise
        finally:
            self._handback = None
            self._armed = None
            if self._fire_handle is not None:
                self._fire_handle.cancel()
                self._fire_handle = None

    def _arm(self, tick: Tick) -> None:
        self._armed = tick
        self._fire_handle = self._timer.call_at(tick.deadline, self._fire)

    def _fire(self) -> None:
        """At the armed tick's deadline: write its frames, one path (the bus re-checks
        each, its ``refresh``, and writes it).  A tick written whole at once that needs
        nothing more (no feedback, no polls) is counted here, and ``_advance`` goes on to
        the next: a steady stream runs from timer callbacks alone.  Anything else goes
        back to the task."""
        handback, tick = self._handback, self._armed
        self._armed = self._fire_handle = None
        if handback is None or handback.done() or tick is None:
            return  # the task stopped waiting (cancelled): nothing goes out
        try:
            send = self.bus.send_prepared
            jobs: list[BusJob] = []
            try:
                for ready in tick.prepared or ():
                    future = send(ready)
                    if ready.job.attempts or not future.done():
                        jobs.append(ready.job)  # written, or waiting its turn
            except MotorbusError as err:
                handback.set_result(Handed(tick, jobs, None, err))
                return
            first = jobs[0] if jobs else None
            if first is None or not first.future.done():
                handback.set_result(Handed(tick, jobs, None))  # dropped, or waiting its turn
                return
            future = first.future
            if (
                len(jobs) > 1
                or tick.feedback
                or tick.polls
                or future.cancelled()
                or future.exception() is not None
            ):
                handback.set_result(Handed(tick, jobs, first.tx_start))
                return
            # Written at the deadline, whole: the tick is done.
            record_sent(tick, first.tx_start, False, 1)
            self._active = None
            # The next tick is planned after the writes of every bus due now (the same
            # deadline, later in the timer's order): planning is not their lateness.
            self._fire_handle = self._timer.call_at(tick.deadline, self._advance)
        except Exception as err:  # a bug: the task raises it rather than wait forever
            handback.set_exception(err)

    def _advance(self) -> None:
        """After a tick ``_fire`` served whole: plan the next, prepare and arm it, unless
        it needs the task (something to await, feedback): then it goes to the task."""
        handback = self._handback
        self._fire_handle = None
        if handback is None or handback.done():
            return  # the task stopped waiting (cancelled)
        try:
            ahead = None
            deadline = self._idle()
            if deadline - PLAN_AHEAD_S <= self._timer.now():
                ahead = self._context.run(self._plan, deadline)  # (the target functions)
                if ahead.served and not ahead.later and not ahead.feedback:
                    self._prepare_tick(ahead)
                    if ahead.prepared:
                        self._active = (deadline, deadline + self._tick_cost_s)
                        self._arm(ahead)
                        return
            handback.set_result(Handed(None, ahead=ahead))
        except Exception as err:  # a bug: the task raises it rather than wait forever
            handback.set_exception(err)

    async def _written(self, handed: Handed) -> tuple[float | None, int, bool]:
        """When the first frame of a tick ``_fire`` handed back left (None if none did),
        its frames, and whether it slipped (its first frame waited its turn: a reply
        owed, or the spacing)."""
        if handed.error is not None:
            log.debug("stream tick on bus %s not sent: %s", self.bus.name, handed.error)
            return None, 0, False
        sent_at, slipped = handed.sent_at, False
        try:
            for job in handed.jobs:
                await job.future
                if sent_at is None:
                    sent_at = job.tx_start if job.attempts else self._timer.now()
                    slipped = True
        except MotorbusError as err:
            log.debug("stream tick on bus %s not sent: %s", self.bus.name, err)
            return None, 0, False
        return sent_at, len(handed.jobs), slipped
