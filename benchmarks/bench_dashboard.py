"""Fan-out of ``motorbus dashboard``: the bus's frames/s with 1 and with 50 WebSocket viewers,
and what 50 viewers connecting at once do to the bus.

The dashboard (one poller on the bus, the aiohttp server) runs here against
``motorbus sim`` on a pty; the viewers run in a child process, as browsers would, each
holding a WebSocket and reading every push.

* Steady: the bus's frames/s (``bus.stats.requests`` over a window) is measured with 1
  viewer and with 50, alternately, several times: the poller sets the traffic, so the
  two should agree (issue 25 asks for 1 % or better).
* Burst (issue 39): once the plots' window is full (``--fill`` seconds), ``--viewers``
  WebSockets connect at the same moment and an e-stop is posted among them.  Measured:
  the e-stop's round trip, the longest time the simulator saw no frame at all (from its
  own frame log), and the size of a new viewer's snapshot.

Prints tables and writes ``benchmarks/results/dashboard.json``.

    python benchmarks/bench_dashboard.py [--seconds 5] [--repeats 3] [--viewers 50] [--fill 30]

Served (``--served``, issue 39): ``motorbus serve`` owns the simulator's port in a
process of its own (``--realtime``: it and the dashboard's controls in real-time
mode); an application client (another
process) streams to la:1 at 100 Hz through it (``Streamer.follow``, a target per tick;
``--app move``: a move every 10 ms on absolute deadlines instead); ``motorbus dashboard
--connect`` (a third process) polls the five actuators.  Alternately, the same run: a
window without viewers (one e-stop of la:5 posted to the dashboard) and a window in
which ``--viewers`` WebSockets connect at once (from a process of their own) while
``motorbus capture`` records the simulator's tap (``sim --tap``: a listen-only copy),
with the e-stop posted 10 ms later from this script's process, which is otherwise idle
(posted from the viewers' process, as above, it would also time that busy process).
Measured in each window: the e-stop's round trip (HTTP post to answer, through the
server), the longest time the simulator saw no frame (its own log), and the stream's
tick jitter, p99, on the kernel's clock (the server's writes, ``perf``) and on the
simulator's (its log); with ``--app move``, the application's command jitter (how far
each interval between two completed moves is from 10 ms, p99) and its move round trip.
Writes ``benchmarks/results/dashboard_served.json``.

    python benchmarks/bench_dashboard.py --served [--seconds 3] [--repeats 5] [--fill 30]
        [--app stream|move] [--realtime]
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import aiohttp

import bench_dashboard_served
from harness import write_report
from motorbus import Bus, Family
from motorbus.dashboard import BusSetup, Dashboard
from motorbus.dashboard.server import make_app, serve_page
from motorbus.sim.process import SimProcess
from motorbus.transport.serial import open_transport

RESULTS = Path(__file__).resolve().parent / "results" / "dashboard.json"
IDS = (1, 2, 3, 4, 5)
PERIOD_S = 0.02


async def viewers_only(url: str, count: int) -> None:
    """Child process: hold ``count`` WebSockets, read every message, print counts at EOF."""
    received = [0] * count

    async def one(n: int, session: aiohttp.ClientSession) -> None:
        async with session.ws_connect(url, compress=15) as ws:  # as a browser does
            async for _ in ws:
                received[n] += 1

    async with aiohttp.ClientSession() as session:
        tasks = [asyncio.create_task(one(n, session)) for n in range(count)]
        await asyncio.sleep(0.5)
        print("ready", flush=True)
        await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    print(json.dumps(received), flush=True)


async def burst_only(base: str, count: int, body: str = "{}") -> None:
    """Child process: at "go", connect ``count`` viewers at once and post an e-stop
    (``body``: which devices, as the page posts it; ``{}`` is every one; ``none``: no
    e-stop, the caller posts it from a process of its own)."""

    async def one(session: aiohttp.ClientSession) -> int:
        # As a browser does (Chromium offers permessage-deflate): compressed if the
        # dashboard agrees.
        async with session.ws_connect(f"ws://{base}/ws", compress=15) as ws:
            msg = await ws.receive(timeout=60)
            return len(msg.data)

    async def estop(session: aiohttp.ClientSession) -> float:
        await asyncio.sleep(0.01)  # posted while the viewers' snapshots are being built
        t0 = time.perf_counter()
        async with session.post(f"http://{base}/api/estop", json=json.loads(body)) as r:
            assert r.status == 200, await r.text()
        return time.perf_counter() - t0

    connector = aiohttp.TCPConnector(limit=0)
    async with aiohttp.ClientSession(connector=connector) as session:
        print("ready", flush=True)
        await asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline)
        t0 = time.perf_counter()
        stop_task = None if body == "none" else asyncio.create_task(estop(session))
        sizes = await asyncio.gather(*(one(session) for _ in range(count)))
        all_in = time.perf_counter() - t0
        estop_s = None if stop_task is None else await stop_task
    print(
        json.dumps({"estop_s": estop_s, "all_connected_s": all_in, "bytes": max(sizes, default=0)})
    )


async def ready_child(
    mode: str, where: str, viewers: int, *extra: str
) -> asyncio.subprocess.Process:
    """This script as a child in ``mode`` (its viewers), once it says it is ready."""
    child = await asyncio.create_subprocess_exec(
        sys.executable, __file__, mode, where, str(viewers), *extra,
        stdin=subprocess.PIPE, stdout=subprocess.PIPE,
    )  # fmt: skip
    assert child.stdout is not None
    assert (await child.stdout.readline()).strip() == b"ready"
    return child


async def burst(sim: SimProcess, base: str, viewers: int) -> dict[str, Any]:
    child = await ready_child("--burst-only", base, viewers)
    assert child.stdout is not None and child.stdin is not None
    await asyncio.sleep(0.3)
    before = len(sim.log_records())
    child.stdin.write(b"go\n")
    await child.stdin.drain()
    out = json.loads((await child.stdout.readline()).decode())
    await asyncio.sleep(0.3)
    child.stdin.close()
    await child.wait()
    rx = [float(r["t"]) for r in sim.log_records()[before:] if r.get("direction") == "request"]
    gaps = [b - a for a, b in itertools.pairwise(rx)]
    return {
        "viewers": viewers,
        "estop_ms": out["estop_s"] * 1e3,
        "all_connected_ms": out["all_connected_s"] * 1e3,
        "longest_silence_ms": max(gaps) * 1e3 if gaps else None,
        "snapshot_bytes": out["bytes"],
    }


async def window(bus: Bus, url: str, viewers: int, seconds: float) -> dict[str, Any]:
    child = await ready_child("--viewers-only", url, viewers)
    assert child.stdout is not None and child.stdin is not None
    await asyncio.sleep(0.5)  # settle
    n0, t0 = bus.stats.requests, time.monotonic()
    await asyncio.sleep(seconds)
    n1, t1 = bus.stats.requests, time.monotonic()
    child.stdin.close()
    out = (await child.communicate())[0].decode().splitlines()
    counts = json.loads(out[-1])
    return {
        "viewers": viewers,
        "frames_per_s": (n1 - n0) / (t1 - t0),
        "messages_min": min(counts),
        "messages_max": max(counts),
    }


async def measure(
    seconds: float, repeats: int, many: int, fill: float, log: Path
) -> dict[str, Any]:
    with SimProcess([f"la:{IDS[0]}-{IDS[-1]}"], baud=921600, log_file=log) as sim:
        bus = Bus(open_transport(sim.path, baudrate=921600), name="arm", families=[Family.LA])
        async with bus:
            dash = Dashboard([BusSetup(bus, list(IDS))], period=PERIOD_S, control=True)
            async with serve_page(make_app(dash, push_hz=10.0), "127.0.0.1", 0) as page:
                port = page.port
                await dash.start()
                started = time.monotonic()
                try:
                    rows = []
                    for _ in range(repeats):
                        for viewers in (1, many):
                            url = f"ws://127.0.0.1:{port}/ws"
                            rows.append(await window(bus, url, viewers, seconds))
                    await asyncio.sleep(max(0.0, fill - (time.monotonic() - started)))
                    bursts = [await burst(sim, f"127.0.0.1:{port}", many) for _ in range(repeats)]
                finally:
                    await dash.stop()
    one = [r["frames_per_s"] for r in rows if r["viewers"] == 1]
    lots = [r["frames_per_s"] for r in rows if r["viewers"] == many]
    mean1, mean_many = sum(one) / len(one), sum(lots) / len(lots)
    return {
        "actuators": len(IDS),
        "period_s": PERIOD_S,
        "expected_frames_per_s": len(IDS) / PERIOD_S,
        "seconds": seconds,
        "windows": rows,
        "frames_per_s_1_viewer": mean1,
        f"frames_per_s_{many}_viewers": mean_many,
        "difference_pct": 100 * (mean_many - mean1) / mean1,
        "fill_s": fill,
        "bursts": bursts,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--viewers", type=int, default=50)
    parser.add_argument(
        "--fill", type=float, default=30.0, help="seconds of samples before the bursts (30)"
    )
    parser.add_argument("--viewers-only", nargs=2, metavar=("URL", "N"), help=argparse.SUPPRESS)
    parser.add_argument("--burst-only", nargs="+", metavar="HOST N [BODY]", help=argparse.SUPPRESS)
    parser.add_argument("--app-only", nargs=2, metavar=("ENDPOINT", "APP"), help=argparse.SUPPRESS)
    parser.add_argument(
        "--served", action="store_true", help="the served mode (issue 39): see the docstring"
    )
    parser.add_argument(
        "--app",
        choices=bench_dashboard_served.APPS,
        default="stream",
        help="--served: the application, a 100 Hz follow stream (default) or a move every 10 ms",
    )
    parser.add_argument(
        "--realtime",
        action="store_true",
        help="--served: motorbus serve and dashboard with --realtime (SCHED_FIFO: root or "
        "CAP_SYS_NICE)",
    )
    args = parser.parse_args()
    if args.app_only:
        endpoint, app = args.app_only
        run = (
            bench_dashboard_served.app_stream
            if app == "stream"
            else bench_dashboard_served.app_only
        )
        asyncio.run(run(endpoint))
        return
    if args.served:
        bench_dashboard_served.main(args, __file__)
        return
    if args.viewers_only:
        asyncio.run(viewers_only(args.viewers_only[0], int(args.viewers_only[1])))
        return
    if args.burst_only:
        asyncio.run(burst_only(*args.burst_only[:1], int(args.burst_only[1]), *args.burst_only[2:]))
        return
    with tempfile.TemporaryDirectory() as tmp:
        report = asyncio.run(
            measure(args.seconds, args.repeats, args.viewers, args.fill, Path(tmp) / "sim.jsonl")
        )
    print(f"{'viewers':>8} {'frames/s':>9} {'msgs/viewer':>12}")
    for r in report["windows"]:
        msgs = f"{r['messages_min']}..{r['messages_max']}"
        print(f"{r['viewers']:>8} {r['frames_per_s']:>9.2f} {msgs:>12}")
    print(
        f"mean: 1 viewer {report['frames_per_s_1_viewer']:.2f} frames/s, {args.viewers} viewers "
        f"{report[f'frames_per_s_{args.viewers}_viewers']:.2f} frames/s "
        f"({report['difference_pct']:+.2f} %); polls ask {report['expected_frames_per_s']:.0f}"
    )
    print(f"\n{args.viewers} viewers connecting at once, after {args.fill:g} s of samples:")
    print(f"{'e-stop ms':>10} {'all in ms':>10} {'no frame ms':>12} {'snapshot kB':>12}")
    for b in report["bursts"]:
        print(
            f"{b['estop_ms']:>10.1f} {b['all_connected_ms']:>10.1f} "
            f"{b['longest_silence_ms']:>12.1f} {b['snapshot_bytes'] / 1e3:>12.1f}"
        )
    write_report(RESULTS, report)


if __name__ == "__main__":
    main()
