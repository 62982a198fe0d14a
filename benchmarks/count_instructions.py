"""CPU per bus-tick as a count: the instructions ``bench_cpu.py``'s loops execute a tick,
and their first-level cache misses.

``bench_cpu.py`` times the loops, and on this shared 2-core VM one round's ratio to (b)
ranges from 0.95 to 2.5 for the same code.  This script counts instead: each loop
(``ours``, (b) ``timerfd``, ``minimal``: ``bench_cpu.py``'s, on one bus, the same work)
runs in a child process under valgrind's cachegrind, which counts every user-space
instruction the process executes and simulates its caches, once for ``--short`` and once
for ``--long`` seconds of ticks; the difference over the difference in ticks sent is what
one tick costs, the start-up (imports, opening the port) cancelling out.  A count does
not move with the machine's load; two runs of the same code agree to about 1 %.

Besides the instructions: the misses of the simulated first-level instruction and data
caches (``I1``, ``D1``; valgrind sizes them as this machine's), a count of how much code
and data a tick touches that the instructions alone do not show, and which makes the
same instructions cost more time.  The simulated caches hold only this process's
accesses: the misses after another process ran in the 10 ms between ticks are not in
them.  Nor is the kernel's side of each system call (``bench_cpu.py``'s CPU includes
it).  Valgrind slows the child about 50x, so one bus only.  A child kept up if it sent
95 % of its ticks, with polls got as many replies, and had at most 5 % of its ticks late
(over 1 ms); a run whose cache simulation slowed it past that is counted again without
the simulation (instructions only; ``caches_simulated`` false), and a row that fell
behind even so is marked (its count is of a saturated loop's work).  Ours's count
includes ``harness.TimerProbe``, ``bench_cpu.py``'s counter of timer arms (a few dozen
instructions an arm).

    python benchmarks/count_instructions.py [--polls none,tick] [--short 2] [--long 6]
        [--sides ours,timerfd,minimal] [--out PATH]

``--sides`` may also name ``bench_cpu_parts.py``'s sides (``no_leases``, ``no_stats``,
``direct_write``, ``without_all``: ours with those guarantees doing nothing), each
counted and put over (b) and the minimal loop where those are counted too.

Needs ``valgrind`` (Debian: ``apt-get install valgrind``).  Writes
``benchmarks/results/instructions.json``: per polls setting and side, the instructions
and the I1 and D1 misses a tick, and ours over (b) and over the minimal loop.
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
#: ``bench_cpu_parts.py``'s sides: ours with parts of its work taken out.
PART_SIDES = ("no_leases", "no_stats", "direct_write", "without_all")
#: A child kept up under valgrind if it sent this share of its ticks at least, with
#: polls got as many replies, and had at most ``LATE_SHARE`` of its ticks late.
KEPT_UP_SHARE = 0.95
LATE_SHARE = 0.05
#: cachegrind's summary lines: "==pid== I   refs:      1,843,299,318", and so on.
COUNTS = {"instructions": "I   refs", "i1_misses": "I1  misses", "d1_misses": "D1  misses"}


def child(side: str, seconds: float, polls: str) -> None:
    """Run one side of ``bench_cpu.py`` (or of ``bench_cpu_parts.py``) on one bus;
    print its ticks as JSON."""
    import bench_cpu
    import bench_cpu_parts

    with tempfile.TemporaryDirectory(prefix="motorbus-instr-") as tmp:
        responder = bench_cpu.Responder(1, Path(tmp) / "rec.json")
        try:
            if side in PART_SIDES:
                out = bench_cpu_parts.run_once(side, responder.paths, seconds, polls)
            else:
                out = bench_cpu.run_side(side, responder.paths, seconds, polls, None)
        finally:
            responder.stop()
    keys = ("ticks", "replies", "late_ticks")
    print(json.dumps({k: out.get(k) for k in keys} | {"polls": polls}))


def collected(stderr: str, caches: bool = True) -> dict[str, int]:
    """The counts of cachegrind's summary in ``stderr`` (``COUNTS``'s keys; without
    ``caches``, the instructions only)."""
    counts = {}
    for key, label in COUNTS.items() if caches else [("instructions", COUNTS["instructions"])]:
        found = re.findall(re.escape(label) + r":\s*([\d,]+)", stderr)
        if not found:
            raise RuntimeError(f"no cachegrind summary in valgrind's output:\n{stderr[-2000:]}")
        counts[key] = int(found[-1].replace(",", ""))
    return counts


def per_tick(short: tuple[int, int], long: tuple[int, int]) -> float | None:
    """A count a tick from two runs' (count, ticks): the difference of the counts over
    the difference of the ticks (None if the ticks did not grow)."""
    ticks = long[1] - short[1]
    if ticks <= 0:
        return None
    return (long[0] - short[0]) / ticks


def kept_up(report: dict[str, Any], seconds: float) -> bool:
    """Whether a child's run (its printed ``report``) kept up with its ticks."""
    due = round(seconds / 0.01)
    ticks = report["ticks"]
    replies_ok = report["polls"] == "none" or (report["replies"] or 0) >= KEPT_UP_SHARE * due
    late_ok = (report.get("late_ticks") or 0) <= LATE_SHARE * ticks
    return ticks >= KEPT_UP_SHARE * due and replies_ok and late_ok


def count(side: str, seconds: float, polls: str, caches: bool) -> tuple[dict[str, int], bool]:
    """(counts with their ``"ticks"``, kept up) of one child run under cachegrind,
    simulating the caches or not (the simulation slows the child further)."""
    cmd = [
        "valgrind",
        "--tool=cachegrind",
        f"--cache-sim={'yes' if caches else 'no'}",
        "--cachegrind-out-file=/dev/null",
        sys.executable,
        str(Path(__file__).resolve()),
        "--child",
        side,
        "--seconds",
        str(seconds),
        "--polls",
        polls,
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=900, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stderr[-2000:]}")
    report = json.loads(done.stdout.strip().splitlines()[-1])
    counts = collected(done.stderr, caches) | {"ticks": int(report["ticks"])}
    return counts, kept_up(report, seconds)


def ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or not b else round(a / b, 3)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--polls", default="none,tick", help="bench_cpu.py's polls settings")
    parser.add_argument("--short", type=float, default=2.0, help="seconds of the short run")
    parser.add_argument("--long", type=float, default=6.0, help="seconds of the long run")
    parser.add_argument("--sides", default=",".join(SIDES), help="the loops to count")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--child", choices=SIDES + PART_SIDES, help=argparse.SUPPRESS)
    parser.add_argument("--seconds", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child, args.seconds, args.polls)
        return 0
    settings = [p for p in args.polls.split(",") if p]
    if not settings or not set(settings) <= {"none", "tick"}:
        parser.error(f"--polls must list none and/or tick, got {args.polls!r}")
    sides = [x for x in args.sides.split(",") if x]
    if not sides or not set(sides) <= set(SIDES + PART_SIDES):
        parser.error(f"--sides must list some of {', '.join(SIDES + PART_SIDES)}")
    if not 0 < args.short < args.long:
        parser.error(f"need 0 < --short < --long, got {args.short} and {args.long}")
    if shutil.which("valgrind") is None:
        raise SystemExit("count_instructions.py needs valgrind (apt-get install valgrind)")
    result: dict[str, Any] = {"short_s": args.short, "long_s": args.long, "buses": 1}
    print(
        f"{'polls':6} {'side':12} {'instructions':>12} {'I1 misses':>10} {'D1 misses':>10}  ticks"
    )
    for polls in settings:
        row: dict[str, Any] = {}
        for side in sides:
            caches = True
            (short, short_ok), (long, long_ok) = (
                count(side, args.short, polls, caches),
                count(side, args.long, polls, caches),
            )
            if not (short_ok and long_ok):  # the simulation slowed it too much: without
                caches = False
                (short, short_ok), (long, long_ok) = (
                    count(side, args.short, polls, caches),
                    count(side, args.long, polls, caches),
                )
            figures = {
                f"{key}_per_tick": per_tick(
                    (short[key], short["ticks"]), (long[key], long["ticks"])
                )
                if key in long
                else None
                for key in COUNTS
            }
            row[side] = {
                **{k: None if v is None else round(v) for k, v in figures.items()},
                "ticks": [short["ticks"], long["ticks"]],
                "caches_simulated": caches,
                "kept_up": short_ok and long_ok,
            }
            shown = ["-" if v is None else f"{v:,.0f}" for v in figures.values()]
            mark = "" if short_ok and long_ok else "  (fell behind)"
            print(
                f"{polls:6} {side:12} {shown[0]:>12} {shown[1]:>10} {shown[2]:>10}"
                f"  {short['ticks']}, {long['ticks']}{mark}"
            )
        for mine in [x for x in sides if x in ("ours", *PART_SIDES)]:
            for base in [x for x in ("timerfd", "minimal") if x in sides]:
                ratios = {
                    key: ratio(row[mine][f"{key}_per_tick"], row[base][f"{key}_per_tick"])
                    for key in COUNTS
                }
                prefix = "" if mine == "ours" else f"{mine}_"
                row |= {f"{prefix}{key}_ratio_{base}": r for key, r in ratios.items()}
                shown = ", ".join(f"{key} {r}" for key, r in ratios.items())
                print(f"{polls:6} {mine} / {base}: {shown}")
        result[f"polls_{polls}"] = row
    write_report(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
