"""A served stream's tick jitter against an embedded one's, in one run, on the kernel clock.

    python benchmarks/bench_serve_stream.py [--seconds 10] [--rounds 9] [--out FILE]

One simulated LA (``motorbus sim`` in its own process, over a pty, 921600 baud), a
100 Hz follow stream (``period=0.01``, one 9-byte 0xF3 broadcast a tick):

* embedded: ``Streamer(bus).follow(...)`` on a ``Bus`` in this process; the write(2)
  calls of this process are traced;
* served: ``motorbus serve`` in its own process, this process a client
  (``motorbus.connect``) whose ``Streamer(site.bus()).follow(...)`` makes the same
  calls; the write(2) calls of the server process are traced.

Two sources each way: ``rows`` (a list: the client sends them ahead in batches) and
``per-tick`` (a callable ``f(t, statuses)``: the client publishes one target per tick
as it goes).  The rounds alternate embedded and served, so both see the same machine.
The figure is the tick jitter of ``kernel_clock.port_figures``: each tick's write(2)
to the pty against a least-squares grid (so a constant offset is not counted), p50 and
p99 in microseconds, as ``bench_stream.py`` reports it; and the stream's own record
(``stream.stats``: lateness against its deadline).  The ratio is served over embedded,
of the medians over the rounds.  Nine rounds by default (about 9 minutes): a round's
p99 is its tenth-worst tick of 1,000, which moved from 200 to 380 us from round to round
either way on a quiet 2-core VM, and the ratio of three rounds' medians moved from 0.75x
to 1.34x between runs of the same code.  Without ``perf`` (root, or a permissive
``perf_event_paranoid``) the kernel figures say "not measured", never made up.

Prints a table and writes ``benchmarks/results/serve_stream.json``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import motorbus
from harness import write_report
from kernel_clock import KernelWriteTrace, port_figures
from motorbus import Bus, InspireLA, Streamer, open_transport
from motorbus.sim import SimProcess

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "serve_stream.json"
BAUD = 921600
PERIOD_S = 0.01
#: One 0xF3 follow broadcast to one actuator: 55 AA len FF F3 id lo hi checksum.
TICK_BYTES = 9


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def position(k: int) -> int:
    """A triangle wave 100..1900 (the trajectory of every run)."""
    phase = k % 360
    return 100 + 10 * (phase if phase < 180 else 360 - phase)


def source(kind: str, ticks: int) -> Any:
    if kind == "rows":
        return [position(k) for k in range(ticks)]

    def per_tick(t: float, statuses: object) -> int | None:
        k = round(t / PERIOD_S)
        return position(k) if k < ticks else None

    return per_tick


async def stream_on(bus: Any, kind: str, ticks: int) -> dict[str, Any]:
    stream = Streamer(bus).follow(InspireLA(bus, 1), source(kind, ticks), period=PERIOD_S)
    await stream.wait()
    return dict(stream.stats.as_dict())


async def embedded(path: str, kind: str, ticks: int) -> dict[str, Any]:
    async with Bus(open_transport(path, baudrate=BAUD)) as bus:
        return await stream_on(bus, kind, ticks)


async def served(endpoint: str, kind: str, ticks: int) -> dict[str, Any]:
    async with motorbus.connect(endpoint) as site:
        return await stream_on(site.bus(), kind, ticks)


def measure(mode: str, kind: str, ticks: int, sim: SimProcess, server: int, ep: str) -> dict:
    pid = os.getpid() if mode == "embedded" else server
    with KernelWriteTrace(pid=pid) as trace:
        if mode == "embedded":
            own = asyncio.run(embedded(sim.path, kind, ticks))
        else:
            own = asyncio.run(served(ep, kind, ticks))
    kernel = port_figures(
        trace, [TICK_BYTES], tick_bytes=TICK_BYTES, period=PERIOD_S, expected_ticks=ticks
    )
    return {"mode": mode, "source": kind, "stream": own, "kernel": kernel}


def median(values: list[float | None]) -> float | None:
    present = [v for v in values if v is not None and v == v]
    return statistics.median(present) if present else None


def fmt(value: float | None) -> str:
    return "n/m" if value is None else f"{value:.0f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--seconds", type=float, default=10.0, help="per stream (default 10)")
    parser.add_argument("--rounds", type=int, default=9, help="alternating rounds (default 9)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    ticks = round(args.seconds / PERIOD_S)
    runs: list[dict[str, Any]] = []
    # Two simulators, one each (the server holds its port), both up for the whole run.
    with (
        tempfile.TemporaryDirectory() as tmp,
        SimProcess(["la:1"], baud=BAUD, log_file=Path(tmp) / "embedded.jsonl") as sim,
        SimProcess(["la:1"], baud=BAUD, log_file=Path(tmp) / "served.jsonl") as served_sim,
    ):
        endpoint = free_endpoint()
        server = subprocess.Popen(
            [sys.executable, "-m", "motorbus", "serve", "--port", served_sim.path, "--baud",
             str(BAUD), "--devices", "la:1", "--listen", endpoint],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )  # fmt: skip
        try:
            assert server.stdout is not None
            if not server.stdout.readline().startswith("serving"):
                raise RuntimeError("motorbus serve did not start")
            for n in range(args.rounds):
                for kind in ("rows", "per-tick"):
                    for mode in ("embedded", "served") if n % 2 == 0 else ("served", "embedded"):
                        run = measure(mode, kind, ticks, sim, server.pid, endpoint)
                        run["round"] = n
                        runs.append(run)
                        print(f"round {n} {mode:8} {kind:8} done", file=sys.stderr, flush=True)
        finally:
            server.terminate()
            server.wait(10)
    summary: dict[str, Any] = {}
    rows = []
    for kind in ("rows", "per-tick"):
        for mode in ("embedded", "served"):
            mine = [r for r in runs if r["mode"] == mode and r["source"] == kind]
            entry = {
                "kernel_tick_jitter_p50_us": median(
                    [r["kernel"].get("kernel_tick_jitter_p50_us") for r in mine]
                ),
                "kernel_tick_jitter_p99_us": median(
                    [r["kernel"].get("kernel_tick_jitter_p99_us") for r in mine]
                ),
                "kernel_ticks_sent_pct": median(
                    [r["kernel"].get("kernel_ticks_sent_pct") for r in mine]
                ),
                "stream_jitter_p50_us": median([r["stream"]["jitter_p50_us"] for r in mine]),
                "stream_jitter_p99_us": median([r["stream"]["jitter_p99_us"] for r in mine]),
                "late": sum(r["stream"]["late"] for r in mine),
                "skipped": sum(r["stream"]["skipped"] for r in mine),
                "held": sum(r["stream"].get("held", 0) for r in mine),
            }
            summary[f"{mode}/{kind}"] = entry
            rows.append((mode, kind, entry))
        emb, srv = summary[f"embedded/{kind}"], summary[f"served/{kind}"]
        for q in ("p50", "p99"):
            a, b = emb[f"kernel_tick_jitter_{q}_us"], srv[f"kernel_tick_jitter_{q}_us"]
            summary[f"ratio/{kind}/{q}"] = None if not a or b is None else b / a
    print(
        f"\n100 Hz follow stream, one LA over a pty at {BAUD} baud, {args.rounds} rounds of "
        f"{args.seconds:g} s (medians over rounds; kernel clock: write(2) to the pty)\n"
    )
    heads = ("kernel p50 us", "kernel p99 us", "stream p50 us", "stream p99 us")
    print(f"{'mode':9} {'source':9} " + " ".join(f"{h:>13}" for h in heads), end="")
    print(f" {'late':>5} {'skipped':>7} {'held':>5}")
    for mode, kind, e in rows:
        print(
            f"{mode:9} {kind:9} {fmt(e['kernel_tick_jitter_p50_us']):>13} "
            f"{fmt(e['kernel_tick_jitter_p99_us']):>13} {fmt(e['stream_jitter_p50_us']):>13} "
            f"{fmt(e['stream_jitter_p99_us']):>13} {e['late']:>5} {e['skipped']:>7} "
            f"{e['held']:>5}"
        )
    for kind in ("rows", "per-tick"):
        p50, p99 = summary[f"ratio/{kind}/p50"], summary[f"ratio/{kind}/p99"]
        shown = " ".join(
            f"{q} {'n/m' if v is None else f'{v:.2f}x'}" for q, v in (("p50", p50), ("p99", p99))
        )
        print(f"served / embedded kernel tick jitter, {kind}: {shown} (goal <= 1.2x)")
    report = {
        "benchmark": "serve_stream",
        "command": "python benchmarks/bench_serve_stream.py " + " ".join(argv or sys.argv[1:]),
        "period_s": PERIOD_S,
        "seconds": args.seconds,
        "rounds": args.rounds,
        "summary": summary,
        "runs": runs,
    }
    # Anything not JSON-ready is written as its str(), as before write_report.
    write_report(args.out, json.loads(json.dumps(report, default=str)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
