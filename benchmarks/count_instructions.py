"""CPU per bus-tick as a count: the instructions ``bench_cpu.py``'s loops execute a tick.

``bench_cpu.py`` times the loops, and on this shared 2-core VM one round's ratio to (b)
ranges from 0.95 to 2.5 for the same code.  This script counts instead: each loop
(``ours``, (b) ``timerfd``, ``minimal``: ``bench_cpu.py``'s, on one bus, the same work)
runs in a child process under valgrind's callgrind, which counts every user-space
instruction the process executes, once for ``--short`` and once for ``--long`` seconds of
ticks; the difference over the difference in ticks sent is the instructions one tick
costs, the start-up (imports, opening the port) cancelling out.  A count does not move
with the machine's load; two runs of the same code agree to about 1 %.

What it does not see: the kernel's side of each system call (``bench_cpu.py``'s CPU
includes it; ours makes about one more ``epoll_wait`` a tick than (b)), and how fast the
instructions run (cache misses, branch misses).  Valgrind slows the child about 50x, so
one bus only: a child that sent under 95 % of its ticks fell behind, and its row is
marked (its count then includes skipped ticks' work, not only sent ones).  Ours's count
includes ``harness.TimerProbe``, ``bench_cpu.py``'s counter of timer arms (a few dozen
instructions an arm).

    python benchmarks/count_instructions.py [--polls none,tick] [--short 2] [--long 6]
        [--out PATH]

Needs ``valgrind`` (Debian: ``apt-get install valgrind``).  Writes
``benchmarks/results/instructions.json``: per polls setting and side, the instructions
a tick, and ours over (b) and over the minimal loop.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from harness import write_report

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "instructions.json"
SIDES = ("ours", "timerfd", "minimal")
#: A child that sent fewer of its ticks fell behind under valgrind (its row is marked).
KEPT_UP_SHARE = 0.95
#: callgrind's summary line: "==pid== Collected : 1840315157".
_COLLECTED = re.compile(r"Collected\s*:\s*(\d+)")


def child(side: str, seconds: float, polls: str) -> None:
    """Run one side of ``bench_cpu.py`` on one bus; print its ticks as JSON."""
    import bench_cpu

    with tempfile.TemporaryDirectory(prefix="motorbus-instr-") as tmp:
        responder = bench_cpu.Responder(1, Path(tmp) / "rec.json")
        try:
            out = bench_cpu.run_side(side, responder.paths, seconds, polls, None)
        finally:
            responder.stop()
    print(json.dumps({"ticks": out["ticks"], "replies": out.get("replies")}))


def collected(stderr: str) -> int:
    """The instruction count of callgrind's summary in ``stderr``."""
    found = _COLLECTED.findall(stderr)
    if not found:
        raise RuntimeError(f"no callgrind summary in valgrind's output:\n{stderr[-2000:]}")
    return int(found[-1])


def per_tick(short: tuple[int, int], long: tuple[int, int]) -> float | None:
    """Instructions a tick from two runs' (instructions, ticks): the difference of the
    counts over the difference of the ticks (None if the ticks did not grow)."""
    ticks = long[1] - short[1]
    if ticks <= 0:
        return None
    return (long[0] - short[0]) / ticks


def count(side: str, seconds: float, polls: str) -> tuple[int, int]:
    """(instructions, ticks) of one child run under callgrind."""
    cmd = [
        "valgrind",
        "--tool=callgrind",
        "--callgrind-out-file=/dev/null",
        sys.executable,
        str(Path(__file__).resolve()),
        "--child",
        side,
        "--seconds",
        str(seconds),
        "--polls",
        polls,
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr[-2000:]}")
    ticks = json.loads(done.stdout.strip().splitlines()[-1])["ticks"]
    return collected(done.stderr), int(ticks)


def ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or not b else round(a / b, 3)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--polls", default="none,tick", help="bench_cpu.py's polls settings")
    parser.add_argument("--short", type=float, default=2.0, help="seconds of the short run")
    parser.add_argument("--long", type=float, default=6.0, help="seconds of the long run")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--child", choices=SIDES, help=argparse.SUPPRESS)
    parser.add_argument("--seconds", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child, args.seconds, args.polls)
        return 0
    settings = [p for p in args.polls.split(",") if p]
    if not settings or not set(settings) <= {"none", "tick"}:
        parser.error(f"--polls must list none and/or tick, got {args.polls!r}")
    if not 0 < args.short < args.long:
        parser.error(f"need 0 < --short < --long, got {args.short} and {args.long}")
    if shutil.which("valgrind") is None:
        raise SystemExit("count_instructions.py needs valgrind (apt-get install valgrind)")
    result: dict[str, Any] = {"short_s": args.short, "long_s": args.long, "buses": 1}
    print(f"{'polls':6} {'side':8} {'instructions a tick':>20} {'ticks (short, long)':>20}")
    for polls in settings:
        row: dict[str, Any] = {}
        for side in SIDES:
            short, long = count(side, args.short, polls), count(side, args.long, polls)
            expected = round(args.long / 0.01)
            kept_up = long[1] >= KEPT_UP_SHARE * expected
            value = per_tick(short, long)
            row[side] = {
                "instructions_per_tick": None if value is None else round(value),
                "ticks": [short[1], long[1]],
                "kept_up": kept_up,
            }
            shown = "-" if value is None else f"{value:,.0f}"
            mark = "" if kept_up else "  (fell behind)"
            print(f"{polls:6} {side:8} {shown:>20} {(short[1], long[1])!s:>20}{mark}")
        ours = row["ours"]["instructions_per_tick"]
        row["ratio_timerfd"] = ratio(ours, row["timerfd"]["instructions_per_tick"])
        row["ratio_minimal"] = ratio(ours, row["minimal"]["instructions_per_tick"])
        print(f"{polls:6} ours / (b) {row['ratio_timerfd']}, ours / minimal {row['ratio_minimal']}")
        result[f"polls_{polls}"] = row
    write_report(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
