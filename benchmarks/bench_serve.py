"""Served bus against embedded, in one run: request round trip and the deadman.

    python benchmarks/bench_serve.py [--requests 2000] [--kills 10] [--out FILE]

Against one simulated LA (``motorbus sim`` in its own process, over a pty, 921600
baud):

* round trip of a status query (``InspireLA.status``): embedded (a ``Bus`` in this
  process) and served (``motorbus serve`` in its own process, this process a client
  through ``motorbus.connect`` on loopback), p50/p99 of ``--requests`` each, same run;
* the deadman: a client process moves la:1 and is killed with SIGKILL (or frozen with
  SIGSTOP: a client gone silent); the time from the signal to the simulator logging
  the pause (the last safe frame), polled every 0.5 ms (an upper bound by up to the
  poll period and the simulator's log write).

Prints a table and writes ``benchmarks/results/serve.json``.  Many buses and clients
per server, and the server's CPU per bus-tick: ``bench_serve_scale.py``; served
streams: ``bench_serve_stream.py``.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import platform
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import motorbus
from harness import write_report
from motorbus import Bus, InspireLA, open_transport
from motorbus.protocol import la
from motorbus.sim import SimProcess

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "serve.json"
BAUD = 921600
PAUSE_1 = la.Control(1, la.ControlAction.PAUSE).encode()

CHILD = """
import asyncio, sys, motorbus
from motorbus import InspireLA
async def main():
    async with motorbus.connect(sys.argv[1], name="victim") as site:
        await InspireLA(site.bus(), 1).move_to(int(sys.argv[2]))
        print("moved", flush=True)
        await asyncio.sleep(60)
asyncio.run(main())
"""


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def pct(values: list[float], p: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(p / 100 * (len(ordered) - 1)))]


async def embedded(path: str, n: int) -> list[float]:
    out = []
    async with Bus(open_transport(path, baudrate=BAUD)) as bus:
        actuator = InspireLA(bus, 1)
        for _ in range(n):
            t = time.perf_counter()
            await actuator.status()
            out.append(time.perf_counter() - t)
    return out


async def served(endpoint: str, n: int) -> list[float]:
    out = []
    async with motorbus.connect(endpoint) as site:
        actuator = InspireLA(site.bus(), 1)
        for _ in range(n):
            t = time.perf_counter()
            await actuator.status()
            out.append(time.perf_counter() - t)
    return out


PAUSE_HEX = " ".join(f"{b:02X}" for b in PAUSE_1)


def pause_logged(log: Path, offset: int) -> tuple[bool, int]:
    """Whether the simulator logged a pause of la:1 after ``offset``; the new offset.
    Only the new bytes are read, so the poll stays cheap however long the log is."""
    with log.open("rb") as fh:
        fh.seek(offset)
        data = fh.read()
    end = data.rfind(b"\n") + 1
    for line in data[:end].splitlines():
        if PAUSE_HEX.encode() in line and b'"request"' in line:
            return True, offset + end
    return False, offset + end


def deadman(log: Path, endpoint: str, target: int, sig: int = signal.SIGKILL) -> float:
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, endpoint, str(target)],
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        assert child.stdout is not None
        if child.stdout.readline().strip() != "moved":
            raise RuntimeError("the client did not move")
        time.sleep(0.2)
        _, offset = pause_logged(log, 0)
        killed = time.monotonic()
        os.kill(child.pid, sig)
        deadline = killed + 10
        while True:
            seen, offset = pause_logged(log, offset)
            if seen:
                break
            if time.monotonic() > deadline:
                raise RuntimeError("no pause within 10 s of the kill")
            time.sleep(0.0005)
        return time.monotonic() - killed
    finally:
        child.kill()
        child.wait()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--requests", type=int, default=2000)
    parser.add_argument("--kills", type=int, default=10)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "sim.jsonl"
        with SimProcess(["la:1"], baud=BAUD, log_file=log) as sim:
            emb = asyncio.run(embedded(sim.path, args.requests))
            endpoint = free_endpoint()
            server = subprocess.Popen(
                [sys.executable, "-m", "motorbus", "serve", "--port", sim.path, "--baud",
                 str(BAUD), "--devices", "la:1", "--listen", endpoint],
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
            )  # fmt: skip
            try:
                assert server.stdout is not None
                server.stdout.readline()
                srv = asyncio.run(served(endpoint, args.requests))
                kills = [deadman(log, endpoint, 500 + 100 * i) for i in range(args.kills)]
                stops = [
                    deadman(log, endpoint, 550 + 100 * i, signal.SIGSTOP)
                    for i in range(max(1, args.kills // 2))
                ]
            finally:
                server.terminate()
                server.wait(15)
    ms = 1e3
    report = {
        "python": platform.python_version(),
        "command": "python benchmarks/bench_serve.py " + " ".join(argv or sys.argv[1:]),
        "requests": args.requests,
        "embedded_ms": {"p50": pct(emb, 50) * ms, "p99": pct(emb, 99) * ms},
        "served_ms": {"p50": pct(srv, 50) * ms, "p99": pct(srv, 99) * ms},
        "deadman_sigkill_ms": {
            "median": statistics.median(kills) * ms,
            "max": max(kills) * ms,
            "runs": [k * ms for k in kills],
        },
        "deadman_sigstop_ms": {
            "liveness_s": 1.0,
            "median": statistics.median(stops) * ms,
            "max": max(stops) * ms,
            "runs": [k * ms for k in stops],
        },
    }
    print(f"{'status round trip':28} {'p50 ms':>8} {'p99 ms':>8}")
    for name in ("embedded", "served"):
        row = report[f"{name}_ms"]
        assert isinstance(row, dict)
        print(f"{name:28} {row['p50']:8.3f} {row['p99']:8.3f}")
    dm = report["deadman_sigkill_ms"]
    assert isinstance(dm, dict)
    print(
        f"deadman SIGKILL -> pause at the simulator: median {dm['median']:.1f} ms, "
        f"max {dm['max']:.1f} ms over {args.kills} kills (goal <= 50 ms)"
    )
    ds = report["deadman_sigstop_ms"]
    assert isinstance(ds, dict)
    print(
        f"deadman SIGSTOP -> pause at the simulator: median {ds['median']:.0f} ms, "
        f"max {ds['max']:.0f} ms over {len(stops)} freezes (--liveness 1 s)"
    )
    write_report(args.out, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
