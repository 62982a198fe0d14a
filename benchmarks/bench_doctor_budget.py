"""``motorbus doctor``'s cycle budget: the occupancy model's theory against a measurement.

For 1, 8 and 15 LA actuators at a 10 ms period (``--period``), ``motorbus sim`` serves
them in a child process (``SimProcess``, wire pacing at 921600 bit/s) and the doctor's
library call (``motorbus.diagnose``) runs its read-only sequence; this prints, from its
``budget`` finding, the theory (broadcast tick, status reads that fit between ticks,
shortest period) beside the measurement (status reads a tick actually answered in the
gaps the ticks leave, for ``--seconds``).  The theory takes the LA's worst-case
turnaround (800 us, manual 3.4.2); the simulator answers in 120 us typically, so the
measurement may exceed it; a measurement more than 20 % short is the doctor's yellow.

Prints a table and writes ``benchmarks/results/doctor_budget.json``.

Usage: ``python benchmarks/bench_doctor_budget.py [--seconds 3] [--period 10] [--realtime]
[--out PATH]``
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import json
import os
import platform
from pathlib import Path
from typing import Any

from motorbus import DoctorConfig, diagnose
from motorbus.runtime import realtime
from motorbus.sim.process import SimProcess

BAUD = 921600
COUNTS = (1, 8, 15)
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "doctor_budget.json"


async def one(n: int, seconds: float, period_ms: float) -> dict[str, Any]:
    with SimProcess([f"la:1-{n}" if n > 1 else "la:1"], baud=BAUD) as sim:
        config = DoctorConfig(
            sim.path,
            BAUD,
            ids=tuple(range(1, n + 1)),
            period_s=period_ms / 1e3,
            requests=10,
            measure_s=seconds,
        )
        report = await diagnose(config)
    budget = report.finding("budget")
    theory, measured = budget.data["theory"], budget.data.get("measured", {})
    expected = theory["polls_between_ticks"]
    got = measured.get("polls_per_tick", 0.0)
    return {
        "actuators": n,
        "level": budget.level.value,
        "theory": theory,
        "measured": measured,
        "gap_pct": (1 - got / expected) * 100 if expected else None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--period", type=float, default=10.0, help="ms")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument(
        "--realtime", action="store_true", help="run the doctor under realtime.enable()"
    )
    args = parser.parse_args()
    load = os.getloadavg()
    rt = realtime.enable() if args.realtime else None
    try:
        rows = [asyncio.run(one(n, args.seconds, args.period)) for n in COUNTS]
    finally:
        if rt is not None:
            realtime.disable(rt)
    mode = f", realtime {rt.as_dict()['applied']}" if rt is not None else ""
    print(f"cycle budget at {args.period:g} ms, {BAUD} bit/s, load {load[0]:.2f}{mode}")
    print(
        f"{'actuators':>9} {'tick ms':>8} {'frames':>6} {'reads/tick theory':>17} "
        f"{'measured':>8} {'gap %':>6} {'lost':>4} {'shortest ms':>11} {'polled ms':>9} level"
    )
    for r in rows:
        t, m = r["theory"], r["measured"]
        gap = f"{r['gap_pct']:.0f}" if r["gap_pct"] is not None else "-"
        print(
            f"{r['actuators']:>9} {t['tick_ms']:>8.2f} {t['broadcast_frames']:>6} "
            f"{t['polls_between_ticks']:>17} {m.get('polls_per_tick', 0.0):>8.2f} {gap:>6} "
            f"{m.get('lost', 0):>4} {t['shortest_period_ms']:>11.2f} "
            f"{t['shortest_period_polled_ms']:>9.2f} {r['level']}"
        )
    doc = {
        "benchmark": "doctor_budget",
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "load_avg": load},
        "period_ms": args.period,
        "seconds": args.seconds,
        "realtime": rt.as_dict() if rt is not None else None,
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
