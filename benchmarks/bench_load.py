"""Stream under load: README's stream with two CPU hogs, with and without real-time mode.

README's stream (15 actuators at 10 ms, 0xF3 broadcasts, ``poll_status=True``) runs for
``--seconds`` against ``motorbus sim`` (a child process) while two ``while True: pass``
processes keep both cores busy, twice in the same run:

* ``plain``: the bus process as it comes (SCHED_OTHER);
* ``rt``: the bus process under SCHED_FIFO priority 50.  ``motorbus.runtime.realtime.enable()``
  is used if this motorbus has it, else ``os.sched_setscheduler`` directly (the report
  says which, under ``rt_method``).

The bus runs in a child process of this script (``--child``), so only it is real-time.
It records its own write(2) calls with ``perf`` (``kernel_clock.py``; the trace starts
before the switch to SCHED_FIFO, so perf itself is not real-time) and fits the 0xF3
writes to a least-squares 10 ms grid: jitter p50/p99/max, late ticks (> 1 ms), missed
ticks, and the smallest gap between two writes to the port.  Without perf every kernel
figure is ``null`` and ``kernel_why`` says why.

Goals (rt with hogs): p99 <= 100 us, max <= 500 us, no missed or late tick, every write
>= 1 ms after the one before.

    python benchmarks/bench_load.py [--quick] [--seconds 20] [--out PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from harness import write_report
from kernel_clock import KernelWriteTrace, port_figures
from motorbus.manager import BusManager
from motorbus.protocol import la
from motorbus.sim.process import SimProcess

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "load.json"
PERIOD_S = 0.010
N_ACTUATORS = 15
BAUD = 921600
HOGS = 2
RT_PRIORITY = 50
BROADCAST_BYTES = len(
    la.split_broadcast(la.BroadcastMode.FOLLOW, dict.fromkeys(range(1, N_ACTUATORS + 1), 1000))[
        0
    ].encode()
)
FRAME_SIZES = (len(la.Control(1, la.ControlAction.QUERY_STATUS).encode()), BROADCAST_BYTES)
GOAL_RT_P99_US = 100.0
GOAL_RT_MAX_US = 500.0
GOAL_MIN_GAP_US = 1000.0
#: Longest a child run may take beyond its planned length.
CHILD_SLACK_S = 60.0
KEYS = (
    "tick_jitter_p50_us",
    "tick_jitter_p99_us",
    "tick_jitter_max_us",
    "late_ticks",
    "missed_ticks",
    "ticks",
    "ticks_sent_pct",
    "min_gap_us",
    "gaps_under_1000us",
    "write_max_us",
)


def trajectory(t: float) -> list[float]:
    return [
        1000 + 600 * math.sin(2 * math.pi * 0.5 * t + 2 * math.pi * i / N_ACTUATORS)
        for i in range(N_ACTUATORS)
    ]


def go_realtime() -> str:
    """Put this process under SCHED_FIFO; return how (or raise OSError)."""
    realtime: Any
    try:
        from motorbus.runtime import realtime
    except ImportError:
        realtime = None
    if realtime is not None and hasattr(realtime, "enable"):
        try:
            realtime.enable(RT_PRIORITY)
        except TypeError:  # an enable() without a priority argument
            realtime.enable()
        # enable() sets SCHED_FIFO with reset-on-fork (children stay ordinary).
        policy = os.sched_getscheduler(0) & ~getattr(os, "SCHED_RESET_ON_FORK", 0)
        if policy == os.SCHED_FIFO:
            return "motorbus.runtime.realtime.enable()"
        # enable() chose another policy or priority: fall through and set it ourselves.
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(RT_PRIORITY))
    return (
        f"os.sched_setscheduler(SCHED_FIFO, {RT_PRIORITY}) "
        "(motorbus.runtime.realtime not available)"
    )


async def stream(path: str, seconds: float) -> dict[str, Any]:
    mgr = BusManager(safe_stop=False)
    mgr.add_bus("load", path, baud=BAUD, devices=[f"la:1-{N_ACTUATORS}"])
    async with mgr:
        actuators = [mgr.la("load", i) for i in range(1, N_ACTUATORS + 1)]
        s = mgr.streamer("load").follow(
            actuators,
            lambda t, _: None if t >= seconds else trajectory(t),
            period=PERIOD_S,
            poll_status=True,
        )
        await asyncio.wait_for(s.wait(), seconds + CHILD_SLACK_S / 2)
        return {
            "host_ticks": s.stats.ticks,
            "host_late": s.stats.late,
            "host_skipped": s.stats.skipped,
            "polls": s.stats.polls,
            "poll_timeouts": s.stats.poll_timeouts,
        }


def child(path: str, seconds: float, rt: bool, out: Path) -> int:
    """Run the stream here (real-time if ``rt``), trace its writes, write JSON to ``out``."""
    method = "none (SCHED_OTHER)"
    with KernelWriteTrace() as trace:
        if rt:
            try:
                method = go_realtime()
            except OSError as err:
                method = f"FAILED: {err}"
        host = asyncio.run(stream(path, seconds))
    kernel = port_figures(
        trace,
        FRAME_SIZES,
        tick_bytes=BROADCAST_BYTES,
        period=PERIOD_S,
        expected_ticks=round(seconds / PERIOD_S),
    )
    result: dict[str, Any] = {"rt_method": method, **host}
    result["kernel_measured"] = bool(kernel.get("kernel_measured"))
    result["kernel_why"] = kernel.get("kernel_why") or None
    for key in KEYS:
        value = kernel.get(f"kernel_{key}")
        if isinstance(value, float):
            value = round(value, 1) if math.isfinite(value) else None
        result[key] = value
    out.write_text(json.dumps(result) + "\n", encoding="utf-8")
    return 0


@contextlib.contextmanager
def cpu_hogs(count: int) -> Iterator[None]:
    """``count`` ``while True: pass`` processes for the length of the block."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]
    try:
        yield
    finally:
        for h in hogs:
            h.kill()
        for h in hogs:
            h.wait()


def run_mode(rt: bool, seconds: float, tmp: Path) -> dict[str, Any]:
    """One run: simulator, two hogs, the bus child; its report."""
    out = tmp / f"{'rt' if rt else 'plain'}.json"
    with SimProcess([f"la:1-{N_ACTUATORS}"], baud=BAUD) as sim, cpu_hogs(HOGS):
        cmd = [sys.executable, __file__, "--child", sim.path, "--seconds", str(seconds)]
        cmd += ["--out", str(out)] + (["--rt"] if rt else [])
        subprocess.run(cmd, check=True, timeout=seconds + CHILD_SLACK_S)
    report: dict[str, Any] = json.loads(out.read_text(encoding="utf-8"))
    return report


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="run length per mode")
    parser.add_argument("--quick", action="store_true", help="5 s per mode")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--child", metavar="PTY", help=argparse.SUPPRESS)
    parser.add_argument("--rt", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        return child(args.child, args.seconds, args.rt, args.out)
    if args.quick:
        args.seconds = 5.0
    if args.seconds <= 0:
        parser.error(f"--seconds must be > 0, got {args.seconds}")
    with tempfile.TemporaryDirectory(prefix="motorbus-load-") as tmp_name:
        tmp = Path(tmp_name)
        t0 = time.monotonic()
        plain = run_mode(False, args.seconds, tmp)
        rt = run_mode(True, args.seconds, tmp)
        wall = time.monotonic() - t0
    rt_method = rt.pop("rt_method")
    plain.pop("rt_method")
    result: dict[str, Any] = {
        "plain": plain,
        "rt": rt,
        "rt_method": rt_method,
        "hogs": HOGS,
        "seconds": args.seconds,
        "wall_s": round(wall, 1),
    }
    print(
        f"stream under load: {N_ACTUATORS} actuators, {PERIOD_S * 1e3:.0f} ms, poll_status, "
        f"{HOGS} CPU hogs, {args.seconds:.0f} s per mode; rt = {rt_method}"
    )
    if not rt["kernel_measured"]:
        print(f"kernel clock: not measured: {rt['kernel_why']}")
    print(f"\n{'kernel clock':34}{'plain':>12}{'real-time':>12}")
    for key in KEYS:
        a, b = plain.get(key), rt.get(key)
        print(f"{key:34}{'n/a' if a is None else a:>12}{'n/a' if b is None else b:>12}")
    for key in ("host_late", "host_skipped", "polls", "poll_timeouts"):
        print(f"{key:34}{plain[key]:>12}{rt[key]:>12}")
    write_report(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
