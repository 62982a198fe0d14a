"""Garbage-collector pauses inside a 100 Hz stream, with and without real-time mode.

One bus of 15 simulated actuators (``motorbus sim`` in a child process, on a pty) gets
a follow stream at 10 ms whose target function allocates like an application does:
short-lived reference cycles every tick, and a history of recent ticks that lives
long enough to reach the old generation.  ``gc.callbacks`` (``GcPauseMonitor``)
times every collection, by generation and by who ran it:

* ``auto``: the interpreter, in the middle of whatever was allocating - the tick's
  own work, in this process;
* ``idle``: ``motorbus.runtime.realtime.idle_hook()``, called by a side task half-way
  between ticks (the place the stream loop will call it from).

Mode ``default`` runs as the library does without real-time mode; mode ``realtime``
calls ``motorbus.runtime.realtime.enable()`` first (SCHED_FIFO, mlockall, ``gc.freeze()``,
automatic full collections off); mode ``gc-only`` does too, but SCHED_FIFO is refused
(as on a machine without the right) and memory is not locked, so only the collector
control differs from ``default``.  Each mode runs in a fresh interpreter.  The claim
checked: in real-time mode no full (generation 2) collection runs inside the stream.

Prints a table and writes ``benchmarks/results/gc.json``.

Usage: ``python benchmarks/bench_gc.py [--seconds 10] [--out PATH]``
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from harness import write_report

BAUD = 921600
N_ACTUATORS = 15
PERIOD_S = 0.010
#: Per tick: this many short-lived reference cycles...
CYCLES_PER_TICK = 300
#: ... and one history entry of this many dicts, kept for HISTORY_TICKS ticks.
HISTORY_DICTS = 20
HISTORY_TICKS = 3000
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "gc.json"
MODES = ("default", "gc-only", "realtime")


async def child_run(mode: str, seconds: float) -> dict[str, Any]:
    from motorbus.manager import BusManager
    from motorbus.runtime import realtime
    from motorbus.sim.process import SimProcess

    history: collections.deque[dict[str, Any]] = collections.deque(maxlen=HISTORY_TICKS)

    def targets(t: float, statuses: Any) -> list[int] | None:
        if t >= seconds:
            return None
        for _ in range(CYCLES_PER_TICK):
            junk: list[Any] = []
            junk.append(junk)
        history.append({"t": t, "values": [{"i": i} for i in range(HISTORY_DICTS)]})
        return [1000 + (i * 37 + round(t * 100)) % 800 for i in range(N_ACTUATORS)]

    rt_report: dict[str, Any] | None = None
    with SimProcess([f"la:1-{N_ACTUATORS}"], baud=BAUD) as sim:
        if mode == "realtime":
            rt_report = realtime.enable().as_dict()
        elif mode == "gc-only":
            # As on a machine that refuses SCHED_FIFO (and without mlockall): the GC
            # control alone, through enable()'s refusal path.
            def refuse(*args: Any) -> None:
                raise PermissionError(1, "Operation not permitted (refused by bench_gc)")

            os.sched_setscheduler = refuse
            rt_report = realtime.enable(lock_memory=False).as_dict()
        mgr = BusManager(safe_stop=False)
        mgr.add_bus("bus", sim.path, baud=BAUD, devices=[f"la:1-{N_ACTUATORS}"])
        idle_calls = 0
        idle_ran = 0
        async with mgr:
            bus = mgr.bus("bus")
            actuators = [mgr.la("bus", i) for i in range(1, N_ACTUATORS + 1)]
            with realtime.GcPauseMonitor() as monitor:
                stream = mgr.streamer("bus").follow(actuators, targets, period=PERIOD_S)
                origin = bus.timer.now()

                async def idle() -> None:
                    nonlocal idle_calls, idle_ran
                    k = 0
                    while not stream.done:
                        k += 1
                        await bus.timer.sleep_until(origin + (k + 0.5) * PERIOD_S)
                        idle_calls += 1
                        idle_ran += realtime.idle_hook()

                idler = asyncio.get_running_loop().create_task(idle())
                await stream.wait()
                idler.cancel()
            stats = stream.stats.as_dict()
    return {
        "mode": mode,
        "stream": stats,
        "gc": monitor.summary(),
        "gen2_auto": monitor.count(2, "auto"),
        "gen2_idle": monitor.count(2, "idle"),
        "idle_calls": idle_calls,
        "idle_collections": idle_ran,
        "realtime": rt_report,
    }


def run_mode(mode: str, seconds: float) -> dict[str, Any]:
    out = subprocess.run(
        [sys.executable, __file__, "--child", mode, "--seconds", str(seconds)],
        capture_output=True,
        text=True,
        timeout=seconds * 10 + 60,
        check=False,
    )
    if out.returncode != 0:
        raise RuntimeError(f"mode {mode} failed: {out.stderr.strip()}")
    result: dict[str, Any] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def print_table(results: list[dict[str, Any]]) -> None:
    print(f"15 actuators at {PERIOD_S * 1e3:.0f} ms, allocating target function; GC pauses")
    head = f"{'mode':<9} {'collections':<12} {'count':>6} {'p99 us':>9} {'max us':>9}"
    print(head)
    for r in results:
        for key, v in r["gc"].items():
            print(f"{r['mode']:<9} {key:<12} {v['count']:6d} {v['p99_us']:9.0f} {v['max_us']:9.0f}")
    print()
    print(f"{'mode':<9} {'gen2 in stream':>14} {'gen2 idle':>9} {'ticks':>6} {'late':>5} "
          f"{'skipped':>7} {'jitter p99 us':>13} {'max us':>8}")  # fmt: skip
    for r in results:
        s = r["stream"]
        print(
            f"{r['mode']:<9} {r['gen2_auto']:14d} {r['gen2_idle']:9d} {s['ticks']:6d} "
            f"{s['late']:5d} {s['skipped']:7d} {s['jitter_p99_us']:13.0f} {s['jitter_max_us']:8.0f}"
        )
    for r in results:
        if r["realtime"] and r["realtime"]["refused"]:
            print(f"{r['mode']}: refused {', '.join(r['realtime']['refused'])}")


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark (or one mode of it, with ``--child``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--seconds", type=float, default=10.0, help="stream length per mode")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON output path")
    parser.add_argument("--child", choices=MODES, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if not args.seconds > 0:
        parser.error(f"--seconds must be positive, got {args.seconds}")
    if args.child:
        print(json.dumps(asyncio.run(child_run(args.child, args.seconds))))
        return 0
    load = os.getloadavg()
    results = [run_mode(mode, args.seconds) for mode in MODES]
    print_table(results)
    report = {
        "benchmark": "gc",
        "seconds": args.seconds,
        "period_s": PERIOD_S,
        "actuators": N_ACTUATORS,
        "workload": {
            "cycles_per_tick": CYCLES_PER_TICK,
            "history_dicts": HISTORY_DICTS,
            "history_ticks": HISTORY_TICKS,
        },
        "no_full_collection_in_stream_in_realtime": all(
            r["gen2_auto"] == 0 for r in results if r["mode"] != "default"
        ),
        "results": results,
        "load_avg_before": list(load),
        "load_avg_after": list(os.getloadavg()),
    }
    write_report(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
