"""Does this machine take the CPU away from a running thread, and does it say so?

One busy loop per CPU named (``--cpus``, default every CPU this process may use), each
pinned to its CPU and in a process of its own, reads ``CLOCK_MONOTONIC`` and its
thread's CPU clock (``CLOCK_THREAD_CPUTIME_ID``) back to back for ``--seconds``.  A
step of the wall clock longer than ``--gap-us`` between two reads is a gap: the thread
did not run for that long.  Beside each gap, how much thread CPU time it was charged:

* next to nothing: the CPU was taken away and the kernel knows it: either this kernel
  gave it to another task (the thread's run-queue wait, ``/proc/thread-self/schedstat``,
  grew by as much: "queued"), or the hypervisor took the vCPU (on a VM whose kernel
  accounts steal time, ``CONFIG_PARAVIRT_TIME_ACCOUNTING``, steal is left out of a
  thread's CPU time: the rest);
* about the gap: the thread was charged for time it did not run (an interrupt, or a
  hypervisor whose steal is not reported).

``/proc/stat``'s steal column over the run (whole machine, clock ticks) is printed
beside it.  A loop alone on an idle machine and one loop per CPU (every vCPU busy) can
differ: ``bench_late_ticks.py``'s "machine: CPU taken away" rests on the first kind.

    python benchmarks/bench_vcpu_gaps.py [--cpus 0,1] [--seconds 15] [--gap-us 150]
        [--out PATH]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import time
from pathlib import Path
from typing import Any

from harness import steal_seconds, write_report

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "vcpu_gaps.json"


def busy_loop(cpu: int, seconds: float, gap: float) -> dict[str, Any]:
    """Spin on ``cpu`` for ``seconds``; every wall-clock step over ``gap`` with the
    thread CPU time charged for it."""
    os.sched_setaffinity(0, {cpu})
    wall, charged = time.monotonic, time.thread_time
    queued0 = _run_queue_wait()
    start = last_wall = wall()
    last_cpu = cpu0 = charged()
    gaps: list[tuple[float, float]] = []
    while True:
        now, used = wall(), charged()
        if now - last_wall > gap:
            gaps.append((now - last_wall, used - last_cpu))
        last_wall, last_cpu = now, used
        if now - start >= seconds:
            break
    queued = _run_queue_wait() - queued0
    steps = [g for g, _ in gaps]
    uncharged = [g - c for g, c in gaps]
    return {
        "cpu": cpu,
        "wall_s": round(last_wall - start, 3),
        "thread_cpu_s": round(last_cpu - cpu0, 3),
        "gaps": len(gaps),
        "gap_max_us": round(1e6 * max(steps, default=0.0), 1),
        "gap_total_ms": round(1e3 * sum(steps), 2),
        "uncharged_total_ms": round(1e3 * sum(uncharged), 2),
        "charged_total_ms": round(1e3 * sum(c for _, c in gaps), 2),
        # Waiting for this kernel to give the CPU back, over the whole loop (the gaps'
        # share of it is at most this; waits under the threshold add a little).
        "queued_total_ms": round(1e3 * queued, 2),
    }


def _run_queue_wait() -> float:
    """This thread's time runnable but not running so far (s), or 0.0 unreadable."""
    try:
        with open("/proc/thread-self/schedstat", encoding="ascii") as f:
            return int(f.read().split()[1]) / 1e9
    except (OSError, IndexError, ValueError):
        return 0.0


def run(cpus: list[int], seconds: float, gap: float) -> list[dict[str, Any]]:
    """One busy loop per CPU of ``cpus``, all at once, each in its own process."""
    with multiprocessing.get_context("spawn").Pool(len(cpus)) as pool:
        return pool.starmap(busy_loop, [(c, seconds, gap) for c in cpus])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    usable = sorted(os.sched_getaffinity(0))
    parser.add_argument("--cpus", default=",".join(map(str, usable)))
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--gap-us", type=float, default=150.0)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    load_before = [round(x, 2) for x in os.getloadavg()]
    try:
        cpus = [int(c) for c in args.cpus.split(",") if c.strip()]
    except ValueError:
        parser.error(f"--cpus must be CPU numbers separated by commas, got {args.cpus!r}")
    bad = [c for c in cpus if c not in usable]
    if not cpus or bad:
        parser.error(f"--cpus must name CPUs of {usable}, got {args.cpus!r}")
    for name in ("seconds", "gap_us"):
        if getattr(args, name) <= 0:
            parser.error(f"--{name.replace('_', '-')} must be > 0, got {getattr(args, name)}")
    cases: list[dict[str, Any]] = []
    for label, group in (("alone", cpus[:1]), ("every CPU busy", cpus)):
        if label == "every CPU busy" and len(cpus) < 2:
            continue
        steal0 = steal_seconds()
        loops = run(group, args.seconds, args.gap_us * 1e-6)
        steal1 = steal_seconds()
        steal = None if steal0 is None or steal1 is None else round(1e3 * (steal1 - steal0), 1)
        cases.append({"case": label, "loops": loops, "steal_ms": steal})
    print(
        f"busy loops, {args.seconds:.0f} s each, gaps over {args.gap_us:.0f} us "
        f"(wall clock steps between two reads)"
    )
    print(
        f"{'case':16}{'cpu':>4}{'gaps':>6}{'max us':>9}{'gaps ms':>9}"
        f"{'uncharged ms':>14}{'queued ms':>11}{'charged ms':>12}{'steal ms':>10}"
    )
    for case in cases:
        for loop in case["loops"]:
            print(
                f"{case['case']:16}{loop['cpu']:>4}{loop['gaps']:>6}{loop['gap_max_us']:>9}"
                f"{loop['gap_total_ms']:>9}{loop['uncharged_total_ms']:>14}"
                f"{loop['queued_total_ms']:>11}{loop['charged_total_ms']:>12}"
                f"{case['steal_ms']!s:>10}"
            )
    write_report(
        args.out,
        {
            "cases": cases,
            "seconds": args.seconds,
            "gap_us": args.gap_us,
            "load_avg_before": load_before,
            "command": "python benchmarks/bench_vcpu_gaps.py " + " ".join(sys.argv[1:]),
        },
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
