"""What a timer wake-up and a pty write cost on this machine: the facts behind two designs.

* CPU per wake-up: N tasks sleep to absolute 10 ms deadlines on the bus's timer, either
  all at the same instants (they share each wake-up) or spread over the period (each
  its own).  This is why buses are grouped in phase groups (``bus/manager.py``) and why
  a stream prepares its next tick in the same wake-up as the last one (``streams.py``).
* How much later a task resumes than the timer callback that wakes it: one event-loop
  step, the reason the bus and the streams send from timer callbacks.
* Duration of one write of a 51-byte broadcast frame to a pty, as a bare ``os.write``
  and through ``SerialTransport.write`` (the bus's path): its spread is part of what a
  receiver sees as send-time jitter (README, Performance).

Prints a table and writes ``benchmarks/results/wakeups.json``.

    python benchmarks/bench_wakeups.py [--seconds 2]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import resource
import time
import tty
from pathlib import Path

from harness import write_report
from motorbus.bus.timer import default_timer
from motorbus.sim.analysis import percentile

RESULTS = Path(__file__).resolve().parent / "results" / "wakeups.json"
PERIOD_S = 0.010


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


async def sleepers(tasks: int, spread: bool, seconds: float) -> dict[str, float]:
    """CPU of ``tasks`` tasks each sleeping to 10 ms absolute deadlines."""
    timer = default_timer()
    ticks = int(seconds / PERIOD_S)
    origin = timer.now() + 0.02

    async def one(offset: float) -> None:
        for k in range(1, ticks + 1):
            await timer.sleep_until(origin + offset + k * PERIOD_S)

    cpu0, wall0 = cpu_seconds(), time.monotonic()
    await asyncio.gather(*(one(i * PERIOD_S / tasks if spread else 0.0) for i in range(tasks)))
    cpu, wall = cpu_seconds() - cpu0, time.monotonic() - wall0
    return {
        "tasks": tasks,
        "spread": spread,
        "cpu_percent": 100 * cpu / wall,
        "cpu_us_per_task_wake": 1e6 * cpu / (tasks * ticks),
    }


async def plain_wakeups(count: int) -> dict[str, float]:
    """Lateness (us) of a timerfd wake-up with no spinning: what any process that
    sleeps until something happens (a select()-based receiver, say) lives with here."""
    from motorbus.bus.timer import TimerfdTimer

    timer = TimerfdTimer(spin_lead=0.0)
    late: list[float] = []
    deadline = timer.now() + 0.02
    try:
        for _ in range(count):
            await timer.sleep_until(deadline)
            late.append((timer.now() - deadline) * 1e6)
            deadline += PERIOD_S
    finally:
        timer.close()
    return {
        "count": count,
        "p50_us": percentile(late, 50),
        "p99_us": percentile(late, 99),
        "max_us": max(late),
    }


async def callback_vs_task(count: int) -> dict[str, float]:
    """Lateness of a timer callback and of a task awaiting the same deadline (us, p50/p99).

    The difference is one event-loop step: what a task woken at a deadline adds over
    acting from the timer callback itself (why the bus transmits from callbacks).
    """
    timer = default_timer()
    loop = asyncio.get_running_loop()
    in_callback: list[float] = []
    in_task: list[float] = []
    deadline = timer.now() + 0.02
    for _ in range(count):
        woke: asyncio.Future[None] = loop.create_future()

        def fire(at: float = deadline, woke: asyncio.Future[None] = woke) -> None:
            in_callback.append((timer.now() - at) * 1e6)
            woke.set_result(None)

        timer.call_at(deadline, fire)
        await woke
        in_task.append((timer.now() - deadline) * 1e6)
        deadline += PERIOD_S
    return {
        "count": count,
        "callback_p50_us": percentile(in_callback, 50),
        "callback_p99_us": percentile(in_callback, 99),
        "task_p50_us": percentile(in_task, 50),
        "task_p99_us": percentile(in_task, 99),
    }


def pty_writes(count: int) -> dict[str, float]:
    """Durations of ``os.write`` of a 51-byte frame to a pty master, in microseconds."""
    master, slave = os.openpty()
    tty.setraw(slave)
    frame = bytes(51)
    durations = []
    try:
        for _ in range(count):
            t0 = time.perf_counter()
            os.write(master, frame)
            durations.append((time.perf_counter() - t0) * 1e6)
            os.read(slave, 4096)  # drain, as a reader would
            time.sleep(0.002)
    finally:
        os.close(master)
        os.close(slave)
    return {
        "count": count,
        "p50_us": percentile(durations, 50),
        "p99_us": percentile(durations, 99),
        "max_us": max(durations),
    }


async def transport_writes(count: int, backend: str) -> dict[str, float]:
    """Durations of ``SerialTransport.write`` of a 51-byte frame to a pty (the bus's path)."""
    from motorbus.transport.serial import SerialTransport

    master, slave = os.openpty()
    tty.setraw(slave)
    transport = SerialTransport(os.ttyname(slave), baudrate=921600, backend=backend)
    await transport.open(lambda data: None, lambda exc: None)
    frame = bytes(51)
    durations = []
    try:
        for _ in range(count):
            t0 = time.perf_counter()
            transport.write(frame)
            durations.append((time.perf_counter() - t0) * 1e6)
            await asyncio.sleep(0.002)
            os.read(master, 4096)
    finally:
        await transport.close()
        os.close(master)
        os.close(slave)
    return {
        "backend": backend,
        "count": count,
        "p50_us": percentile(durations, 50),
        "p99_us": percentile(durations, 99),
        "max_us": max(durations),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=2.0, help="per sleeper case")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    cases = [(1, False), (8, False), (8, True), (32, False), (32, True)]
    rows = [asyncio.run(sleepers(n, spread, args.seconds)) for n, spread in cases]
    steps = asyncio.run(callback_vs_task(200))
    plain = asyncio.run(plain_wakeups(200))
    writes = pty_writes(500)
    transport = asyncio.run(transport_writes(500, "fast"))
    print(f"{'tasks':>6} {'deadlines':>10} {'CPU %':>7} {'CPU us / task wake-up':>22}")
    for r in rows:
        kind = "spread" if r["spread"] else "shared"
        print(
            f"{r['tasks']:>6} {kind:>10} {r['cpu_percent']:>7.1f} "
            f"{r['cpu_us_per_task_wake']:>22.0f}"
        )
    print(
        f"\npty write of 51 bytes: p50 {writes['p50_us']:.0f} us, p99 {writes['p99_us']:.0f} us,"
        f" max {writes['max_us']:.0f} us"
    )
    print(
        f"SerialTransport.write (backend fast), same frame: p50 {transport['p50_us']:.0f} us,"
        f" p99 {transport['p99_us']:.0f} us, max {transport['max_us']:.0f} us"
    )
    print(
        f"timer callback late p50 {steps['callback_p50_us']:.0f} / p99 "
        f"{steps['callback_p99_us']:.0f} us; a task awaiting it p50 {steps['task_p50_us']:.0f}"
        f" / p99 {steps['task_p99_us']:.0f} us"
    )
    print(
        f"plain (unspun) timerfd wake-up late p50 {plain['p50_us']:.0f} / p99 "
        f"{plain['p99_us']:.0f} / max {plain['max_us']:.0f} us"
    )
    result = {
        "plain_wakeup": plain,
        "sleepers": rows,
        "callback_vs_task": steps,
        "pty_write": writes,
        "transport_write": transport,
        "period_s": PERIOD_S,
    }
    write_report(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
