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
* the process's system calls, entry and return (kernel clock, the same trace as ``W``),
  but those the loop sleeps in (``epoll_wait``: its ``select``);
* the loop's slow callbacks (longer than ``bench_late_ticks.SLOW_CALLBACK_S``): start,
  stop and what ran (a task's coroutine, or the callback's name);
* the thread's CPU time (``CLOCK_THREAD_CPUTIME_ID``) at every ``select``'s entry and
  return and at every tick's write: where the thread was awake (out of ``select``), how
  much of the time it really ran.

:func:`attribute` names, for every tick later than the threshold, the first cause that
explains at least half of its lateness:

``gc``
    a garbage collection overlapped the tick, from the timer's arming to the write;
``machine: run queue``
    the thread waited that long for a CPU since the previous tick (another process,
    or a CPU hog, had it);
``machine: system call held``
    from the timer's arming to the tick's write, the loop was that long inside system
    calls (a poll's ``write(2)``, a ``read(2)`` of a reply, the timer's
    ``timerfd_settime``, even ``getpid``): each is microseconds of work, so time beyond
    that is the kernel's (a pty's lock, the process on its other end) or the
    hypervisor's (on this project's VM, single calls of each kind took 0.3-5 ms:
    ``benchmarks/README.md``, "bench_late_ticks.py");
``machine: CPU taken away``
    from the timer's arming to the write, the thread was awake (out of ``select``) that
    much longer than it ran, beyond its run-queue wait and its system calls: it
    was neither running, nor waiting for a CPU in this kernel, nor in a system call.  On
    a VM whose kernel accounts steal time (``CONFIG_PARAVIRT_TIME_ACCOUNTING``: a
    thread's CPU time leaves out what the hypervisor took), that is the hypervisor
    running something else on this vCPU;
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
    "machine: system call held",
    "machine: CPU taken away",
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
    #: The process's system calls but the loop's waits: (entered, returned), in order
    #: (none: not traced).
    syscalls: Sequence[tuple[float, float]] = ()
    #: The thread's CPU time: (host time, CPU seconds, 1.0 if it is awake from there to
    #: the next sample, 0.0 if it sleeps in ``select``), in order (none: not recorded).
    thread_cpu: Sequence[tuple[float, float, float]] = ()
    #: The loop's slow callbacks: (start, stop, what ran), in order.
    slow_callbacks: Sequence[tuple[float, float, str]] = ()


@dataclass(frozen=True, slots=True)
class LateTick:
    """One late tick and the figures its cause was chosen from (µs)."""

    index: int
    late_us: float
    cause: str
    gc_us: float
    runqueue_us: float
    syscalls_us: float
    taken_us: float
    loop_busy_us: float
    wakeup_us: float
    wake_to_write_us: float
    #: The most of the thread's own CPU time that can fall between the arming and the
    #: write (``taken_us`` is the least of its time off the CPU that must).
    on_cpu_us: float = 0.0
    #: The longest slow callback that ran between the arming and the write, and how
    #: long it ran ("" if none): what "ours" names.
    callback: str = ""

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


def _awake_off_cpu(
    samples: Sequence[tuple[float, float, float]], lo: float, hi: float
) -> tuple[float, float]:
    """(off CPU, on CPU) inside ``[lo, hi]`` while the thread was awake.

    Between two samples the clocks say how long the thread ran, not when: "off" is the
    least of its time off the CPU that must fall inside the window (all of it that
    could not fit in the stretch's part outside), "on" the most of its running that
    could.  So the machine is blamed for no more, and our code for no less, than the
    samples show.
    """
    off = on = 0.0
    i = max(0, bisect.bisect_right([t for t, _, _ in samples], lo) - 1)
    for (t0, c0, awake), (t1, c1, _) in zip(samples[i:], samples[i + 1 :], strict=False):
        if t0 >= hi:
            break
        if not awake or t1 <= lo or t1 <= t0:
            continue
        inside = min(t1, hi) - max(t0, lo)
        ran = max(0.0, c1 - c0)
        away = max(0.0, (t1 - t0) - ran)
        off += max(0.0, away - ((t1 - t0) - inside))
        on += min(ran, inside)
    return off, on


def _longest_callback(callbacks: Sequence[tuple[float, float, str]], lo: float, hi: float) -> str:
    """The longest of ``callbacks`` that overlaps ``[lo, hi]``, with its length."""
    best = max(
        ((stop - start, what) for start, stop, what in callbacks if stop > lo and start < hi),
        default=None,
    )
    return "" if best is None else f"{best[1]} ({best[0] * 1e6:,.0f} us)"


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
        off_cpu, on_cpu = _awake_off_cpu(records.thread_cpu, armed, write)
        # What neither the run queue nor a system call explains (both subtracted whole:
        # never more taken away than the thread's own clocks show).
        taken = max(0.0, off_cpu - queued - held)
        busy, wakeup = _loop_at(records.selects, armed)
        if wake is not None and wake[1] - armed > busy + wakeup:
            # The rest of the wake-up's lateness, out of select: callbacks that ran first.
            busy = wake[1] - armed - wakeup
        to_write = write - max(deadline, wake[2]) if wake is not None else 0.0
        need = SHARE * late
        figures = (gc, queued, held, taken, busy, wakeup, to_write)
        cause = next((c for c, v in zip(CAUSES, figures, strict=False) if v >= need), CAUSES[-1])
        out.append(
            LateTick(
                index=k,
                late_us=late * 1e6,
                cause=cause,
                gc_us=gc * 1e6,
                runqueue_us=queued * 1e6,
                syscalls_us=held * 1e6,
                taken_us=taken * 1e6,
                loop_busy_us=busy * 1e6,
                wakeup_us=wakeup * 1e6,
                wake_to_write_us=to_write * 1e6,
                on_cpu_us=on_cpu * 1e6,
                callback=_longest_callback(records.slow_callbacks, armed, write),
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
