"""A/B of two motorbus source trees: CPU per bus-tick, in alternating pairs.

On this shared VM the same code's CPU moves by up to 2x within minutes (README's
four-run table), so "before" and "after" measured one after the other say little about a
change of a few per cent.  This runs ``bench_cpu.py``'s ``ours`` workload (a follow
stream and a status poll per bus and 10 ms tick, on ptys a responder answers) from two
trees in pairs, each run a fresh process with ``PYTHONPATH`` on its tree, the order
alternating from pair to pair (before first in even pairs).  A pair's two runs are
seconds apart, so a slow spell falls on both: the figure is the median of the pairs'
after/before CPU ratios, with how many pairs the after side won.  Beside it, each side's
median timer spin and tick p99 (the lateness of the tick writes of all its streams, the
bus's own view), late ticks and reply timeouts (each timed-out poll's retry waits out
its device's late guard): what a CPU saving must not cost; and its
``timerfd_settime`` calls per tick sent over the whole run (each one for the near
future reprograms the CPU's timer, tens of us on a VM).  A count moves far less than
CPU time, but not nothing: how many deadline changes share a loop turn depends on the
timing, so its pairs are compared in the same sitting too.

The "before" tree is a git revision of this checkout (``--before-rev``, exported with
``git archive``) or a directory holding the ``motorbus`` package (``--before``); the
"after" tree is this checkout's ``src`` unless ``--after`` names another.  The workload
is this checkout's ``bench_cpu.py``, whatever the trees.

    python benchmarks/ab_cpu.py --before-rev HEAD~1 [--buses 1,16,32] [--seconds 2]
        [--pairs 8] [--polls tick|shared] [--kernel] [--out PATH]

``--kernel`` runs each run under ``perf`` (``kernel_clock.py``, root) and adds the worst
bus's tick p99 on the kernel's clock: the instrument that shares none of the bus's
assumptions.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results" / "ab_cpu.json"
sys.path.insert(0, str(HERE))

import bench_cpu  # noqa: E402  (the workload)
from harness import write_report  # noqa: E402

#: What a child run reports (``bench_cpu.ours``'s keys).
CHILD_KEYS = (
    "cpu_percent",
    "spin_percent",
    "ticks",
    "replies",
    "stream_errors",
    "tick_p99_us",
    "tick_max_us",
    "late_ticks",
    "skipped_ticks",
    "reply_timeouts",
)


def order(pair: int) -> tuple[str, str]:
    """Which side runs first in ``pair``: before in even pairs, after in odd ones."""
    return ("before", "after") if pair % 2 == 0 else ("after", "before")


def paired_summary(before: list[float], after: list[float]) -> dict[str, Any]:
    """The after/before ratio of each pair, their median, and the pairs after won."""
    if len(before) != len(after) or not before:
        raise ValueError("need as many after runs as before runs, at least one")
    ratios = [a / b for b, a in zip(before, after, strict=True) if b > 0]
    return {
        "before_median": round(statistics.median(before), 2),
        "after_median": round(statistics.median(after), 2),
        "ratios": [round(r, 3) for r in ratios],
        "median_ratio": round(statistics.median(ratios), 3) if ratios else None,
        "after_won": sum(1 for r in ratios if r < 1),
        "pairs": len(ratios),
    }


def median_of(runs: list[dict[str, Any]], key: str, digits: int = 1) -> float | None:
    """The median of ``key`` over the runs that report it, rounded to ``digits``; None
    if none does."""
    values = [r[key] for r in runs if r.get(key) is not None]
    return round(statistics.median(values), digits) if values else None


def export_rev(rev: str, dest: Path) -> Path:
    """``src`` of git revision ``rev`` of this checkout, exported under ``dest``."""
    archive = subprocess.run(
        ["git", "-C", str(REPO), "archive", rev, "src"], check=True, capture_output=True
    )
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive.stdout, check=True)
    return dest / "src"


def run_child(
    tree: Path, buses: int, seconds: float, kernel: bool = False, polls: str = "tick"
) -> dict[str, Any]:
    """One ``ours`` run with ``motorbus`` imported from ``tree`` (under ``perf`` if
    ``kernel``; ``polls`` as ``bench_cpu.ours``'s)."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    proc = subprocess.run(
        [
            sys.executable,
            __file__,
            "--child",
            str(buses),
            str(seconds),
            str(int(kernel)),
            polls,
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=120 + 4 * seconds,
    )
    if proc.returncode:
        raise SystemExit(f"a run from {tree} failed:\n{proc.stderr[-2000:]}")
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return result


def count_settime_calls() -> list[int]:
    """Count, from now on, the bus timer's ``timerfd_settime`` calls (arming and
    disarming) in a one-item list; an empty list where the tree has no timerfd timer.

    Through the timer's syscall wrapper, which every tree since the timerfd timer has
    (``motorbus.bus.timerfd.TimerfdApi``; ``motorbus.bus.timer._TimerfdApi`` before
    2026-12-07), so that trees before the timer counted its own ``arms`` compare too.
    """
    import importlib

    try:
        api = importlib.import_module("motorbus.bus.timerfd").TimerfdApi
    except ImportError:
        api = getattr(importlib.import_module("motorbus.bus.timer"), "_TimerfdApi", None)
    if api is None:
        return []
    calls = [0]
    real = api.set_absolute_ns

    def counted(self: Any, fd: int, deadline_ns: int) -> None:
        calls[0] += 1
        real(self, fd, deadline_ns)

    api.set_absolute_ns = counted
    return calls


def child(buses: int, seconds: float, kernel: bool, polls: str) -> None:
    import asyncio
    import contextlib

    import motorbus
    from kernel_clock import KernelWriteTrace, worst_tick_figures

    bench_cpu.raise_fd_limit(buses)
    settimes = count_settime_calls()
    trace = KernelWriteTrace()
    with tempfile.TemporaryDirectory(prefix="motorbus-ab-") as tmp:
        responder = bench_cpu.Responder(buses, Path(tmp) / "rec.json")
        try:
            with trace if kernel else contextlib.nullcontext():
                res = asyncio.run(bench_cpu.ours(responder.paths, seconds, polls))
        finally:
            responder.stop()
    out = {k: res[k] for k in CHILD_KEYS}
    out["settime_per_tick"] = (
        round(settimes[0] / res["ticks"], 3) if settimes and res["ticks"] else None
    )
    if kernel:  # the worst bus's tick writes on the kernel's clock (kernel_clock.py)
        tick_bytes = len(bench_cpu.broadcast_bytes(0.0))
        out.update(worst_tick_figures(trace, tick_bytes, bench_cpu.PERIOD_S))
    out["motorbus"] = str(Path(motorbus.__file__).resolve().parent)
    print(json.dumps(out))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    side = parser.add_mutually_exclusive_group()
    side.add_argument("--before-rev", help="git revision of this checkout (e.g. HEAD~1)")
    side.add_argument("--before", type=Path, help="a directory holding the motorbus package")
    parser.add_argument("--after", type=Path, default=REPO / "src")
    parser.add_argument("--buses", default="1,16,32")
    parser.add_argument("--seconds", type=float, default=2.0, help="length of each run")
    parser.add_argument("--pairs", type=int, default=8)
    parser.add_argument(
        "--kernel",
        action="store_true",
        help="also time each run's tick writes on the kernel's clock (perf, as root)",
    )
    parser.add_argument(
        "--polls",
        choices=bench_cpu.POLL_PHASES,
        default="tick",
        help="where the poll tasks ask for a status (bench_cpu.py --polls)",
    )
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(int(args.child[0]), float(args.child[1]), args.child[2] == "1", args.child[3])
        return 0
    if args.before is None and args.before_rev is None:
        parser.error("give --before-rev REV or --before DIR")
    try:
        counts = [int(x) for x in args.buses.split(",") if x]
    except ValueError:
        parser.error(f"--buses must be comma-separated integers, got {args.buses!r}")
    if not counts or min(counts) < 1 or args.seconds <= 0 or args.pairs < 1:
        parser.error("--buses counts >= 1, --seconds > 0 and --pairs >= 1")
    with tempfile.TemporaryDirectory(prefix="motorbus-ab-tree-") as tmp:
        before = export_rev(args.before_rev, Path(tmp)) if args.before_rev else args.before
        trees = {"before": before.resolve(), "after": args.after.resolve()}
        for name, tree in trees.items():
            if not (tree / "motorbus" / "__init__.py").is_file():
                parser.error(f"the {name} tree {tree} holds no motorbus package")
        print(
            f"ours (polls: {args.polls}), {args.seconds:g} s runs, {args.pairs} pairs a count, "
            "alternating; "
            f"before = {args.before_rev or before}, after = {args.after}"
        )
        cases = []
        for n in counts:
            runs: dict[str, list[dict[str, Any]]] = {"before": [], "after": []}
            for pair in range(args.pairs):
                for name in order(pair):
                    runs[name].append(
                        run_child(trees[name], n, args.seconds, args.kernel, args.polls)
                    )
            summary = paired_summary(
                [r["cpu_percent"] for r in runs["before"]],
                [r["cpu_percent"] for r in runs["after"]],
            )
            precision = {side: median_of(runs[side], "tick_p99_us") for side in runs}
            spin = {side: median_of(runs[side], "spin_percent") for side in runs}
            settime = {side: median_of(runs[side], "settime_per_tick", 2) for side in runs}
            # Ticks written later than the stream's LATE_AFTER_S, and reply deadlines
            # that ran out (a late responder): medians of the runs.
            late = {side: median_of(runs[side], "late_ticks", 0) for side in runs}
            timeouts = {side: median_of(runs[side], "reply_timeouts", 0) for side in runs}
            case = {
                "buses": n,
                **summary,
                "tick_p99_us": precision,
                "spin_percent": spin,
                "settime_per_tick": settime,
                "late_ticks": late,
                "reply_timeouts": timeouts,
            }
            if args.kernel:
                case["kernel_tick_jitter_p99_us"] = {
                    side: median_of(runs[side], "kernel_tick_jitter_p99_us") for side in runs
                }
            cases.append({**case, "runs": runs})
            print(
                f"  {n:3d} buses: CPU median before {summary['before_median']:5.1f} %, after "
                f"{summary['after_median']:5.1f} %; paired after/before median "
                f"{summary['median_ratio']}, after lower in {summary['after_won']} of "
                f"{summary['pairs']} pairs; spin {spin['before']} / {spin['after']} %; "
                f"timerfd_settime a tick {settime['before']} / {settime['after']}; "
                f"tick p99 (bus's view) {precision['before']} / {precision['after']} us; "
                f"late ticks {late['before']} / {late['after']}, reply timeouts "
                f"{timeouts['before']} / {timeouts['after']}",
                flush=True,
            )
            if args.kernel:
                k = case["kernel_tick_jitter_p99_us"]
                print(
                    f"        worst bus's tick p99, kernel clock: {k['before']} / {k['after']} us"
                )
    result = {
        "before": args.before_rev or str(args.before),
        "after": str(args.after),
        "seconds": args.seconds,
        "polls": args.polls,
        "pairs": args.pairs,
        "cases": cases,
    }
    write_report(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
