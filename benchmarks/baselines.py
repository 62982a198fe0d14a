"""Hand-written tick loops, no bus and no motorbus timer: the baselines a sceptic accepts.

Issue 23.  Each loop writes the same frame (``frame(k)``, the caller's: in
``bench_stream.py`` the 15-entry 0xF3 follow broadcast of tick ``k``, built each tick
with ``motorbus.protocol.la`` as ``bench_cpu.py``'s minimal loop does) with
``os.write`` to raw, non-blocking ptys, once per ``period`` on an absolute grid
``origin + k * period`` (ports staggered by ``period / ports``), for ``seconds``:

* ``sleep``: ``await asyncio.sleep(deadline - loop.time())`` to each absolute deadline:
  the loop a careful user writes (it does not drift, unlike send-then-sleep);
* ``timerfd``: a bare ``timerfd`` armed at each absolute deadline
  (``TFD_TIMER_ABSTIME``, ``CLOCK_MONOTONIC``) and read by an ``add_reader`` callback
  that writes the frames: the floor of CPU per tick for an event-loop program;
* ``timerfd_spin``: the same timerfd armed ``spin`` earlier, then a busy-wait on
  ``time.monotonic()`` to the deadline: the floor of jitter, at full CPU cost for
  the last stretch of every tick.

``polled_timerfd_loop`` runs the last two with ``bench_cpu.py``'s heavier work (a status
query after each tick, its reply read) on many buses spread over tick phases as
``BusManager`` spreads them: baselines (b) and (c) of its CPU ratios.

Every loop returns this process's CPU seconds from its first tick's lead-in to its
last tick (the event loop already running, ports open), the wall seconds and the ticks
written; the tick times are measured from outside (``kernel_clock.py``: the
kernel's clock of each ``write(2)``), as for motorbus's streams.  Used by
``bench_stream.py`` (jitter) and ``bench_cpu.py``-style CPU per tick.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import ctypes.util
import os
import resource
import time
import tty
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

#: The baselines, in the order reports show them.
BASELINES = ("sleep", "timerfd", "timerfd_spin")
#: Busy-wait stretch of ``timerfd_spin`` before each deadline (covers a typical wake-up
#: lateness of 100-300 µs on a quiet machine).
SPIN_S = 0.0005
#: Start-up room before the first tick.
LEAD_S = 0.05
#: How long ``polled_timerfd_loop`` waits after its run for replies still on their way.
REPLY_GRACE_S = 1.0

_CLOCK_MONOTONIC = 1
_TFD_TIMER_ABSTIME = 1
_NS = 1_000_000_000


class _TimeSpec(ctypes.Structure):
    _fields_ = (("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long))


class _ITimerSpec(ctypes.Structure):
    _fields_ = (("it_interval", _TimeSpec), ("it_value", _TimeSpec))


class _Timerfd:
    """One CLOCK_MONOTONIC timerfd, armed at absolute times (libc through ctypes)."""

    def __init__(self) -> None:
        self._libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        self._libc.timerfd_create.argtypes = (ctypes.c_int, ctypes.c_int)
        self._libc.timerfd_settime.argtypes = (
            ctypes.c_int,
            ctypes.c_int,
            ctypes.POINTER(_ITimerSpec),
            ctypes.c_void_p,
        )
        self.fd = self._libc.timerfd_create(_CLOCK_MONOTONIC, os.O_NONBLOCK | os.O_CLOEXEC)
        if self.fd < 0:
            raise OSError(ctypes.get_errno(), "timerfd_create")
        self._spec = _ITimerSpec()
        self._ref = ctypes.byref(self._spec)

    def arm(self, deadline_s: float) -> None:
        """Expire once at ``deadline_s`` on ``time.monotonic()``'s clock."""
        value = self._spec.it_value
        value.tv_sec, value.tv_nsec = divmod(round(deadline_s * _NS), _NS)
        if self._libc.timerfd_settime(self.fd, _TFD_TIMER_ABSTIME, self._ref, None) < 0:
            raise OSError(ctypes.get_errno(), "timerfd_settime")

    def close(self) -> None:
        os.close(self.fd)


@dataclass
class LoopResult:
    """What one baseline run cost: CPU and wall seconds of this process, ticks written."""

    name: str
    cpu_s: float
    wall_s: float
    ticks: int
    ports: int

    @property
    def cpu_percent(self) -> float:
        return 100 * self.cpu_s / self.wall_s if self.wall_s else float("nan")

    @property
    def cpu_us_per_bus_tick(self) -> float:
        return 1e6 * self.cpu_s / self.ticks if self.ticks else float("nan")

    def as_dict(self) -> dict[str, Any]:
        return {
            "cpu_percent": round(self.cpu_percent, 2),
            "cpu_us_per_bus_tick": round(self.cpu_us_per_bus_tick, 1),
            "ticks": self.ticks,
            "ports": self.ports,
            "wall_s": round(self.wall_s, 3),
        }


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _open_raw(paths: Sequence[str]) -> list[int]:
    fds = []
    for path in paths:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(fd)
        fds.append(fd)
    return fds


def _write(fd: int, data: bytes) -> None:
    with contextlib.suppress(BlockingIOError):  # a full pty drops the frame, as a UART would not
        os.write(fd, data)


async def _sleep_loop(
    fds: list[int], frame: Callable[[int], bytes], period: float, ticks: int
) -> tuple[float, float]:
    loop = asyncio.get_running_loop()
    wall0, cpu0 = time.monotonic(), _cpu_seconds()
    origin = loop.time() + LEAD_S

    async def one(i: int) -> None:
        start = origin + i * period / len(fds)
        for k in range(ticks):
            deadline = start + k * period
            delay = deadline - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            _write(fds[i], frame(k))

    await asyncio.gather(*(one(i) for i in range(len(fds))))
    return time.monotonic() - wall0, _cpu_seconds() - cpu0


async def _timerfd_loop(
    fds: list[int], frame: Callable[[int], bytes], period: float, ticks: int, spin: float
) -> tuple[float, float]:
    """One timerfd per port, re-armed at each absolute deadline (minus ``spin``)."""
    loop = asyncio.get_running_loop()
    timers = [_Timerfd() for _ in fds]  # set-up (libc look-up), not counted
    wall0, cpu0 = time.monotonic(), _cpu_seconds()
    origin = time.monotonic() + LEAD_S  # the loop's clock is time.monotonic on Linux
    done = loop.create_future()
    left = [len(fds)]
    counts = [0] * len(fds)

    def on_expiry(i: int) -> None:
        timer = timers[i]
        with contextlib.suppress(BlockingIOError):
            os.read(timer.fd, 8)
        k = counts[i]
        deadline = origin + i * period / len(fds) + k * period
        if spin:
            while time.monotonic() < deadline:
                pass
        _write(fds[i], frame(k))
        counts[i] = k + 1
        if k + 1 < ticks:
            timer.arm(deadline + period - spin)
        else:
            loop.remove_reader(timer.fd)
            left[0] -= 1
            if left[0] == 0:
                done.set_result(None)

    for i, timer in enumerate(timers):
        loop.add_reader(timer.fd, on_expiry, i)
        timer.arm(origin + i * period / len(fds) - spin)
    try:
        await done
        return time.monotonic() - wall0, _cpu_seconds() - cpu0
    finally:
        for timer in timers:
            loop.remove_reader(timer.fd)
            timer.close()


@dataclass(frozen=True)
class PolledWork:
    """``bench_cpu.py``'s work per bus and tick: a broadcast, then a status query.

    Attributes:
        frame: the tick's frame, ``frame(k)`` for tick ``k`` (built for each bus, each
            tick, as a bus's stream does).
        queries: the query frames, one per tick, round-robin; none, no queries (the
            ticks alone).
        reply_size: bytes of one reply (replies are counted as bytes read / this).
        period: tick period, seconds.
        poll_offset: how long after its bus's tick a query is written, seconds.
        phases: the tick phases the buses are spread over: bus ``i`` ticks
            ``(i % phases) * period / phases`` into each period, as ``BusManager``
            spreads its buses, and the buses of a phase share one wake-up.
    """

    frame: Callable[[int], bytes]
    queries: Sequence[bytes]
    reply_size: int
    period: float
    poll_offset: float
    phases: int


async def polled_timerfd_loop(
    paths: Sequence[str], work: PolledWork, seconds: float, *, spin: float
) -> dict[str, Any]:
    """``work`` on ``paths`` by hand: baselines (b) and (c) with many buses and queries.

    One timerfd per tick phase, armed in turn at the phase's tick (``spin`` early and
    then a busy-wait to the deadline, when ``spin`` > 0: baseline (c)) and at its
    queries, ``poll_offset`` later (no busy-wait: queries need no precision here, as in
    ``bench_cpu.py``'s other loops).  Each pty's ``add_reader`` callback reads replies.
    No framing, no matching, no timeouts, no spacing rule.

    Returns:
        ``cpu_percent``, ``cpu_s``, ``wall_s``, ``ticks``, ``polls`` and ``replies``,
        counted as ``bench_cpu.minimal`` counts them.
    """
    loop = asyncio.get_running_loop()
    fds = _open_raw(paths)
    phases = max(1, min(work.phases, len(fds)))
    groups = [fds[g::phases] for g in range(phases)]
    timers = [_Timerfd() for _ in groups]  # set-up (libc look-up), not counted
    received = [0] * len(fds)
    ticks = max(1, round(seconds / work.period))
    counts = {"ticks": 0, "polls": 0}
    done = loop.create_future()
    left = [phases]
    # Phase g's step s: tick s // 2 when s is even, that tick's queries when s is odd.
    steps = [0] * phases
    origin = time.monotonic() + LEAD_S  # the loop's clock is time.monotonic on Linux

    def due(g: int, s: int) -> float:
        k, polls = divmod(s, 2)
        return origin + g * work.period / phases + k * work.period + polls * work.poll_offset

    def on_readable(i: int) -> None:
        with contextlib.suppress(BlockingIOError):
            received[i] += len(os.read(fds[i], 4096))

    def on_expiry(g: int) -> None:
        timer = timers[g]
        with contextlib.suppress(BlockingIOError):
            os.read(timer.fd, 8)
        s = steps[g]
        k, polls = divmod(s, 2)
        if polls:
            query = work.queries[k % len(work.queries)]
            for fd in groups[g]:
                _write(fd, query)
            counts["polls"] += len(groups[g])
        else:
            if spin:
                deadline = due(g, s)
                while time.monotonic() < deadline:
                    pass
            for fd in groups[g]:
                _write(fd, work.frame(k))
            counts["ticks"] += len(groups[g])
            if not work.queries:
                s += 1  # no query step
        steps[g] = s = s + 1
        if s < 2 * ticks:
            timer.arm(due(g, s) - (spin if s % 2 == 0 else 0.0))
        else:
            loop.remove_reader(timer.fd)
            left[0] -= 1
            if left[0] == 0:
                done.set_result(None)

    for i, fd in enumerate(fds):
        loop.add_reader(fd, on_readable, i)
    wall0, cpu0 = time.monotonic(), _cpu_seconds()
    for g, timer in enumerate(timers):
        loop.add_reader(timer.fd, on_expiry, g)
        timer.arm(due(g, 0) - spin)
    try:
        await done
        await asyncio.sleep(work.poll_offset)  # the last replies, as the other loops wait
        wall, cpu = time.monotonic() - wall0, _cpu_seconds() - cpu0
        # Replies a loaded machine delivers later still count (not their CPU): a reply
        # count short of the polls then means lost replies, not a slow responder.
        owed = counts["polls"] * work.reply_size
        give_up = time.monotonic() + REPLY_GRACE_S
        while sum(received) < owed and time.monotonic() < give_up:
            await asyncio.sleep(0.005)
    finally:
        for timer in timers:
            loop.remove_reader(timer.fd)
            timer.close()
        for fd in fds:
            loop.remove_reader(fd)
            os.close(fd)
    return polled_result(cpu, wall, counts, sum(received) // work.reply_size)


def polled_result(
    cpu_s: float, wall_s: float, counts: dict[str, int], replies: int
) -> dict[str, Any]:
    """What a loop of ``bench_cpu.py``'s work reports: ``cpu_percent``, ``cpu_s``,
    ``wall_s``, ``ticks`` and ``polls`` (from ``counts``), ``replies``."""
    return {
        "cpu_percent": 100 * cpu_s / wall_s,
        "cpu_s": cpu_s,
        "wall_s": wall_s,
        "ticks": counts["ticks"],
        "polls": counts["polls"],
        "replies": replies,
    }


def run_baseline(
    name: str, paths: Sequence[str], frame: Callable[[int], bytes], period: float, seconds: float
) -> LoopResult:
    """Run baseline ``name`` on ``paths`` for ``seconds``; its CPU, wall time and ticks."""
    if name not in BASELINES:
        raise ValueError(f"baseline {name!r}: choose one of {', '.join(BASELINES)}")
    ticks = round(seconds / period)
    fds = _open_raw(paths)
    try:
        if name == "sleep":
            wall, cpu = asyncio.run(_sleep_loop(fds, frame, period, ticks))
        else:
            spin = SPIN_S if name == "timerfd_spin" else 0.0
            wall, cpu = asyncio.run(_timerfd_loop(fds, frame, period, ticks, spin))
    finally:
        for fd in fds:
            os.close(fd)
    return LoopResult(name, cpu, wall, ticks * len(fds), len(fds))
