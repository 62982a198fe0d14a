"""Lateness of periodic absolute deadlines: asyncio.sleep vs LoopTimer vs TimerfdTimer.

For each event loop (default asyncio, uvloop if installed) and period (1 ms, 10 ms), a
task wakes at ``origin + k * period`` for ``--seconds`` seconds with each method and
records ``time.monotonic() - deadline`` at every wake-up.  Negative lateness is an early
wake-up (a broken deadline).  Prints a table and writes ``benchmarks/results/timer.json``,
with each method's p99 as a ratio of the ``asyncio.sleep`` baseline measured in the same
run.

Usage: ``python benchmarks/bench_timer.py [--seconds 2] [--out PATH] [--samples PATH]``
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import time
from collections.abc import Awaitable, Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from harness import write_report
from motorbus.bus.timer import LoopTimer, Timer, TimerfdTimer, timerfd_available

PERIODS_S = (0.001, 0.010)
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "timer.json"

Sleeper = Callable[[float], Awaitable[None]]


@dataclass(frozen=True, slots=True)
class Result:
    """Lateness statistics of one (loop, period, method) run, in microseconds."""

    loop: str
    period_ms: float
    method: str
    wakeups: int
    p50_us: float
    p99_us: float
    max_us: float
    early: int
    most_early_us: float
    p99_ratio_to_sleep: float = 1.0


def percentile(sorted_values: list[float], q: float) -> float:
    """Return the ``q`` quantile (0..1) of already sorted values (nearest rank)."""
    index = min(len(sorted_values) - 1, max(0, round(q * (len(sorted_values) - 1))))
    return sorted_values[index]


async def measure(sleep_until: Sleeper, period: float, seconds: float) -> list[float]:
    """Wake at absolute deadlines ``origin + k * period``; return lateness values (s)."""
    origin = time.monotonic() + period
    count = max(1, int(seconds / period))
    lateness = []
    for k in range(count):
        deadline = origin + k * period
        await sleep_until(deadline)
        lateness.append(time.monotonic() - deadline)
    return lateness


async def asyncio_sleep_until(deadline: float) -> None:
    """The baseline: what asyncio code usually does (and what fires early on uvloop)."""
    await asyncio.sleep(max(0.0, deadline - time.monotonic()))


async def run_loop(
    loop_name: str, seconds: float, samples: list[dict[str, object]] | None = None
) -> list[Result]:
    """Measure every method and period on the running loop.

    If ``samples`` is given, one record per run (loop, period_ms, method and the
    lateness values in seconds) is appended to it.
    """
    timers: list[tuple[str, Timer | None]] = [("asyncio.sleep", None), ("LoopTimer", LoopTimer())]
    if timerfd_available():
        # The default (no spin, issue 40), and the spin real-time mode asks for.
        timers.append(("TimerfdTimer", TimerfdTimer(spin_lead=0.0)))
        timers.append(("TimerfdTimer+spin", TimerfdTimer(spin_lead=TimerfdTimer.SPIN_LEAD_S)))
    results = []
    for period in PERIODS_S:
        baseline_p99 = 0.0
        for method, timer in timers:
            sleeper = asyncio_sleep_until if timer is None else timer.sleep_until
            values = sorted(await measure(sleeper, period, seconds))
            if samples is not None:
                samples.append(
                    {
                        "loop": loop_name,
                        "period_ms": period * 1e3,
                        "method": method,
                        "lateness": values,
                    }
                )
            early = [v for v in values if v < 0]
            result = Result(
                loop=loop_name,
                period_ms=period * 1e3,
                method=method,
                wakeups=len(values),
                p50_us=statistics.median(values) * 1e6,
                p99_us=percentile(values, 0.99) * 1e6,
                max_us=values[-1] * 1e6,
                early=len(early),
                most_early_us=-min(early) * 1e6 if early else 0.0,
            )
            if timer is None:
                baseline_p99 = result.p99_us
            ratio = result.p99_us / baseline_p99 if baseline_p99 > 0 else float("nan")
            results.append(Result(**{**asdict(result), "p99_ratio_to_sleep": round(ratio, 3)}))
    for _, timer in timers:
        if timer is not None:
            timer.close()
    return results


def loop_factories() -> list[tuple[str, Callable[[], asyncio.AbstractEventLoop]]]:
    """Return the event loops to measure: default asyncio, and uvloop if installed."""
    factories: list[tuple[str, Callable[[], asyncio.AbstractEventLoop]]] = [
        ("asyncio", asyncio.new_event_loop)
    ]
    try:
        import uvloop
    except ImportError:
        print("uvloop not installed: measuring the default loop only", file=sys.stderr)
    else:
        factories.append(("uvloop", uvloop.new_event_loop))
    return factories


def print_table(results: list[Result]) -> None:
    """Print the results as an aligned table."""
    header = (
        f"{'loop':8} {'period':>7} {'method':14} {'wakeups':>7} {'p50 µs':>8} {'p99 µs':>8} "
        f"{'max µs':>8} {'early':>6} {'most early µs':>13} {'p99/sleep':>9}"
    )
    print(header)
    print("-" * len(header))
    for r in results:
        print(
            f"{r.loop:8} {r.period_ms:>5.0f}ms {r.method:14} {r.wakeups:>7} {r.p50_us:>8.0f} "
            f"{r.p99_us:>8.0f} {r.max_us:>8.0f} {r.early:>6} {r.most_early_us:>13.0f} "
            f"{r.p99_ratio_to_sleep:>9.2f}"
        )


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; return the process exit status."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument(
        "--seconds", type=float, default=2.0, help="duration of each run (default 2)"
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON output path")
    parser.add_argument(
        "--samples",
        type=Path,
        default=None,
        help="also write every lateness value (seconds) to this JSON file, for plots",
    )
    args = parser.parse_args(argv)
    if args.seconds <= 0:
        parser.error(f"--seconds must be positive, got {args.seconds}")

    results: list[Result] = []
    samples: list[dict[str, object]] = []
    for name, factory in loop_factories():
        with asyncio.Runner(loop_factory=factory) as runner:
            results.extend(runner.run(run_loop(name, args.seconds, samples)))
    print_table(results)

    report = {
        "benchmark": "timer",
        "seconds_per_run": args.seconds,
        "timerfd": timerfd_available(),
        "results": [asdict(r) for r in results],
    }
    write_report(args.out, report)
    if args.samples is not None:
        args.samples.parent.mkdir(parents=True, exist_ok=True)
        text = json.dumps({"unit": "s", "runs": samples}) + "\n"
        args.samples.write_text(text, encoding="utf-8")
        print(f"wrote {args.samples}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
