"""15 LA statuses at 921,600 bit/s over a pty: a group read against a LeRobot-style loop,
and what a blocking call costs over the asyncio call.

``motorbus sim`` runs in a child process (``SimProcess``, 15 actuators, wire pacing).
Each round reads the status of IDs 1..15, timed from the first request to the last
reply, by:

* ``pyserial loop``: the baseline, a blocking loop over plain pyserial as LeRobot's
  ``sync_read`` or DynamixelSDK's ``GroupSyncRead`` do for servos without a bulk read:
  write one request, wait for its 22-byte reply, next ID;
* ``group read, blocking``: ``motorbus.blocking.read_statuses(bus, ids)``, one call;
* ``group read, asyncio``: ``await motorbus.read_statuses(bus, ids)``;
* ``status() loop, blocking`` / ``status() loop, asyncio``: fifteen ``status()`` calls;
* all four again with ``min_spacing=0``: the bus's 1 ms start-to-start spacing (LA
  manual 3.4.2, the bus's default, which the pyserial loop does not keep) taken out, to
  show what the rest of the stack costs against the baseline, and what pipelining saves
  once the spacing no longer hides it.

Then the per-call overhead of the blocking API: one ``status()`` blocking vs asyncio,
and an empty coroutine run through the blocking runner vs awaited (the thread hop
alone).  The modes run in turn, ``--reps`` times each, in rotating order, on the same
simulator; each holds the port alone (the bus opens it with an exclusive lock).

Prints a table and writes ``benchmarks/results/group_read.json``.

Usage: ``python benchmarks/bench_group_read.py [--rounds 50] [--reps 3] [--calls 300]
[--out PATH]``
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import serial

import motorbus
import motorbus.blocking as mb
from harness import write_report
from motorbus.blocking._runner import runner
from motorbus.protocol import la
from motorbus.protocol.base import wire_time
from motorbus.sim.process import SimProcess

BAUD = 921600
IDS = list(range(1, 16))
REPLY_SIZE = 22
#: pyserial's read timeout: a lost reply fails the run instead of hanging it.
SERIAL_TIMEOUT_S = 0.5
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "group_read.json"
#: Every bus's host margin: a reply later than the default 2 ms on this shared machine
#: must not end the run as a timeout.  It moves only deadlines, not when replies come.
HOST_MARGIN_S = 0.02
QUERIES = {i: la.Control(i, la.ControlAction.QUERY_STATUS).encode() for i in IDS}


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q * (len(ordered) - 1))))]


# -- the baseline: one request, wait for its reply, next -------------------------------------


def pyserial_loop(path: str, rounds: int) -> list[float]:
    samples: list[float] = []
    with serial.Serial(path, BAUD, timeout=SERIAL_TIMEOUT_S) as port:
        for _ in range(rounds + 1):  # the first round warms up
            t0 = time.perf_counter()
            for ident in IDS:
                port.write(QUERIES[ident])
                reply = port.read(REPLY_SIZE)
                if len(reply) != REPLY_SIZE or reply[3] != ident:
                    raise RuntimeError(f"la:{ident}: got {reply.hex(' ')!r}")
            samples.append(time.perf_counter() - t0)
    return samples[1:]


# -- motorbus, blocking ------------------------------------------------------------------------


def blocking_rounds(path: str, rounds: int, how: str, spacing: float | None) -> list[float]:
    options: dict[str, Any] = {"host_margin": HOST_MARGIN_S}
    if spacing is not None:
        options["min_spacing"] = spacing
    transport = motorbus.open_transport(path, baudrate=BAUD)
    samples: list[float] = []
    with mb.Bus(transport, families=[motorbus.Family.LA], reconnect=False, **options) as bus:
        actuators = [bus.la(i) for i in IDS]
        for _ in range(rounds + 1):
            t0 = time.perf_counter()
            if how == "group":
                statuses = mb.read_statuses(bus, IDS)
            else:
                statuses = {a.id: a.status() for a in actuators}
            samples.append(time.perf_counter() - t0)
            if list(statuses) != IDS:
                raise RuntimeError(f"read {list(statuses)}")
    return samples[1:]


# -- motorbus, asyncio -------------------------------------------------------------------------


async def async_rounds(path: str, rounds: int, how: str, spacing: float | None) -> list[float]:
    options: dict[str, Any] = {"host_margin": HOST_MARGIN_S}
    if spacing is not None:
        options["min_spacing"] = spacing
    transport = motorbus.open_transport(path, baudrate=BAUD)
    samples: list[float] = []
    async with motorbus.Bus(
        transport, families=[motorbus.Family.LA], reconnect=False, **options
    ) as bus:
        actuators = [motorbus.InspireLA(bus, i) for i in IDS]
        for _ in range(rounds + 1):
            t0 = time.perf_counter()
            if how == "group":
                statuses = await motorbus.read_statuses(bus, IDS)
            else:
                statuses = {a.id: await a.status() for a in actuators}
            samples.append(time.perf_counter() - t0)
            if list(statuses) != IDS:
                raise RuntimeError(f"read {list(statuses)}")
    return samples[1:]


# -- per-call overhead -------------------------------------------------------------------------


async def _nothing() -> None:
    return None


def per_call_blocking(path: str, calls: int) -> dict[str, list[float]]:
    transport = motorbus.open_transport(path, baudrate=BAUD)
    status: list[float] = []
    hop: list[float] = []
    run = runner()
    with mb.Bus(
        transport, families=[motorbus.Family.LA], reconnect=False, host_margin=HOST_MARGIN_S
    ) as bus:
        actuator = bus.la(1)
        for _ in range(calls):
            t0 = time.perf_counter()
            actuator.status()
            status.append(time.perf_counter() - t0)
        for _ in range(calls):
            t0 = time.perf_counter()
            run.call(_nothing())
            hop.append(time.perf_counter() - t0)
    return {"status": status, "empty": hop}


async def per_call_async(path: str, calls: int) -> dict[str, list[float]]:
    transport = motorbus.open_transport(path, baudrate=BAUD)
    status: list[float] = []
    empty: list[float] = []
    async with motorbus.Bus(
        transport, families=[motorbus.Family.LA], reconnect=False, host_margin=HOST_MARGIN_S
    ) as bus:
        actuator = motorbus.InspireLA(bus, 1)
        for _ in range(calls):
            t0 = time.perf_counter()
            await actuator.status()
            status.append(time.perf_counter() - t0)
        for _ in range(calls):
            t0 = time.perf_counter()
            await asyncio.ensure_future(_nothing())  # a task, as the runner makes one
            empty.append(time.perf_counter() - t0)
    return {"status": status, "empty": empty}


# -- the run -----------------------------------------------------------------------------------


def summary_ms(samples: list[float]) -> dict[str, float]:
    return {
        "n": len(samples),
        "median_ms": statistics.median(samples) * 1e3,
        "p90_ms": percentile(samples, 0.9) * 1e3,
        "min_ms": min(samples) * 1e3,
        "max_ms": max(samples) * 1e3,
    }


def wire_floor_ms() -> float:
    """15 x (query + reply on the wire): what no client can beat, turnarounds aside."""
    return len(IDS) * (wire_time(len(QUERIES[1]), BAUD) + wire_time(REPLY_SIZE, BAUD)) * 1e3


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; return 0."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--rounds", type=int, default=50, help="group reads per block")
    parser.add_argument("--reps", type=int, default=3, help="blocks per mode, rotating")
    parser.add_argument("--calls", type=int, default=300, help="calls for the overhead")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON output path")
    args = parser.parse_args(argv)
    for name in ("rounds", "reps", "calls"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be at least 1, got {getattr(args, name)}")
    modes: dict[str, Callable[[str], list[float]]] = {
        "pyserial loop (baseline)": lambda p: pyserial_loop(p, args.rounds),
        "group read, blocking": lambda p: blocking_rounds(p, args.rounds, "group", None),
        "group read, asyncio": lambda p: asyncio.run(async_rounds(p, args.rounds, "group", None)),
        "status() loop, blocking": lambda p: blocking_rounds(p, args.rounds, "loop", None),
        "status() loop, asyncio": lambda p: asyncio.run(async_rounds(p, args.rounds, "loop", None)),
        "group read, blocking, min_spacing=0": lambda p: blocking_rounds(
            p, args.rounds, "group", 0.0
        ),
        "group read, asyncio, min_spacing=0": lambda p: asyncio.run(
            async_rounds(p, args.rounds, "group", 0.0)
        ),
        "status() loop, blocking, min_spacing=0": lambda p: blocking_rounds(
            p, args.rounds, "loop", 0.0
        ),
        "status() loop, asyncio, min_spacing=0": lambda p: asyncio.run(
            async_rounds(p, args.rounds, "loop", 0.0)
        ),
    }
    samples: dict[str, list[float]] = {m: [] for m in modes}
    calls: dict[str, list[float]] = {
        "status_blocking": [],
        "status_async": [],
        "empty_blocking": [],
        "empty_async": [],
    }
    names = list(modes)
    with SimProcess([f"la:1-{IDS[-1]}"], baud=BAUD) as sim:
        for rep in range(args.reps):
            for k in range(len(names)):
                mode = names[(k + rep) % len(names)]  # rotate: no mode always goes first
                samples[mode] += modes[mode](sim.path)
            blocking = per_call_blocking(sim.path, args.calls)
            aio = asyncio.run(per_call_async(sim.path, args.calls))
            calls["status_blocking"] += blocking["status"]
            calls["empty_blocking"] += blocking["empty"]
            calls["status_async"] += aio["status"]
            calls["empty_async"] += aio["empty"]
    results = {m: summary_ms(s) for m, s in samples.items()}
    base = results["pyserial loop (baseline)"]["median_ms"]
    for r in results.values():
        r["vs_baseline"] = r["median_ms"] / base
    overhead = {
        name: {
            "median_us": statistics.median(values) * 1e6,
            "p90_us": percentile(values, 0.9) * 1e6,
        }
        for name, values in calls.items()
    }
    overhead_status_us = (
        overhead["status_blocking"]["median_us"] - (overhead["status_async"]["median_us"])
    )
    overhead_empty_us = (
        overhead["empty_blocking"]["median_us"] - (overhead["empty_async"]["median_us"])
    )
    report = {
        "benchmark": "group_read",
        "ids": IDS,
        "baud": BAUD,
        "rounds_per_block": args.rounds,
        "reps": args.reps,
        "wire_floor_ms": wire_floor_ms(),
        "spacing_floor_ms": len(IDS) * 1.0,
        "modes": results,
        "per_call": overhead,
        "blocking_overhead_status_us": overhead_status_us,
        "blocking_overhead_empty_us": overhead_empty_us,
    }
    print(f"15 LA statuses, {BAUD} bit/s over a pty, {args.reps} x {args.rounds} rounds per mode")
    print(
        f"wire floor {report['wire_floor_ms']:.2f} ms (queries + replies); "
        f"1 ms spacing floor {report['spacing_floor_ms']:.0f} ms"
    )
    print(f"{'mode':<38} {'median ms':>9} {'p90 ms':>7} {'min ms':>7} {'vs baseline':>11}")
    for mode, r in results.items():
        print(
            f"{mode:<38} {r['median_ms']:9.2f} {r['p90_ms']:7.2f} {r['min_ms']:7.2f} "
            f"{r['vs_baseline']:10.2f}x"
        )
    print(f"{'one call':<38} {'median us':>9} {'p90 us':>7}")
    for name, o in overhead.items():
        print(f"{name:<38} {o['median_us']:9.0f} {o['p90_us']:7.0f}")
    print(
        f"blocking overhead per call: status() {overhead_status_us:+.0f} us, "
        f"empty coroutine {overhead_empty_us:+.0f} us"
    )
    write_report(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
