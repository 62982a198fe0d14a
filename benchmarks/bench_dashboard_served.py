"""The served mode of ``bench_dashboard.py`` (``--served``; its docstring says what is
measured).  Four processes besides this one: ``motorbus sim`` (the pty), ``motorbus
serve`` (owns the port), the application (``bench_dashboard.py --app-only``: a 100 Hz
follow stream to la:1 through the server, or with ``--app move`` a move of la:1 every
10 ms) and ``motorbus dashboard --connect``; the viewers and the e-stop come from a
fifth (``--burst-only``).  Windows without and with viewers alternate in the same run,
so both see the same machine load.

The stream's jitter is taken by two instruments that share nothing with the server's
clock: the kernel's (``perf``: the server's write(2) calls of a tick's 9 bytes, fitted
to a 10 ms grid per window, as ``bench_serve_stream.py`` does) and the simulator's (when
its reader cut each tick's frame, fitted the same way)."""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import aiohttp

from harness import write_report
from kernel_clock import KernelWriteTrace, grid_jitter
from motorbus.sim.process import SimProcess

RESULTS = Path(__file__).resolve().parent / "results" / "dashboard_served.json"
IDS = (1, 2, 3, 4, 5)
#: The dashboard's poll round, seconds (as the in-process burst of bench_dashboard.py).
POLL_S = 0.02
#: The application's command period: 100 moves a second.
APP_PERIOD_S = 0.01
#: A stream tick on the wire: one 0xF3 follow broadcast to one actuator (9 bytes).
TICK_BYTES = 9
#: The applications ``--app`` chooses from.
APPS = ("stream", "move")
#: The e-stop posted in every window: la:5, which the application does not drive.
ESTOP_BODY = {"bus": "arm", "id": 5}
#: When the e-stop is posted after the viewers start connecting, seconds.
ESTOP_AFTER_S = 0.01
READY_S = 60.0


async def app_only(endpoint: str) -> None:
    """Child process: move la:1 every 10 ms (absolute deadlines) through the server until
    stdin closes; then print every tick as ``[due, sent, done, ok]`` (monotonic s)."""
    import motorbus
    from motorbus.errors import MotorbusError
    from motorbus.protocol import la

    async with motorbus.connect(endpoint, name="app") as site:
        bus = site.bus()
        loop = asyncio.get_running_loop()
        stop = loop.run_in_executor(None, sys.stdin.read)
        ticks: list[tuple[float, float, float, bool]] = []
        print("ready", flush=True)
        due = time.monotonic()
        n = 0
        while not stop.done():
            due += APP_PERIOD_S
            delay = due - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            sent = time.monotonic()
            ok = True
            try:
                await bus.request(la.MoveTo(1, 500 + (n % 100) * 10))
            except MotorbusError:
                ok = False
            ticks.append((due, sent, time.monotonic(), ok))
            n += 1
    print(json.dumps(ticks), flush=True)


async def app_stream(endpoint: str) -> None:
    """Child process: a 100 Hz follow stream of la:1 through the server (a target per
    tick, published as it goes) until stdin closes; then print the stream's own stats."""
    import motorbus
    from motorbus import InspireLA, Streamer

    async with motorbus.connect(endpoint, name="app") as site:
        bus = site.bus()
        loop = asyncio.get_running_loop()
        stop = loop.run_in_executor(None, sys.stdin.read)

        def target(t: float, statuses: object) -> int | None:
            return None if stop.done() else 500 + (round(t / APP_PERIOD_S) % 100) * 10

        stream = Streamer(bus).follow(
            InspireLA(bus, 1), target, period=APP_PERIOD_S, safe_action="pause"
        )
        print("ready", flush=True)
        await stream.wait()
        stats = dict(stream.stats.as_dict())
    print(json.dumps({"stats": stats}, default=str), flush=True)


def tick_jitter(times: list[float], t0: float, t1: float) -> dict[str, Any]:
    """The grid jitter (us) of the tick times inside [t0, t1]."""
    fit = grid_jitter([t for t in times if t0 <= t <= t1], APP_PERIOD_S)
    ok = fit.ticks > 2 and fit.p99_us == fit.p99_us
    return {
        "ticks": fit.ticks,
        "p50_us": fit.p50_us if ok else None,
        "p99_us": fit.p99_us if ok else None,
        "max_us": fit.max_us if ok else None,
        "missed": fit.missed,
    }


def is_tick(record: dict[str, Any]) -> bool:
    """Is this simulator log record a stream tick (a 0xF3 follow broadcast)?"""
    head = str(record.get("hex", "")).split()
    return len(head) > 4 and head[4].upper() == "F3"


def tick_starts(trace: KernelWriteTrace) -> list[float]:
    """When the server's write(2) of each stream tick began (kernel clock, seconds)."""
    fds = [c.fd for c in trace.calls if c.count == TICK_BYTES and c.fd > 2]
    return trace.starts(max(set(fds), key=fds.count), [TICK_BYTES]) if fds else []


def kernel_figures(
    trace: KernelWriteTrace | None, starts: list[float], t0: float, t1: float
) -> dict[str, Any]:
    """The stream's tick jitter inside [t0, t1] on the kernel's clock (``starts``: the
    trace's ``tick_starts``)."""
    out: dict[str, Any] = {}
    if trace is not None and trace.measured:
        kernel = tick_jitter(starts, t0, t1)
        out["kernel_tick_p50_us"], out["kernel_tick_p99_us"] = kernel["p50_us"], kernel["p99_us"]
        out["kernel_tick_max_us"], out["kernel_ticks"] = kernel["max_us"], kernel["ticks"]
        out["kernel_missed"] = kernel["missed"]
    else:
        out["kernel_tick_p99_us"] = None
        out["kernel_why"] = "perf not run" if trace is None else trace.why
    return out


def pooled_kernel_figures(
    trace: KernelWriteTrace | None, starts: list[float], windows: list[dict[str, Any]], many: int
) -> dict[str, Any]:
    """The ticks of every window of a kind fitted together (one stream, one grid): a
    p99 over 2,000-3,000 ticks, where a window's own is its second or third worst."""
    if trace is None or not trace.measured:
        return {}
    out: dict[str, Any] = {}
    for viewers in (0, many):
        spans = [(w["t0"], w["t1"]) for w in windows if w["viewers"] == viewers]
        fit = grid_jitter([t for t in starts if any(a <= t <= b for a, b in spans)], APP_PERIOD_S)
        out[f"{viewers}_viewers"] = {
            "ticks": fit.ticks, "p50_us": fit.p50_us, "p99_us": fit.p99_us, "max_us": fit.max_us
        }  # fmt: skip
    a, b = out["0_viewers"]["p99_us"], out[f"{many}_viewers"]["p99_us"]
    out["p99_ratio"] = b / a if a else None
    return out


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def start(args: list[str], ready: str) -> tuple[asyncio.subprocess.Process, str]:
    """A child process and the first stdout line that starts with ``ready``."""
    proc = await asyncio.create_subprocess_exec(
        *args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, limit=1 << 24
    )
    assert proc.stdout is not None
    async with asyncio.timeout(READY_S):
        while True:
            line = (await proc.stdout.readline()).decode()
            if not line:
                raise RuntimeError(f"{args[:5]} ended before saying {ready!r}")
            if line.startswith(ready):
                return proc, line.strip()


async def end(proc: asyncio.subprocess.Process) -> None:
    if proc.returncode is None:
        proc.terminate()
    try:
        await asyncio.wait_for(proc.wait(), 15)
    except TimeoutError:
        proc.kill()
        await proc.wait()


def p99(values: list[float]) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(0.99 * (len(ordered) - 1)))]


def app_figures(ticks: list[list[Any]], t0: float, t1: float) -> dict[str, Any]:
    """The application's moves completed inside [t0, t1]: interval jitter, round trip."""
    done = [t for t in ticks if t0 <= t[2] <= t1]
    jitter = [abs((b[2] - a[2]) - APP_PERIOD_S) * 1e3 for a, b in itertools.pairwise(done)]
    rtt = [(t[2] - t[1]) * 1e3 for t in done]
    late = [max(0.0, t[1] - t[0]) * 1e3 for t in done]
    return {
        "moves": len(done),
        "failed": sum(1 for t in done if not t[3]),
        "jitter_p99_ms": p99(jitter) if jitter else None,
        "jitter_max_ms": max(jitter) if jitter else None,
        "move_rtt_p50_ms": statistics.median(rtt) if rtt else None,
        "move_rtt_p99_ms": p99(rtt) if rtt else None,
        "send_late_p99_ms": p99(late) if late else None,
    }


async def capture(sim: SimProcess, out: Path) -> asyncio.subprocess.Process:
    """``motorbus capture`` on the simulator's tap (a listen-only copy of the traffic),
    once it says it is listening."""
    assert sim.tap is not None
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "motorbus", "capture", "--port", str(sim.tap),
        "--baud", "921600", "--family", "la", "--out", str(out),
        stdin=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    assert proc.stderr is not None
    async with asyncio.timeout(READY_S):
        while b"listening" not in (line := await proc.stderr.readline()):
            if not line:
                raise RuntimeError("motorbus capture ended before it was listening")
    return proc


async def window(
    script: str, sim: SimProcess, base: str, viewers: int, seconds: float, folder: Path
) -> dict[str, Any]:
    """One window: ``viewers`` connect at once (0: none), from a process of their own;
    the e-stop is posted from this one (otherwise idle) among them, on a connection of
    its own (a kept-alive one showed 20-30 ms stalls of its own on loopback, with or
    without viewers)."""
    child, _ = await start(
        [sys.executable, script, "--burst-only", base, str(viewers), "none"], "ready"
    )
    assert child.stdout is not None and child.stdin is not None
    cap = await capture(sim, folder / f"capture-{time.monotonic_ns()}.jsonl") if viewers else None
    await asyncio.sleep(0.3)
    before = len(sim.log_records())
    t0 = time.monotonic()
    child.stdin.write(b"go\n")
    await child.stdin.drain()
    await asyncio.sleep(ESTOP_AFTER_S)
    async with aiohttp.ClientSession() as http:
        posted = time.perf_counter()
        async with http.post(f"http://{base}/api/estop", json=ESTOP_BODY) as r:
            assert r.status == 200, await r.text()
        estop_s = time.perf_counter() - posted
    out = json.loads((await child.stdout.readline()).decode())
    await asyncio.sleep(max(0.0, seconds - (time.monotonic() - t0)))
    t1 = time.monotonic()
    captured = 0
    if cap is not None:
        cap.send_signal(signal.SIGINT)
        await cap.wait()
        captured = sum(1 for path in folder.glob("capture-*.jsonl") for _ in path.open()) - 1
        for path in folder.glob("capture-*.jsonl"):
            path.unlink()
    records = sim.log_records()[before:]
    child.stdin.close()
    await child.wait()
    requests = [r for r in records if r.get("direction") == "request"]
    rx = [float(r["t"]) for r in requests]
    gaps = [b - a for a, b in itertools.pairwise(rx)]
    # The stream's ticks as the simulator cut them (its own clock): 0xF3 broadcasts.
    sim = tick_jitter([t for t, r in zip(rx, requests, strict=True) if is_tick(r)], -1e9, 1e9)
    return {
        "viewers": viewers,
        "t0": t0,
        "t1": t1,
        "estop_ms": estop_s * 1e3,
        "all_connected_ms": out["all_connected_s"] * 1e3,
        "longest_silence_ms": max(gaps) * 1e3 if gaps else None,
        "snapshot_bytes": out["bytes"],
        "capture_lines": captured,
        "sim_tick_p99_us": sim["p99_us"],
        "sim_ticks": sim["ticks"],
    }


async def measure(
    script: str,
    seconds: float,
    repeats: int,
    many: int,
    fill: float,
    log: Path,
    app: str,
    realtime: bool = False,
) -> dict[str, Any]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    tap = log.parent / "tap"
    trace: KernelWriteTrace | None = None
    with SimProcess([f"la:{IDS[0]}-{IDS[-1]}"], baud=921600, log_file=log, tap=tap) as sim:
        server, _ = await start(
            [
                sys.executable, "-m", "motorbus", "serve", "--port", sim.path,
                "--baud", "921600", "--name", "arm", "--listen", endpoint,
                "--host-margin-ms", "50", "--stop-leased-only",
                *(["--realtime"] if realtime else []),
            ],
            "serving",
        )  # fmt: skip
        procs = [server]
        try:
            app_proc, _ = await start(
                [sys.executable, script, "--app-only", endpoint, app], "ready"
            )
            procs.append(app_proc)
            dash, url = await start(
                [
                    sys.executable, "-m", "motorbus", "dashboard", "--connect", endpoint,
                    "--ids", f"{IDS[0]}-{IDS[-1]}", "--control", "--listen", "127.0.0.1:0",
                    "--interval", str(POLL_S), *(["--realtime"] if realtime else []),
                ],
                "http://",
            )  # fmt: skip
            procs.append(dash)
            base = url.removeprefix("http://").rstrip("/")
            await asyncio.sleep(fill)
            windows = []
            if app == "stream":
                # The server's writes, on the kernel's clock, for every window.
                trace = KernelWriteTrace(pid=server.pid)
                trace.start()
            try:
                for _ in range(repeats):
                    for viewers in (0, many):
                        windows.append(
                            await window(script, sim, base, viewers, seconds, log.parent)
                        )
            finally:
                if trace is not None:
                    trace.stop()
            assert app_proc.stdin is not None and app_proc.stdout is not None
            app_proc.stdin.close()
            told = json.loads((await asyncio.wait_for(app_proc.stdout.readline(), 30)).decode())
        finally:
            for proc in reversed(procs):
                await end(proc)
    starts = tick_starts(trace) if trace is not None and trace.measured else []
    if app == "stream":
        for w in windows:
            w.update(kernel_figures(trace, starts, w["t0"], w["t1"]))
    else:
        for w in windows:
            w.update(app_figures(told, w["t0"], w["t1"]))
    report = summary(windows, many, seconds, fill, app)
    report["server_realtime"] = realtime
    if app == "stream":
        report["stream_stats"] = told["stats"]
        report["kernel_tick_pooled"] = pooled_kernel_figures(trace, starts, windows, many)
    return report


def _median(windows: list[dict[str, Any]], key: str) -> float | None:
    values = [w[key] for w in windows if w[key] is not None]
    return statistics.median(values) if values else None


#: The figures compared with and without viewers, by application.
COMPARED = {
    "stream": ("estop_ms", "longest_silence_ms", "kernel_tick_p99_us", "sim_tick_p99_us"),
    "move": ("estop_ms", "longest_silence_ms", "jitter_p99_ms", "move_rtt_p99_ms"),
}


def summary(
    windows: list[dict[str, Any]], many: int, seconds: float, fill: float, app: str
) -> dict[str, Any]:
    quiet = [w for w in windows if w["viewers"] == 0]
    burst = [w for w in windows if w["viewers"] == many]
    ratios = {}
    for key in COMPARED[app]:
        a, b = _median(quiet, key), _median(burst, key)
        ratios[key] = None if not a or b is None else b / a
    return {
        "actuators": len(IDS),
        "poll_s": POLL_S,
        "app": app,
        "app_period_s": APP_PERIOD_S,
        "viewers": many,
        "window_s": seconds,
        "fill_s": fill,
        "windows": windows,
        "median_without_viewers": {k: _median(quiet, k) for k in ratios},
        f"median_with_{many}_viewers": {k: _median(burst, k) for k in ratios},
        "ratio_with_over_without": ratios,
        "capture": "motorbus capture on the simulator's tap during each window with viewers",
    }


def main(args: argparse.Namespace, script: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        report = asyncio.run(
            measure(script, args.seconds, args.repeats, args.viewers, args.fill,
                    Path(tmp) / "sim.jsonl", args.app, args.realtime)
        )  # fmt: skip
    doing = "streaming to la:1 at 100 Hz" if args.app == "stream" else "moving la:1 every 10 ms"
    if args.realtime:
        doing += " (the server and the dashboard's controls in real-time mode)"
    print(
        f"served: an application {doing}, dashboard --connect polling "
        f"{len(IDS)} actuators every {POLL_S * 1e3:g} ms, {args.fill:g} s of samples first"
    )
    if args.app == "stream":
        head = ("viewers", "e-stop ms", "no frame ms", "kernel p99", "sim p99", "ticks", "snap kB")
        keys = ("kernel_tick_p99_us", "sim_tick_p99_us", "sim_ticks")
    else:
        head = ("viewers", "e-stop ms", "no frame ms", "jitter p99", "move p99", "moves", "snap kB")
        keys = ("jitter_p99_ms", "move_rtt_p99_ms", "moves")
    print("".join(f"{h:>12}" for h in head))
    for w in report["windows"]:
        cells = (
            w["viewers"], w["estop_ms"], w["longest_silence_ms"], *(w.get(k) for k in keys),
            w["snapshot_bytes"] / 1e3,
        )  # fmt: skip
        print("".join(f"{c:>12.1f}" if isinstance(c, float) else f"{c!s:>12}" for c in cells))
    if args.app == "stream" and report["windows"][0].get("kernel_why"):
        print(f"kernel clock not measured: {report['windows'][0]['kernel_why']}")
    print("median ratio, with viewers / without (same run):")
    for key, ratio in report["ratio_with_over_without"].items():
        print(f"  {key:<20} {'-' if ratio is None else f'{ratio:.2f}x'}")
    pooled = report.get("kernel_tick_pooled")
    if pooled:
        quiet, busy = pooled["0_viewers"], pooled[f"{args.viewers}_viewers"]
        print(
            f"kernel tick p99, every window's ticks together: {quiet['p99_us']:.0f} us "
            f"({quiet['ticks']} ticks) without viewers, {busy['p99_us']:.0f} us "
            f"({busy['ticks']}) with: {pooled['p99_ratio']:.2f}x"
        )
    write_report(RESULTS, report)
