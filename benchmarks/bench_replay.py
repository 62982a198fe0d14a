"""How close to their recorded times ``motorbus replay --to`` sends requests.

A frame log of N LA status queries recorded 10 ms apart (IDs 1-3 in turn) is replayed
to ``pty_recorder.py --answer`` (which answers at once), and the replay's write(2)
calls are traced on the kernel's clock (``kernel_clock.py``).  The k-th write is held
to slot k of a 10 ms grid whose origin is fitted (``grid_jitter(by_index=True)``: a
constant offset is not counted, drift and wobble are), as a device expecting the
recorded pace would see it.  Also counted: gaps between consecutive writes more than
1 ms off the recorded 10 ms.

``--before-src DIR`` also runs the same measurement against another source tree (e.g. a
``git archive`` of the commit before), in a child process with ``PYTHONPATH=DIR``, and
prints both.  Prints a table and writes ``benchmarks/results/replay.json``.

    python benchmarks/bench_replay.py [--requests 200] [--before-src /tmp/old/src]
"""

from __future__ import annotations

import argparse
import io
import itertools
import json
import os
import signal
import subprocess
import sys
import tempfile
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Any

from harness import write_report
from kernel_clock import KernelWriteTrace, grid_jitter

RESULTS = Path(__file__).resolve().parent / "results" / "replay.json"
PERIOD_S = 0.010
QUERY_BYTES = 8
OFF_S = 1e-3


def write_log(path: Path, requests: int) -> None:
    from motorbus.protocol import la  # the motorbus under test (PYTHONPATH)

    header = {"format": "motorbus-frame-log", "version": 1, "source": "capture",
              "started_utc": "2026-01-01T00:00:00.000000Z", "families": ["la"],
              "baud": 921600, "port": None}  # fmt: skip
    lines = [json.dumps(header)]
    for n in range(requests):
        raw = la.Control(1 + n % 3, la.ControlAction.QUERY_STATUS).encode()
        lines.append(json.dumps({"t": round(n * PERIOD_S, 6), "kind": "frame", "family": "la",
                                 "direction": "request", "hex": raw.hex(" ").upper()}))  # fmt: skip
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def measure(requests: int) -> dict[str, Any]:
    """Replay in this process, traced; the figures."""
    from motorbus.cli.main import main

    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "log.jsonl"
        write_log(log, requests)
        recorder = subprocess.Popen(
            [sys.executable, str(Path(__file__).with_name("pty_recorder.py")), "1",
             str(Path(tmp) / "rec.json"), "--answer"],
            stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        assert recorder.stdout is not None
        port = recorder.stdout.readline().strip()
        try:
            out, err = io.StringIO(), io.StringIO()
            with KernelWriteTrace() as trace, redirect_stdout(out), redirect_stderr(err):
                code = main(["replay", str(log), "--to", port, "--wait", "0.05"])
        finally:
            recorder.send_signal(signal.SIGINT)
            recorder.wait(timeout=30)
    result: dict[str, Any] = {"requests": requests, "exit": code, "summary": err.getvalue()[-200:]}
    if not trace.measured:
        return {**result, "kernel_measured": False, "kernel_why": trace.why}
    fds = {c.fd for c in trace.calls if c.count == QUERY_BYTES and c.fd > 2}
    starts = sorted(c.start for c in trace.calls if c.fd in fds and c.count == QUERY_BYTES)
    fit = grid_jitter(starts, PERIOD_S, by_index=True)
    gaps = [b - a for a, b in itertools.pairwise(starts)]
    result.update(
        {
            "kernel_measured": True,
            "writes": len(starts),
            "jitter_p50_us": round(fit.p50_us, 1),
            "jitter_p99_us": round(fit.p99_us, 1),
            "jitter_max_us": round(fit.max_us, 1),
            "gaps_off_by_over_1ms": sum(1 for g in gaps if abs(g - PERIOD_S) > OFF_S),
            "gaps": len(gaps),
        }
    )
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=200)
    parser.add_argument("--before-src", type=Path, help="source tree (its src/) to compare")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args.requests)))
        return 0
    runs: dict[str, Any] = {}
    if args.before_src is not None:
        env = {**os.environ, "PYTHONPATH": str(args.before_src)}
        child = subprocess.run(
            [sys.executable, __file__, "--child", "--requests", str(args.requests)],
            env=env, capture_output=True, text=True, check=True,
        )  # fmt: skip
        runs["before"] = json.loads(child.stdout.splitlines()[-1])
    runs["after"] = measure(args.requests)
    keys = ("writes", "jitter_p50_us", "jitter_p99_us", "jitter_max_us", "gaps_off_by_over_1ms")
    print(f"{'run':8s}" + "".join(f"{k:>22s}" for k in keys))
    for label, r in runs.items():
        if not r.get("kernel_measured"):
            print(f"{label:8s}  not measured: {r.get('kernel_why')}")
            continue
        print(f"{label:8s}" + "".join(f"{r[k]!s:>22s}" for k in keys))
    write_report(RESULTS, {"period_s": PERIOD_S, "runs": runs})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
