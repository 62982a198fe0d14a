"""How much of the CPU gap to the minimal loop is asyncio tasks: a third side for bench_cpu.

``bench_cpu.py`` compares motorbus (``ours``: a stream and a poll task per bus) with a
minimal loop made of ``loop.call_at`` callbacks.  A program that uses motorbus, or any
asyncio library, is written with tasks, and a task wake-up costs more than a callback.
This runs, in the same process and on the same ptys, three sides doing the same writes:

* ``minimal``: ``bench_cpu.minimal`` (callbacks, no tasks);
* ``tasks``: the same work written as a careful user writes it without a library: per
  bus a stream task (absolute deadlines, ``loop.call_at`` futures) that writes the
  broadcast, and a poll task that writes the status query and awaits a future which an
  ``add_reader`` callback resolves once the 22-byte reply is in (5 ms timeout).  No
  framing, matching, spacing rule or precise timer: the cost of the task structure;
* ``ours``: ``bench_cpu.ours``.

Each pair runs the three in a rotating order (a slow spell of the shared machine falls
on all three), and the figures are the medians of the pairs' ratios: ours / minimal (the
issue-23 ratio), tasks / minimal (what tasks alone cost) and ours / tasks (what the
library costs over the task structure its user writes anyway).

    python benchmarks/bench_cpu_tasks.py [--buses 1,16] [--seconds 3] [--pairs 6]
        [--out PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import statistics
import sys
import tempfile
import time
import tty
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "cpu_tasks.json"
sys.path.insert(0, str(HERE))

import bench_cpu  # noqa: E402  (the workload, the minimal loop and ours)
from bench_cpu import LEAD_S, PERIOD_S, REPLY_BYTES  # noqa: E402
from harness import write_report  # noqa: E402
from motorbus.protocol import la  # noqa: E402

#: How long the poll task waits for a reply before it goes on (the bus's budget is less).
REPLY_TIMEOUT_S = 0.005
SIDES = ("minimal", "tasks", "ours")
#: The ratios reported, as (name, numerator side, denominator side).
RATIOS = (
    ("ours_over_minimal", "ours", "minimal"),
    ("tasks_over_minimal", "tasks", "minimal"),
    ("ours_over_tasks", "ours", "tasks"),
)


async def tasks_loop(
    paths: list[str], seconds: float, reply_timeout: float = REPLY_TIMEOUT_S
) -> dict[str, Any]:
    """The work of ``bench_cpu.minimal`` written with a stream and a poll task per bus
    (see the module docstring); CPU %, ticks, replies (those in by ``reply_timeout``)."""
    loop = asyncio.get_running_loop()
    fds = []
    for path in paths:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(fd)
        fds.append(fd)
    queries = [la.Control(i, la.ControlAction.QUERY_STATUS).encode() for i in range(1, 16)]
    n = len(fds)
    origin = loop.time() + LEAD_S
    end = origin + seconds
    waiting: list[asyncio.Future[None] | None] = [None] * n
    buffered = [0] * n
    counts = {"ticks": 0, "replies": 0}

    def on_readable(i: int) -> None:
        with contextlib.suppress(BlockingIOError):
            buffered[i] += len(os.read(fds[i], 4096))
        reply = waiting[i]
        if reply is not None and buffered[i] >= REPLY_BYTES and not reply.done():
            buffered[i] -= REPLY_BYTES
            reply.set_result(None)

    async def sleep_until(t: float) -> None:
        wake = loop.create_future()
        handle = loop.call_at(t, wake.set_result, None)
        try:
            await wake
        finally:
            handle.cancel()

    async def stream(i: int) -> None:
        k = 0
        while (t := origin + i * PERIOD_S / n + k * PERIOD_S) < end:
            await sleep_until(t)
            os.write(fds[i], bench_cpu.broadcast_bytes(k * PERIOD_S))
            counts["ticks"] += 1
            k += 1

    async def poller(i: int) -> None:
        k = 0
        while (t := origin + i * PERIOD_S / n + k * PERIOD_S) < end:
            await sleep_until(t + bench_cpu.MINIMAL_POLL_OFFSET_S)
            reply = waiting[i] = loop.create_future()
            os.write(fds[i], queries[k % len(queries)])
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(reply, reply_timeout)
                counts["replies"] += 1
            waiting[i] = None
            k += 1

    for i, fd in enumerate(fds):
        loop.add_reader(fd, on_readable, i)
    wall0, cpu0 = time.monotonic(), bench_cpu.cpu_seconds()
    try:
        await asyncio.gather(*(stream(i) for i in range(n)), *(poller(i) for i in range(n)))
    finally:
        wall, cpu = time.monotonic() - wall0, bench_cpu.cpu_seconds() - cpu0
        for fd in fds:
            loop.remove_reader(fd)
            os.close(fd)
    return {"cpu_percent": 100 * cpu / wall, "ticks": counts["ticks"], "replies": counts["replies"]}


def rotation(pair: int) -> tuple[str, ...]:
    """The order of the three sides in ``pair``: each side goes first every third pair."""
    k = pair % len(SIDES)
    return SIDES[k:] + SIDES[:k]


def summarise(pairs: list[dict[str, dict[str, Any]]]) -> dict[str, Any]:
    """Per side the median CPU %; per ratio of ``RATIOS`` the median of the pairs' own
    ratios and their range."""
    out: dict[str, Any] = {
        f"{side}_cpu_percent": round(statistics.median(p[side]["cpu_percent"] for p in pairs), 1)
        for side in SIDES
    }
    for name, top, bottom in RATIOS:
        ratios = [p[top]["cpu_percent"] / p[bottom]["cpu_percent"] for p in pairs]
        out[name] = round(statistics.median(ratios), 2)
        out[f"{name}_range"] = [round(min(ratios), 2), round(max(ratios), 2)]
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--buses", default="1,16", help="comma-separated bus counts")
    parser.add_argument("--seconds", type=float, default=3.0, help="each side's run, per pair")
    parser.add_argument("--pairs", type=int, default=6, help="rounds of the three sides")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    try:
        counts = [int(x) for x in args.buses.split(",") if x]
    except ValueError:
        parser.error(f"--buses must be comma-separated integers, got {args.buses!r}")
    if not counts or min(counts) < 1:
        parser.error(f"--buses must list counts >= 1, got {args.buses!r}")
    if args.seconds <= 0 or args.pairs < 1:
        parser.error(f"--seconds must be > 0 and --pairs >= 1, got {args.seconds}, {args.pairs}")
    bench_cpu.raise_fd_limit(max(counts))
    sides: dict[str, Callable[[list[str], float], Coroutine[Any, Any, dict[str, Any]]]] = {
        "minimal": bench_cpu.minimal,
        "tasks": tasks_loop,
        "ours": bench_cpu.ours,
    }
    rows = []
    print(f"CPU per bus-tick, three sides, {args.pairs} pairs of {args.seconds:g} s each")
    print("| buses | minimal | tasks | ours | tasks/minimal | ours/minimal | ours/tasks |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="motorbus-cpu-tasks-") as tmp:
        for n in counts:
            responder = bench_cpu.Responder(n, Path(tmp) / f"tasks{n}.json")
            pairs: list[dict[str, dict[str, Any]]] = []
            try:
                for k in range(args.pairs):
                    pairs.append(
                        {
                            side: asyncio.run(sides[side](responder.paths, args.seconds))
                            for side in rotation(k)
                        }
                    )
            finally:
                responder.stop()
            row = {"buses": n, **summarise(pairs), "pairs": pairs}
            rows.append(row)

            def cell(name: str, r: dict[str, Any] = row) -> str:
                lo, hi = r[f"{name}_range"]
                return f"{r[name]:.2f} ({lo:.2f}-{hi:.2f})"

            print(
                f"| {n} | {row['minimal_cpu_percent']:.1f} % | {row['tasks_cpu_percent']:.1f} % "
                f"| {row['ours_cpu_percent']:.1f} % | {cell('tasks_over_minimal')} "
                f"| {cell('ours_over_minimal')} | {cell('ours_over_tasks')} |",
                flush=True,
            )
    write_report(args.out, {"rows": rows, "seconds": args.seconds})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
