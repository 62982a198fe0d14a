"""Where ``bench_cpu.py``'s CPU per bus-tick goes, by layer: its ``ours`` side under cProfile.

Runs ``bench_cpu.ours`` (a follow stream and a status poll per bus and 10 ms tick, on
ptys one ``pty_recorder.py --answer`` process answers) for ``--buses`` and ``--seconds``
under cProfile, and prints the function calls per bus-tick and the profiled self time
split by layer:

* ``shell``: the asyncio shells of the bus and the streams (``motorbus/bus/bus.py``,
  ``engine.py``, ``timer.py``, ``lease_shell.py``, ``motorbus/streams.py``, the
  transports);
* ``core``: the pure core (``motorbus/protocol``, ``motorbus/streaming``, and the bus's
  ``schedule``, ``matching``, ``leases``, ``occupancy``, ``stats``);
* ``motorbus, other``: the rest of the package (the devices, the manager, ...);
* ``asyncio``, ``selectors``: the event loop;
* ``C``: built-ins, the system calls and the clock reads (the timer's spin among them);
* ``benchmark``: the workload's own code (its trajectory).

cProfile adds about the same cost to every call, so the shares say where the calls are,
not what each would cost without it.  The spin's clock reads are counted apart
(``time.monotonic`` calls a bus-tick).

    python benchmarks/profile_cpu.py [--buses 16] [--seconds 5] [--out PATH]

``--no-cprofile`` runs the same workload without cProfile and writes nothing: for a
sampling profiler from outside, which sees the loop thread as it runs::

    py-spy record -r 500 -f raw -o ours.txt -- \
        python benchmarks/profile_cpu.py --no-cprofile --seconds 15
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import tempfile
from collections import Counter
from pathlib import Path

import bench_cpu
from harness import write_report

RESULTS = Path(__file__).resolve().parent / "results" / "profile_cpu.json"
SHELL = (
    "motorbus/bus/bus.py",
    "motorbus/bus/engine.py",
    "motorbus/bus/timer.py",
    "motorbus/bus/lease_shell.py",
    "motorbus/streams.py",
    "motorbus/transport/",
)
CORE = (
    "motorbus/protocol/",
    "motorbus/streaming/",
    "motorbus/bus/schedule.py",
    "motorbus/bus/matching.py",
    "motorbus/bus/leases.py",
    "motorbus/bus/occupancy.py",
    "motorbus/bus/stats.py",
)
LAYERS = ("shell", "core", "motorbus, other", "asyncio", "selectors", "C", "benchmark", "other")


def layer(filename: str) -> str:
    """The layer a profiled function's file belongs to (``LAYERS``)."""
    path = filename.replace("\\", "/")
    if path == "~":
        return "C"
    if any(part in path for part in SHELL):
        return "shell"
    if any(part in path for part in CORE):
        return "core"
    if "/motorbus/" in path:
        return "motorbus, other"
    if "/asyncio/" in path:
        return "asyncio"
    if path.endswith("/selectors.py"):
        return "selectors"
    if "/benchmarks/" in path:
        return "benchmark"
    return "other"


def by_layer(stats: pstats.Stats) -> tuple[Counter[str], int, int]:
    """Self time per layer (s), all calls, and ``time.monotonic`` calls."""
    seconds: Counter[str] = Counter()
    calls = clock_reads = 0
    for (filename, _, name), (_, ncalls, self_s, _, _) in stats.stats.items():  # type: ignore[attr-defined]
        seconds[layer(filename)] += self_s
        calls += ncalls
        if name == "<built-in method time.monotonic>":
            clock_reads += ncalls
    return seconds, calls, clock_reads


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--buses", type=int, default=16)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--no-cprofile", action="store_true", help="the workload alone, for py-spy")
    args = parser.parse_args()
    if args.buses < 1:
        parser.error(f"--buses must be >= 1, got {args.buses}")
    if args.seconds <= 0:
        parser.error(f"--seconds must be > 0, got {args.seconds}")
    bench_cpu.raise_fd_limit(args.buses)
    with tempfile.TemporaryDirectory(prefix="motorbus-profile-") as tmp:
        responder = bench_cpu.Responder(args.buses, Path(tmp) / "record.json")
        profile = cProfile.Profile()
        try:
            if not args.no_cprofile:
                profile.enable()
            result = bench_cpu.run_side("ours", responder.paths, args.seconds, "tick", None)
            profile.disable()
        finally:
            responder.stop()
    if args.no_cprofile:
        print(
            f"ours at {args.buses} buses, {args.seconds:.0f} s: {result['cpu_percent']:.1f} % "
            f"of a core, {result['ticks']} bus-ticks (not profiled, nothing written)"
        )
        return 0
    ticks = max(1, result["ticks"])
    seconds, calls, clock_reads = by_layer(pstats.Stats(profile))
    total = sum(seconds.values()) or 1.0
    shares = {name: round(100 * seconds[name] / total, 1) for name in LAYERS}
    print(
        f"ours at {args.buses} buses, {args.seconds:.0f} s under cProfile: "
        f"{result['ticks']} bus-ticks, {result['replies']} replies"
    )
    print(
        f"function calls a bus-tick: {calls / ticks:.0f}, of them time.monotonic "
        f"{clock_reads / ticks:.0f}"
    )
    print("profiled self time by layer:")
    for name in LAYERS:
        print(f"  {name:18}{shares[name]:6.1f} %")
    write_report(
        args.out,
        {
            "buses": args.buses,
            "seconds": args.seconds,
            "bus_ticks": result["ticks"],
            "calls_per_bus_tick": round(calls / ticks, 1),
            "clock_reads_per_bus_tick": round(clock_reads / ticks, 1),
            "self_time_percent_by_layer": shares,
            "command": f"python benchmarks/profile_cpu.py --buses {args.buses} "
            f"--seconds {args.seconds:g}",
        },
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
