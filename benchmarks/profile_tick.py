"""Where the CPU of one bus-tick goes: README's stream under cProfile, per tick.

Streams 15 actuators at 10 ms (one 0xF3 broadcast a tick, ``poll_status=True``) over a
real pty to ``motorbus sim`` in a child process for ``--seconds``, under cProfile, and
prints the functions that take the most CPU, in microseconds per tick (self time and
cumulative), plus, measured without the profiler in the same run, the process CPU per
tick and how long after each tick's deadline the bus called the transport's ``write``
with the tick's frame (the Python work at the deadline; the kernel's own view of the
write is ``bench_late_ticks.py``'s), and the calls a tick (every Python and C function
call cProfile saw in this process, the loop's own included, over the ticks: a count,
which does not move with the machine; this tick also carries a status poll, so it is
more than ``tests/bus/test_call_budget.py``'s bare tick).
Writes ``benchmarks/results/profile_tick.json``.

Usage: ``python benchmarks/profile_tick.py [--seconds 5] [--top 25] [--out PATH]``
"""

from __future__ import annotations

import argparse
import asyncio
import bisect
import cProfile
import math
import pstats
import time
from pathlib import Path
from typing import Any

import motorbus
from harness import TimerProbe, write_report
from motorbus.sim.process import SimProcess

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "profile_tick.json"
PERIOD_S = 0.01
IDS = range(1, 16)


def percentile(values: list[float], p: float) -> float:
    """Nearest-rank percentile of ``values`` (0 when empty)."""
    if not values:
        return 0.0
    ordered = sorted(values)
    return ordered[max(0, math.ceil(len(ordered) * p / 100) - 1)]


async def stream(path: str, seconds: float) -> dict[str, Any]:
    transport = motorbus.open_transport(path, baudrate=921600)
    writes: list[float] = []  # when the bus called write(), time.monotonic()
    write = transport.write

    def timed_write(data: bytes) -> None:
        writes.append(time.monotonic())
        write(data)

    transport.write = timed_write  # type: ignore[method-assign]
    async with motorbus.Bus(transport, families=[motorbus.Family.LA]) as bus:
        actuators = [motorbus.InspireLA(bus, i) for i in IDS]
        for a in actuators:
            await a.enable()
        ticks = round(seconds / PERIOD_S)
        rows = [[1000 + 400 * math.sin(k / 50 + i / 3) for i in range(15)] for k in range(ticks)]
        probe = TimerProbe(bus.timer)
        cpu0 = time.process_time()
        s = motorbus.Streamer(bus).follow(actuators, rows, period=PERIOD_S, poll_status=True)
        await s.wait()
        cpu = time.process_time() - cpu0
        n = max(1, s.stats.ticks)
        # The first write at or after each tick's deadline is its frame (the polls of a
        # tick come after it, and end a millisecond before the next deadline).
        after_deadline = []
        for k in range(s.next_tick):
            due = s.origin + k * s.period
            i = bisect.bisect_left(writes, due)
            if i < len(writes) and writes[i] - due < s.period:
                after_deadline.append(writes[i] - due)
        return {
            "ticks": s.stats.ticks,
            "cpu_s": cpu,
            # The timer's share: how often it woke the loop, how long it spun.
            "timer_wakeups_per_tick": probe.wakeups / n,
            "timer_spin_us_per_tick": 1e6 * probe.spin_s / n,
            "write_after_deadline_us": {
                f"p{p}": 1e6 * percentile(after_deadline, p) for p in (50, 90, 99)
            },
            "stats": s.stats.as_dict(),
        }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--top", type=int, default=25)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args()
    with SimProcess(["la:1-15"], baud=921600) as sim:
        plain = asyncio.run(stream(sim.path, args.seconds))
        profiler = cProfile.Profile()
        profiler.enable()
        profiled = asyncio.run(stream(sim.path, args.seconds))
        profiler.disable()
    ticks = max(1, profiled["ticks"])
    stats = pstats.Stats(profiler)
    rows = []
    for (file, line, func), (_, calls, self_t, cum_t, _) in stats.stats.items():  # type: ignore[attr-defined]
        rows.append(
            {
                "function": f"{Path(file).name}:{line}({func})",
                "calls_per_tick": calls / ticks,
                "self_us_per_tick": self_t / ticks * 1e6,
                "cum_us_per_tick": cum_t / ticks * 1e6,
            }
        )
    rows.sort(key=lambda r: r["self_us_per_tick"], reverse=True)
    calls_per_tick = sum(r["calls_per_tick"] for r in rows)
    per_tick_us = plain["cpu_s"] / max(1, plain["ticks"]) * 1e6
    print(
        f"process CPU per tick without the profiler: {per_tick_us:.0f} us "
        f"({plain['ticks']} ticks, {plain['cpu_s']:.2f} s CPU); timer: "
        f"{plain['timer_wakeups_per_tick']:.2f} wake-ups and "
        f"{plain['timer_spin_us_per_tick']:.0f} us of spin a tick"
    )
    print(f"calls a tick under cProfile (Python and C functions): {calls_per_tick:.0f}")
    late = plain["write_after_deadline_us"]
    print(
        f"tick frame's write() called after the deadline: p50 {late['p50']:.0f} us, "
        f"p90 {late['p90']:.0f} us, p99 {late['p99']:.0f} us"
    )
    print(f"{'self us/tick':>12} {'cum us/tick':>12} {'calls/tick':>10}  function")
    for r in rows[: args.top]:
        print(
            f"{r['self_us_per_tick']:12.1f} {r['cum_us_per_tick']:12.1f} "
            f"{r['calls_per_tick']:10.1f}  {r['function']}"
        )
    write_report(
        args.out,
        {
            "cpu_us_per_tick": per_tick_us,
            "calls_per_tick": calls_per_tick,
            "plain": plain,
            "top": rows[:100],
        },
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
