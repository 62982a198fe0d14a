"""Why was a tick late?  The pure attribution of ``bench_late_ticks.py``.

A stream tick is due at its deadline ``D`` (``origin + k * period``) and reached the
kernel at ``W`` (the ``write(2)`` of its 0xF3 broadcast, kernel clock).  Around it the
bus process recorded, on the same ``CLOCK_MONOTONIC`` clock:

* the timer's wake-ups (``TimerfdTimer.wake_observer``): when the timerfd was armed to
  fire (``D`` minus the spin lead), when the callback ran, and until when it spun;
* the event loop's ``select`` calls: when each was entered and when it returned;
* garbage collections (``gc.callbacks``): start and stop;
* the thread's run-queue wait (``/proc/thread-self/schedstat``, second field) read at
  every tick's write: time the thread was runnable but another task had the CPU;
* the process's ``write(2)`` calls, entry and return (kernel clock, the same trace as
  ``W``).

:func:`attribute` names, for every tick later than the threshold, the first cause that
explains at least half of its lateness:

``gc``
    a garbage collection overlapped the tick, from the timer's arming to the write;
``machine: run queue``
    the thread waited that long for a CPU since the previous tick (another process,
    or a CPU hog, had it);
``machine: write(2) held``
    from the timer's arming to the tick's write, the loop was that long inside
    ``write(2)`` calls of other frames (a poll): the kernel held them (a pty's lock,
    the process on its other end, a vCPU the hypervisor took away); a UART driver with
    room in its buffer returns at once;
``ours: loop busy``
    from the timerfd's firing to the timer's callback, the loop ran other callbacks
    that long: it was running them when the timerfd fired and went on before it looked
    at its fds again, or the look that found the timerfd ready found other work too,
    which ran first (our code, or an application's callback);
``machine: slow wake-up``
    the loop was waiting in ``select`` and it returned that late after the timerfd
    fired, without run-queue wait (a CPU leaving a deep idle state, a hypervisor);
``ours: wake to write``
    the timer woke in time, but the frame left that long after the deadline (work in
    callbacks due before it, or the bus holding the frame);
``unattributed``
    none of these explains half of it (the figures are reported anyway).

Pure: numbers in, a table out; unit-tested in ``tests/test_late_ticks.py``.
"""

from __future__ import annotations

import bisect
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass

__all__ = ["CAUSES", "LateTick", "TickRecords", "attribute", "summarise"]

CAUSES = (
    "gc",
    "machine: run queue",
    "machine: write(2) held",
    "ours: loop busy",
    "machine: slow wake-up",
    "ours: wake to write",
    "unattributed",
)
#: A cause must explain at least this share of a tick's lateness.
SHARE = 0.5
#: How far before a deadline the wake-up that serves it may have been armed (s): the
#: timer's largest spin lead plus room.
ARM_WINDOW_S = 0.001


@dataclass(frozen=True, slots=True)
class TickRecords:
    """What the bus process recorded during a run (times in seconds, one clock)."""

    #: The ticks' deadlines, in order.
    deadlines: Sequence[float]
    #: The kernel's entry into write(2) of each tick's broadcast, in order.
    writes: Sequence[float]
    #: Timer wake-ups: (armed, woke, spun until), in order.
    wakeups: Sequence[tuple[float, float, float]]
    #: The loop's select calls: (entered, returned), in order.
    selects: Sequence[tuple[float, float]]
    #: Garbage collections: (start, stop), in order.
    collections: Sequence[tuple[float, float]]
    #: (host time, cumulative run-queue wait in seconds), read at each tick's write.
    runqueue: Sequence[tuple[float, float]]
    #: The process's write(2) calls: (entered, returned), in order (none: not traced).
    syscalls: Sequence[tuple[float, float]] = ()


@dataclass(frozen=True, slots=True)
class LateTick:
    """One late tick and the figures its cause was chosen from (µs)."""

    index: int
    late_us: float
    cause: str
    gc_us: float
    runqueue_us: float
    write_calls_us: float
    loop_busy_us: float
    wakeup_us: float
    wake_to_write_us: float

    def as_dict(self) -> dict[str, float | int | str]:
        return {k: round(v, 1) if isinstance(v, float) else v for k, v in asdict(self).items()}


def _deadline_of(write: float, deadlines: Sequence[float]) -> int | None:
    """Index of the last deadline at or before ``write`` (a write is never early)."""
    i = bisect.bisect_right(deadlines, write) - 1
    return i if i >= 0 else None


def _overlap(intervals: Sequence[tuple[float, float]], lo: float, hi: float) -> float:
    """Total time of ``intervals`` inside ``[lo, hi]``."""
    total = 0.0
    for start, stop in intervals:
        if stop > lo and start < hi:
            total += min(stop, hi) - max(start, lo)
    return total


def _runqueue_between(runqueue: Sequence[tuple[float, float]], lo: float, hi: float) -> float:
    """Run-queue wait accumulated between the samples nearest ``lo`` and ``hi``."""
    times = [t for t, _ in runqueue]
    i = bisect.bisect_right(times, lo) - 1
    j = bisect.bisect_left(times, hi)
    if i < 0 or j >= len(runqueue):
        return 0.0
    return max(0.0, runqueue[j][1] - runqueue[i][1])


def _loop_at(selects: Sequence[tuple[float, float]], t: float) -> tuple[float, float]:
    """(busy, wake-up delay) at ``t``: how long the loop went on running callbacks after
    ``t`` before it entered ``select`` again, or, if it was in ``select`` at ``t``, how
    long after ``t`` that call returned."""
    entered = [s for s, _ in selects]
    i = bisect.bisect_right(entered, t) - 1
    if i >= 0 and selects[i][1] > t:
        return 0.0, selects[i][1] - t
    nxt = i + 1
    if nxt < len(selects):
        return selects[nxt][0] - t, 0.0
    return 0.0, 0.0


def attribute(records: TickRecords, threshold: float = 500e-6) -> list[LateTick]:
    """Every tick whose write came more than ``threshold`` after its deadline, with the
    first cause (in ``CAUSES`` order) that explains ``SHARE`` of its lateness."""
    deadlines = list(records.deadlines)
    woke_at = [w for _, w, _ in records.wakeups]
    previous_write = None
    out: list[LateTick] = []
    for write in records.writes:
        k = _deadline_of(write, deadlines)
        since = previous_write
        previous_write = write
        if k is None:
            continue
        deadline = deadlines[k]
        late = write - deadline
        if late <= threshold:
            continue
        # The wake-up that served this tick: the last one before the write, armed for it.
        j = bisect.bisect_right(woke_at, write) - 1
        wake = records.wakeups[j] if j >= 0 else None
        if wake is not None and not deadline - ARM_WINDOW_S <= wake[0] <= deadline:
            wake = None
        armed = wake[0] if wake is not None and wake[0] > 0 else deadline
        gc = _overlap(records.collections, armed, write)
        queued = _runqueue_between(records.runqueue, since if since is not None else armed, write)
        held = _overlap(records.syscalls, armed, write)  # the tick's own call starts at write
        busy, wakeup = _loop_at(records.selects, armed)
        if wake is not None and wake[1] - armed > busy + wakeup:
            # The rest of the wake-up's lateness, out of select: callbacks that ran first.
            busy = wake[1] - armed - wakeup
        to_write = write - max(deadline, wake[2]) if wake is not None else 0.0
        need = SHARE * late
        figures = (gc, queued, held, busy, wakeup, to_write)
        cause = next((c for c, v in zip(CAUSES, figures, strict=False) if v >= need), CAUSES[-1])
        out.append(
            LateTick(
                index=k,
                late_us=late * 1e6,
                cause=cause,
                gc_us=gc * 1e6,
                runqueue_us=queued * 1e6,
                write_calls_us=held * 1e6,
                loop_busy_us=busy * 1e6,
                wakeup_us=wakeup * 1e6,
                wake_to_write_us=to_write * 1e6,
            )
        )
    return out


def summarise(late: Sequence[LateTick]) -> dict[str, dict[str, float]]:
    """Per cause: how many late ticks, and the worst lateness (µs)."""
    counts = Counter(t.cause for t in late)
    return {
        cause: {
            "ticks": counts[cause],
            "worst_us": round(max((t.late_us for t in late if t.cause == cause), default=0.0), 1),
        }
        for cause in CAUSES
    }
