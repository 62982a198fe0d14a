"""Where a round trip's time goes: before the write, on the line, after the reply is read.

``InspireLA.status()`` on a ``Bus`` over a pty to the LA simulator (a child process, as
in ``bench_bus.py``), paced at one call per 1.5 ms.  Each call is split by this
process's own ``os.write`` of the request and ``os.read`` of the reply (both wrapped):

* ``to_write``: from the call to the request's ``write`` (our code: checks, leases,
  scheduling, the input drain);
* ``write_to_read``: from the write to the read that brought the reply (the pty, the
  simulator and the loop's wake-up);
* ``read_to_done``: from that read to the call's return (our code: reassembler, matcher,
  the future, the task's step).

Medians over ``--n`` calls, in µs.  ``--before-src DIR`` runs the same measurement
against another source tree (``PYTHONPATH=DIR``, in a child process), alternating
``--pairs`` times, so that a before and an after come from the same sitting.

    python benchmarks/bench_rtt_split.py [--n 800] [--pairs 3] [--before-src OLD/src]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from bench_bus import BAUD, DEFAULT_BACKEND, PACE_S, served

PARTS = ("to_write", "write_to_read", "read_to_done", "total")
#: A reply is the read that brings at least this many bytes (a status is 22).
REPLY_MIN_BYTES = 20


async def measure(path: str, n: int) -> dict[str, float]:
    """Median µs of each part over ``n`` status calls on a bus over ``path``."""
    from motorbus.bus.bus import Bus
    from motorbus.bus.timer import default_timer
    from motorbus.devices.la import InspireLA
    from motorbus.protocol.base import Family
    from motorbus.transport.serial import SerialTransport

    marks: dict[str, float] = {}
    real_write, real_read = os.write, os.read

    def write(fd: int, data: Any) -> int:
        marks.setdefault("w", time.perf_counter())
        return real_write(fd, data)

    def read(fd: int, size: int) -> bytes:
        data = real_read(fd, size)
        if len(data) >= REPLY_MIN_BYTES:
            marks.setdefault("r", time.perf_counter())
        return data

    timer = default_timer()
    transport = SerialTransport(path, baudrate=BAUD, backend=DEFAULT_BACKEND)
    rows: list[tuple[float, float, float, float]] = []
    os.write, os.read = write, read  # type: ignore[assignment]
    try:
        async with Bus(transport, families=[Family.LA], host_margin=0.05) as bus:
            actuator = InspireLA(bus, 1)
            await actuator.status()  # warm-up
            origin = timer.now() + PACE_S
            for k in range(n):
                await timer.sleep_until(origin + k * PACE_S)
                marks.clear()
                t0 = time.perf_counter()
                await actuator.status()
                done = time.perf_counter()
                if "w" in marks and "r" in marks:
                    w, r = marks["w"], marks["r"]
                    rows.append((w - t0, r - w, done - r, done - t0))
    finally:
        os.write, os.read = real_write, real_read
    if not rows:
        raise RuntimeError("no round trip was split: the reads or writes were not seen")
    return {
        part: round(sorted(row[i] for row in rows)[len(rows) // 2] * 1e6, 1)
        for i, part in enumerate(PARTS)
    }


def one(n: int) -> dict[str, float]:
    with served("process", None) as path:
        return asyncio.run(measure(path, n))


def in_child(src: str, n: int) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([src, str(Path(__file__).parent)])}
    out = subprocess.run(
        [sys.executable, __file__, "--n", str(n), "--child"],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=300,
    )
    result: dict[str, float] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=800, help="round trips per measurement")
    parser.add_argument("--pairs", type=int, default=3, help="alternations with --before-src")
    parser.add_argument("--before-src", help="another source tree to measure in turn")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.n < 10 or args.pairs < 1:
        parser.error(f"--n must be >= 10 and --pairs >= 1, got {args.n} and {args.pairs}")
    if args.child:
        print(json.dumps(one(args.n)))
        return 0
    here = str(Path(__file__).resolve().parents[1] / "src")
    runs: list[tuple[str, dict[str, float]]] = []
    for _ in range(args.pairs if args.before_src else 1):
        if args.before_src:
            runs.append(("before", in_child(args.before_src, args.n)))
        runs.append(("after" if args.before_src else "this tree", in_child(here, args.n)))
    print(f"status round trip split, median µs over {args.n} calls each")
    print(f"{'run':10}" + "".join(f"{p:>16}" for p in PARTS))
    for label, r in runs:
        print(f"{label:10}" + "".join(f"{r[p]:>16.1f}" for p in PARTS))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
