"""Timers that never fire early and, on Linux, hold deadlines to about 100 µs.

asyncio cannot do either on its own (docs/platform.md §1): the default loop rounds every
timeout *up* to a whole millisecond (an 800 µs reply timeout takes at least 1.1 ms), and
uvloop rounds to the *nearest* millisecond against a millisecond clock, so its timers fire
up to a millisecond early (1 % spurious reply timeouts, a 1 ms spacing rule broken 99.8 %
of the time).  motorbus therefore schedules every deadline through a :class:`Timer`:

* :class:`TimerfdTimer` (Linux): one ``timerfd`` armed at the earliest pending absolute
  ``CLOCK_MONOTONIC`` deadline and watched with ``loop.add_reader``; it works under the
  default loop and uvloop alike.
* :class:`LoopTimer` (everywhere else, and the fallback if ``timerfd`` is unavailable):
  ``loop.call_at``, re-scheduled when it wakes before the deadline.  It is never early
  but keeps the loop's lateness (about 1 ms on the default loop).

Both use ``time.monotonic()`` as their clock, so deadlines are plain floats in seconds
that any layer can compute: periodic streams use ``origin + k * period``, which never
drifts.  Callbacks of one timer run in deadline order (ties in scheduling order).
"""

from __future__ import annotations

import abc
import asyncio
import collections
import contextvars
import heapq
import logging
import math
import os
import sys
import time
import weakref
from collections.abc import Callable
from typing import Any

from motorbus import lifecycle
from motorbus.bus.timerfd import api as _api
from motorbus.bus.timerfd import timerfd_available
from motorbus.errors import LocalProtocolError

__all__ = [
    "LoopTimer",
    "Timer",
    "TimerHandle",
    "TimerfdTimer",
    "default_timer",
    "spin_asked",
    "timerfd_available",
]

_log = logging.getLogger("motorbus.bus")

_EXPIRY_COUNT_SIZE = 8  # timerfd read(2) returns a uint64 expiry count
_NS_PER_S = 1_000_000_000
#: Asks every ``TimerfdTimer`` to spin before precise deadlines, up to this many us.
SPIN_ENV_VAR = "MOTORBUS_TIMER_SPIN_US"


def spin_asked() -> bool:
    """Whether a ``TimerfdTimer`` made now spins before precise deadlines by default:
    ``MOTORBUS_TIMER_SPIN_US`` is set (to more than 0), or real-time mode is on or asked
    for.  Never otherwise: a spin costs CPU on every deadline (issue 40)."""
    setting = os.environ.get(SPIN_ENV_VAR)
    if setting:
        return float(setting) > 0
    return lifecycle.realtime_wanted()


class TimerHandle:
    """A scheduled callback; :meth:`cancel` it to stop it from running."""

    __slots__ = ("_callback", "_cancelled", "_done", "_timer", "_watch", "deadline", "precise")

    def __init__(
        self, timer: Timer, deadline: float, callback: Callable[[], None], precise: bool = True
    ) -> None:
        """Create a handle; use :meth:`Timer.call_at`."""
        self._timer: Timer | None = timer
        self.deadline = deadline
        self.precise = precise
        self._callback: Callable[[], None] | None = callback
        self._cancelled = False
        self._done = False
        #: The loop's own handle while the loop's timer watches it (call_at_lazily).
        self._watch: asyncio.TimerHandle | None = None

    def __repr__(self) -> str:
        state = "cancelled" if self._cancelled else "done" if self._done else "pending"
        return f"<TimerHandle deadline={self.deadline:.6f} {state}>"

    def cancelled(self) -> bool:
        """Return True if :meth:`cancel` was called before the callback ran."""
        return self._cancelled

    def cancel(self) -> None:
        """Stop the callback from running; harmless after it ran or was cancelled."""
        if self._cancelled or self._done:
            return
        self._cancelled = True
        self._callback = None
        timer, self._timer = self._timer, None
        watch = self._watch
        if timer is not None and watch is not None:  # still the loop's: not in the heap
            self._watch = None
            del timer._watching[self]
            watch.cancel()
        elif timer is not None:
            timer._forget_cancelled(self)


class Timer(abc.ABC):
    """Schedules callbacks at absolute ``time.monotonic()`` deadlines, never early.

    Pending callbacks sit in one heap; a subclass only provides a wake-up source armed at
    the earliest deadline.  On every wake-up the callbacks whose deadline has passed run
    in deadline order (ties in scheduling order) and the source is re-armed at the next;
    a wake-up before the earliest deadline just re-arms.  (A deadline of
    :meth:`call_at_lazily` joins the heap only for its last stretch.)  One timer serves
    one event loop; get the shared one with :func:`default_timer`.
    """

    #: "timerfd" or "loop".
    name: str
    #: How long before a deadline of :meth:`call_at_lazily` the loop's own timer hands it
    #: to the wake-up source: that timer sleeps whole milliseconds, rounded up (under 1 ms
    #: late, plus a wake-up's 0.1-0.5 ms), for watches up to ``LAZY_WITHIN_S``; for some
    #: longer ones asyncio's rounding adds a millisecond (``9 * 1e-3 > 0.009``;
    #: bench_timer.py: asyncio.sleep at a 10 ms period, 2.3 ms late at p99).
    HANDOVER_S = 2e-3
    #: The longest watch (from now to the handover) left to the loop's timer.
    LAZY_WITHIN_S = 8e-3
    #: Whether this timer's clock is the loop's (``time.monotonic``), so that the loop's
    #: timer may watch the first part of a lazily called deadline.
    _LAZY = False

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        # Weak, so the per-loop cache in default_timer() does not keep a dead loop alive.
        self._loop_ref = weakref.ref(loop)
        self._closed = False
        self._heap: list[tuple[float, int, TimerHandle]] = []
        self._seq = 0  # ties in scheduling order (an int: no next() a deadline)
        self._cancelled_in_heap = 0
        # A change of the earliest deadline re-arms the wake-up source once the loop's
        # turn is over (_rearm_soon): one re-arm for a turn's changes (a wake-up that
        # resolves a task's sleep, the request the task then sends): a settime for the
        # near future costs a VM tens of us (bench_pieces.py).  While _holds is above 0
        # (callbacks running, a caller's hold_arming()) changes are only noted.
        self._holds = 0
        self._rearm_due = False
        self._flush_queued = False
        self._context = contextvars.Context()  # the re-arm reads none: not a copy each
        # asyncio's own loops (not uvloop) run the handles in their ``_ready`` deque:
        # there the queued re-arm is one handle made once, appended again each time (a
        # call, not call_soon's six and a Handle: issue 40); not in debug mode (its
        # call_soon checks the thread).  Its loop weakly, as default_timer's cache.
        ready = getattr(loop, "_ready", None)
        asyncio_loop = isinstance(loop, asyncio.BaseEventLoop) and not loop.get_debug()
        self._ready = ready if asyncio_loop and type(ready) is collections.deque else None
        proxy: Any = weakref.proxy(loop)
        # call_at_lazily: on asyncio's own loops, whose clock is time.monotonic (weakly,
        # as above: a bound method would keep the loop alive through default_timer's cache).
        own_clock = getattr(loop.time, "__func__", None) is asyncio.BaseEventLoop.time
        lazy = self._LAZY and self._ready is not None and own_clock
        self._lazy_loop = proxy if lazy else None
        #: Lazily called deadlines the loop's timer still watches, with their places in
        #: the scheduling order (ties: a handed-over one keeps its place).
        self._watching: dict[TimerHandle, int] = {}
        self._handover_s = self.HANDOVER_S
        self._flush_handle = asyncio.Handle(self._flush_rearm, (), proxy, self._context)
        if type(self).now is Timer.now:
            # The clock is the C function itself: one call a read, not two (issue 40).
            self.now = time.monotonic  # type: ignore[method-assign]

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The event loop this timer runs callbacks on.

        Raises:
            RuntimeError: the loop no longer exists.
        """
        loop = self._loop_ref()
        if loop is None:
            raise RuntimeError("the event loop of this timer is gone")
        return loop

    @property
    def pending(self) -> int:
        """Number of scheduled callbacks that have neither run nor been cancelled."""
        return len(self._heap) - self._cancelled_in_heap + len(self._watching)

    def now(self) -> float:
        """Return the current time in seconds, the clock of ``time.monotonic()``."""
        return time.monotonic()

    def call_at(
        self, deadline: float, callback: Callable[[], None], *, precise: bool = True
    ) -> TimerHandle:
        """Run ``callback()`` on the loop once ``now() >= deadline``.

        Args:
            deadline: absolute time in seconds (``time.monotonic()`` clock); a deadline in
                the past runs the callback as soon as possible, never synchronously.
            callback: called with no arguments; exceptions go to the loop's exception
                handler.
            precise: spend CPU to run it within microseconds of ``deadline`` (where the
                timer can); ``False`` for wake-ups that only need to be roughly on time.

        Returns:
            A handle whose ``cancel()`` stops the callback.

        Raises:
            RuntimeError: the timer is closed.
            LocalProtocolError: ``deadline`` is NaN.
        """
        if self._closed:
            raise RuntimeError(f"{type(self).__name__} is closed")
        if deadline != deadline:  # NaN: it would sit in the heap out of order, and never arm
            raise LocalProtocolError(
                "deadline must be a time in seconds (time.monotonic clock), got nan",
                field="deadline",
                value=deadline,
            )
        handle = TimerHandle(self, deadline, callback, precise)
        heap = self._heap
        self._seq += 1
        heapq.heappush(heap, (deadline, self._seq, handle))
        if heap[0][2] is handle:
            if self._holds:
                self._rearm_due = True  # what _rearm_soon does in a hold, without the call
            elif not self._flush_queued:
                self._rearm_soon()
        return handle

    def call_at_lazily(
        self, deadline: float, callback: Callable[[], None], now: float | None = None
    ) -> TimerHandle:
        """:meth:`call_at` for a deadline that is usually cancelled before it comes (a
        reply's): the wake-up source is armed for it only in its last ``HANDOVER_S``.
        Until then the loop's own timer watches it, so a cancel then re-arms nothing (on
        a VM a ``timerfd_settime`` for the near future costs ~12 us, ``bench_pieces.py``,
        and a reply deadline cost two).  A plain :meth:`call_at` where that saves
        nothing (an earlier deadline is pending: the source stays armed for it) or
        cannot be done well (another loop or clock; a handover already past, or further
        than ``LAZY_WITHIN_S``).  Never early, in deadline order, as :meth:`call_at`.
        ``now``: the caller's latest reading of :meth:`now`, if it has one (a call fewer).
        """
        loop, heap = self._lazy_loop, self._heap
        handover = deadline - self._handover_s
        if (
            loop is None
            or (heap and heap[0][0] <= deadline)  # the source stays armed for that one
            or not 0 < handover - (self.now() if now is None else now) <= self.LAZY_WITHIN_S
            or self._closed  # (call_at raises; as for NaN, which fails the range above)
        ):
            return self.call_at(deadline, callback)
        handle = TimerHandle(self, deadline, callback)
        handle._watch = loop.call_at(handover, self._on_handover, handle, context=self._context)
        self._seq += 1
        self._watching[handle] = self._seq
        return handle

    def _hand_over(self, handle: TimerHandle) -> None:
        """A watched deadline enters the heap, keeping its place among equal ones."""
        handle._watch = None
        seq = self._watching.pop(handle)
        heap = self._heap
        heapq.heappush(heap, (handle.deadline, seq, handle))
        if heap[0][2] is handle:
            self._rearm_soon()

    def _on_handover(self, handle: TimerHandle) -> None:
        """The loop's timer: ``handle``'s last stretch has begun.  If the loop was held
        up past the deadline itself, it runs now (with whatever was due before it)."""
        if handle.deadline <= (now := self.now()) and not self._holds:
            self._wake(now)  # (which hands it over, with any other watched one due)
        else:
            self._hand_over(handle)

    def _take_watched(self, now: float) -> None:
        """Hand over the watched deadlines whose last stretch began by ``now`` (late)."""
        for handle in [h for h in self._watching if h.deadline - self._handover_s <= now]:
            assert handle._watch is not None
            handle._watch.cancel()
            self._hand_over(handle)

    def hold_arming(self) -> None:
        """Defer re-arming the wake-up source until the matching :meth:`release_arming`.

        For a callback that cancels and schedules several deadlines in a row (a reply
        that frees the bus and schedules the next write): the source is re-armed once,
        after the release (at the end of the loop's turn, as every re-arm), for the
        earliest deadline then.  Holds nest.  No callback runs early because of a hold;
        one can only run late if the loop gets to sleep before the release, so call
        both from the same callback (``try``/``finally``).
        """
        self._holds += 1

    def release_arming(self) -> None:
        """End a :meth:`hold_arming`; the last release re-arms if anything changed."""
        self._holds -= 1
        if not self._holds and self._rearm_due and not self._closed:
            self._rearm_due = False
            if not self._flush_queued:
                self._rearm_soon()

    async def sleep_until(self, deadline: float, *, precise: bool = True) -> None:
        """Sleep until ``now() >= deadline``; cancel-safe (the wake-up is unscheduled).

        A deadline already past still yields to the loop once, so a periodic task that
        overran cannot starve other tasks.

        Args:
            deadline: absolute time in seconds, ``time.monotonic()`` clock.
            precise: as for :meth:`call_at`; ``False`` spends no CPU spinning, and
                wakes as late as a plain timer wake-up (never early).
        """
        if deadline <= self.now():
            await asyncio.sleep(0)
            return
        future: asyncio.Future[None] = self.loop.create_future()

        def wake() -> None:
            if not future.done():
                future.set_result(None)

        handle = self.call_at(deadline, wake, precise=precise)
        try:
            await future
        finally:
            handle.cancel()

    def close(self) -> None:
        """Drop every pending callback, release the wake-up source; idempotent.

        Later :meth:`call_at` calls raise ``RuntimeError``.
        """
        if self._closed:
            return
        self._closed = True
        for _, _, handle in self._heap:
            handle._callback = None
            handle._cancelled = True
        self._heap.clear()
        for handle in self._watching:
            assert handle._watch is not None
            handle._watch.cancel()
            handle._watch = handle._callback = None
            handle._cancelled = True
        self._watching.clear()
        self._cancelled_in_heap = 0
        self._release()

    @abc.abstractmethod
    def _arm(self, deadline: float) -> None:
        """Make sure :meth:`_wake` runs at (or after) ``deadline``, replacing earlier arming."""

    @abc.abstractmethod
    def _disarm(self) -> None:
        """Cancel the pending wake-up, if any."""

    @abc.abstractmethod
    def _release(self) -> None:
        """Free the wake-up source (called once, by :meth:`close`)."""

    def _wake(self, now: float | None = None) -> None:
        """The wake-up source fired (the clock read ``now``, if just read): run every
        due callback in deadline order (each once; exceptions go to the loop's
        exception handler), then re-arm at the next deadline."""
        heap = self._heap
        loop = self._loop_ref()
        if loop is None:
            raise RuntimeError("the event loop of this timer is gone")
        now = self.now() if now is None else now
        # Callbacks that schedule and cancel deadlines re-arm nothing until all have run.
        self._holds += 1
        try:
            if self._watching:  # handed over first, so that they run in deadline order
                self._take_watched(now)
            while heap:
                if heap[0][0] > now:  # not due by the last reading: read the clock again
                    now = self.now()
                    if self._watching:
                        self._take_watched(now)
                    if heap[0][0] > now:
                        break
                handle = heapq.heappop(heap)[2]
                if handle._cancelled:
                    self._cancelled_in_heap -= 1
                    continue
                # TimerHandle's run, inline (a call fewer a deadline).
                callback, handle._callback = handle._callback, None
                handle._done = True
                handle._timer = None
                try:
                    callback()  # type: ignore[misc]  # set while neither run nor cancelled
                except (SystemExit, KeyboardInterrupt):
                    raise
                except BaseException as exc:
                    context = {"message": "exception in timer callback", "exception": exc}
                    loop.call_exception_handler({**context, "handle": handle})
                if self._closed:
                    return
        finally:
            self._holds -= 1
        if self._holds:
            self._rearm_due = True  # woken inside a caller's hold: its release re-arms
        else:
            self._rearm_due = False
            if self._ready is not None and not self._ready and not self._flush_queued:
                self._flush_rearm()  # nothing else runs this loop turn: no turn for it
            elif not self._flush_queued:
                self._rearm_soon()

    def _flush_rearm(self) -> None:
        """The queued re-arm of :meth:`_rearm_soon`: arm the wake-up source for the
        earliest live deadline (or disarm it)."""
        self._flush_queued = False
        if self._closed:
            return
        if self._holds:
            self._rearm_due = True
            return
        heap = self._heap
        while heap and heap[0][2]._cancelled:
            heapq.heappop(heap)
            self._cancelled_in_heap -= 1
        if heap:
            self._arm(heap[0][0])
        else:
            self._disarm()

    def _forget_cancelled(self, handle: TimerHandle) -> None:
        heap = self._heap
        if heap and heap[0][2] is handle:
            # The earliest (a reply's deadline) leaves at once, with the cancelled ones
            # it uncovers: the earliest is always live.  Re-armed for the next rather
            # than waking up for nothing (a syscall, against a wake-up: 100x on a VM).
            heapq.heappop(heap)
            while heap and heap[0][2]._cancelled:
                heapq.heappop(heap)
                self._cancelled_in_heap -= 1
            if not self._closed and not self._flush_queued:
                self._rearm_soon()
            return
        self._cancelled_in_heap += 1
        # Compact when most are dead, so they cannot pile up (the earliest is live: stays).
        if self._cancelled_in_heap * 2 > len(heap):
            # In place: _wake may be iterating over this very list.
            heap[:] = [entry for entry in heap if not entry[2]._cancelled]
            heapq.heapify(heap)
            self._cancelled_in_heap = 0

    def _rearm_soon(self) -> None:
        """Re-arm after the callbacks the loop has queued so far (or at the end of the
        current hold): one re-arm for all the changes of a loop turn (``_wake`` re-arms
        at once when nothing is queued: no loop turn for it).

        Never early, never missed: the re-arm is itself a queued callback, and a loop
        with a queued callback does not sleep, so it runs before the loop can wait on
        the wake-up source, for the earliest deadline then.  It can only add to a
        deadline's lateness the callbacks queued before it, for a deadline inside the
        current loop turn, which those callbacks would have held up anyway.
        """
        if self._holds:
            self._rearm_due = True
        elif not self._flush_queued:
            self._flush_queued = True
            if self._ready is not None:
                self._ready.append(self._flush_handle)
            else:
                self.loop.call_soon(self._flush_rearm, context=self._context)


class LoopTimer(Timer):
    """Portable timer on ``loop.call_at`` that re-arms itself when woken early.

    Never early, under any loop; as late as the loop's own timers (about 0.5-1 ms on the
    default loop).  When uvloop rounds a short remaining delay to zero, the re-arming
    spins through loop iterations for the rest of that millisecond: correct, not cheap.
    """

    name = "loop"

    def __init__(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        """Create a timer for ``loop`` (the running loop by default)."""
        super().__init__(loop or asyncio.get_running_loop())
        self._wakeup: asyncio.TimerHandle | None = None
        self._armed_at: float | None = None

    def _arm(self, deadline: float) -> None:
        if self._armed_at == deadline:
            return
        self._disarm()
        loop = self.loop
        # loop.time() need not be time.monotonic() (uvloop counts whole milliseconds), so
        # the deadline becomes a delay on the loop's own clock.
        delay = max(0.0, deadline - self.now())
        self._wakeup = loop.call_at(loop.time() + delay, self._on_wakeup)
        self._armed_at = deadline

    def _disarm(self) -> None:
        if self._wakeup is not None:
            self._wakeup.cancel()
        self._wakeup = None
        self._armed_at = None

    def _release(self) -> None:
        self._disarm()

    def _on_wakeup(self) -> None:
        self._wakeup = None
        self._armed_at = None
        self._wake()


class TimerfdTimer(Timer):
    """Linux timer: one ``timerfd`` on absolute ``CLOCK_MONOTONIC`` deadlines.

    The fd is armed at the earliest pending deadline and watched with
    ``loop.add_reader``.  A bare timerfd wake-up is 40-70 us late at p50 and 100-120 us
    at p99 here (docs/platform.md 1, benchmarks/bench_timer.py) - and on an idle
    machine, whose cores sleep deeply, ~300 us p50 and ~500 us p99
    (benchmarks/bench_wakeups.py).  Never early.

    Spinning is only on request: real-time mode (``--realtime``, ``MOTORBUS_REALTIME``,
    ``motorbus.runtime.realtime.enable``, on or asked for when the timer is made), the
    environment variable ``MOTORBUS_TIMER_SPIN_US`` (the longest lead in us; 0 keeps it
    off), or ``spin_lead=``.  The fd then fires ``spin_lead`` seconds before a precise
    deadline (a lead of 60-500 us that follows the recent lateness of precise deadlines'
    wake-ups that the loop's own work did not hold up) and the wake-up spins on the clock
    for the rest: a deadline fires within ~25 us at p99, for at most the lead in CPU per
    wake-up (bench_wakeups.py: timer callback lateness).  What it costs is counted from
    outside: ``wake_observer`` is told each wake-up and its spin (the benchmarks'
    ``harness.TimerProbe``); the timer keeps no counters.
    """

    name = "timerfd"
    _LAZY = True
    #: The longest the fd fires before a deadline, to spin the rest (seconds), where
    #: spinning is asked for (``MOTORBUS_TIMER_SPIN_US`` sets it; see the class).
    SPIN_LEAD_S = float(os.environ.get(SPIN_ENV_VAR) or "500") * 1e-6
    #: The shortest lead, whatever the recent wake-ups did.
    SPIN_LEAD_MIN_S = 60e-6
    #: The lead follows twice the recent worst lateness of the wake-ups armed for a
    #: precise deadline, which decays by this factor a wake-up: a busy machine wakes
    #: promptly and spins little, an idle one (deep C-states) wakes late and gets the
    #: full lead.  A wake-up later than the longest lead covers counts as half of it
    #: (``_on_expiry``).  Counting the plain deadlines' wake-ups too (a poll task's sleep,
    #: which lands where the loop is busy) held the lead near its maximum with 32 buses: 16 %
    #: of a core spun, 6 % without them (benchmarks/README.md).  (A lead of the recent p99
    #: lateness instead spent as much CPU here and let p99 tick jitter grow from
    #: 150-170 to 185-190 us: bench_late_ticks.py, 2026-12-02.)
    LATENESS_DECAY = 0.98

    def __init__(
        self, loop: asyncio.AbstractEventLoop | None = None, *, spin_lead: float | None = None
    ) -> None:
        """Create the timer and its timerfd for ``loop`` (the running loop by default).

        ``spin_lead``: the longest spin before a precise deadline (s); ``None`` (the
        default) spins ``SPIN_LEAD_S`` only where spinning is asked for (see the class),
        else not at all.

        Raises:
            OSError: ``timerfd`` is not available.
        """
        super().__init__(loop or asyncio.get_running_loop())
        if spin_lead is None:
            spin_lead = self.SPIN_LEAD_S if spin_asked() else 0.0
        self._spin_lead = spin_lead
        # The fd fires up to the spin lead before a precise deadline: the handover too.
        self._handover_s = self.HANDOVER_S + spin_lead
        self._wake_late = self._spin_lead / 2  # start cautious: assume a slow wake-up
        if not spin_lead and type(self).now is TimerfdTimer.now:
            # Only the spin lead reads ``_seen``: without it, the clock is the C function.
            self.now = time.monotonic  # type: ignore[method-assign]
        self._api = _api()
        self._fd = self._api.create()
        # Closes the fd if the timer is dropped without close() (its loop went away).
        self._finalizer = weakref.finalize(self, os.close, self._fd)
        self._armed_ns = 0
        #: Whether the fd is armed for a precise deadline (the lead follows only those).
        self._armed_precise = False
        self._reading = False
        #: Called on each fd wake-up as ``(armed, woke, spun_until)`` (``time.monotonic``
        #: seconds; ``armed`` is 0.0 for a wake-up nobody armed): for tools that find out
        #: why a deadline was late.  Keep it short; it runs before the due callbacks.
        self.wake_observer: Callable[[float, float, float], None] | None = None
        #: The latest clock reading handed out: the loop was running our code then.
        self._seen = 0.0

    def now(self) -> float:
        """Return the current time (``time.monotonic()``), and note that the loop was
        busy with motorbus's work at it (see ``_on_expiry``)."""
        self._seen = t = time.monotonic()
        return t

    def _arm(self, deadline: float) -> None:
        if not self._reading:
            self.loop.add_reader(self._fd, self._on_expiry)
            self._reading = True
        heap = self._heap
        precise = bool(heap) and heap[0][2].precise
        if precise and self._spin_lead:
            deadline -= self._current_lead()
        # Up to whole ns, never before the deadline; at least 1 (all zero disarms the fd).
        ns = math.ceil(deadline * _NS_PER_S)
        if ns < 1:
            ns = 1
        if ns != self._armed_ns:
            self._api.set_absolute_ns(self._fd, ns)
            self._armed_ns = ns
            self._armed_precise = precise

    def _current_lead(self) -> float:
        if not self._spin_lead:
            return 0.0
        return min(self._spin_lead, max(self.SPIN_LEAD_MIN_S, 2 * self._wake_late))

    @property
    def lead(self) -> float:
        """How long before a precise deadline the fd fires now, to spin the rest (s)."""
        return self._current_lead()

    def _disarm(self) -> None:
        if self._armed_ns:
            self._api.set_absolute_ns(self._fd, 0)
            self._armed_ns = 0

    def _release(self) -> None:
        loop = self._loop_ref()
        if self._reading and loop is not None and not loop.is_closed():
            loop.remove_reader(self._fd)
        self._reading = False
        self._finalizer()

    def _on_expiry(self) -> None:
        busy_until = self._seen  # before now() below moves it
        # Nothing to read after a spurious wake-up or a re-arm that followed the expiry.
        try:  # noqa: SIM105  (contextlib.suppress: three calls more a wake-up)
            os.read(self._fd, _EXPIRY_COUNT_SIZE)
        except BlockingIOError:
            pass
        # The fd expired, so the armed time has passed: forget it, or re-arming at the
        # same deadline (woken early by float rounding) would be skipped as a no-op.
        woke = self.now()
        armed = self._armed_ns / _NS_PER_S
        # The lead is for the kernel's part of a wake-up's lateness, so it follows only
        # the wake-ups that show it (and only with a spin): armed for a precise deadline
        # (a plain one lands wherever the loop is busy), with the loop idle from the
        # arming on (if the clock was read since, motorbus's work ran and the wake-up may
        # have waited for it: the loop's lateness, neither to raise the lead nor to wear
        # it down; counted, a third of the CPU spun with 16 buses: benchmarks/README.md,
        # "Spin lead").  Clipped at half the longest lead: a wake-up later than that (the
        # thread descheduled; one 30 ms outlier held the lead at its maximum for ~250
        # wake-ups) is no reason to spin longer.
        if self._spin_lead and self._armed_ns and self._armed_precise and busy_until <= armed:
            late = min(woke - armed, self._spin_lead / 2)
            self._wake_late = max(late, self._wake_late * self.LATENESS_DECAY)
        self._armed_ns = 0
        spun_until = woke
        heap = self._heap
        if heap and self._spin_lead and heap[0][2].precise and not heap[0][2]._cancelled:
            first = heap[0][0]
            if woke < first <= woke + self._current_lead() + self.SPIN_LEAD_MIN_S:
                clock = time.monotonic
                while (spun_until := clock()) < first:
                    pass  # the last microseconds: a timer wake-up cannot be this precise
        if self.wake_observer is not None:
            self.wake_observer(armed, woke, spun_until)
        self._wake(spun_until)  # the latest clock reading: nothing due by then runs early


_timers: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Timer] = weakref.WeakKeyDictionary()


def default_timer(loop: asyncio.AbstractEventLoop | None = None) -> Timer:
    """Return the shared timer of ``loop`` (the running loop by default), creating it once.

    A :class:`TimerfdTimer` on Linux, else (or if ``timerfd`` fails) a :class:`LoopTimer`.

    Raises:
        RuntimeError: no loop given and none running.
    """
    loop = loop or asyncio.get_running_loop()
    timer = _timers.get(loop)
    if timer is None or timer._closed:
        timer = _make_timer(loop)
        _timers[loop] = timer
    return timer


def _make_timer(loop: asyncio.AbstractEventLoop) -> Timer:
    if sys.platform.startswith("linux"):
        try:
            return TimerfdTimer(loop)
        except (OSError, AttributeError) as err:
            _log.debug("timerfd unavailable (%s): falling back to LoopTimer", err)
    return LoopTimer(loop)
