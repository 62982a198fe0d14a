"""One ``motorbus serve`` with many buses and clients against embedded, in one run.

    python benchmarks/bench_serve_scale.py [--buses 8,16,32] [--per-client 8]
                                           [--seconds 8] [--kills 3] [--out FILE] [--quick]

For each bus count N of ``--buses`` (default 8, 16 and 32): N simulated LA buses (one
``la:1`` each, 921600 baud, full simulator with wire-time pacing), one pty each, all
served by one process (``benchmarks/sim_many.py``, a simulator thread per pty).  One
bus file lists them all (a ``[[bus]]`` table per bus, ``host_margin_ms = 20``).  The
load: every bus asks its actuator's status on a 100 Hz grid (a request is sent at
each 10 ms tick; a tick missed because the previous reply came late is skipped and
counted).

* embedded: one process opens the bus file (``BusManager``) and runs the load on
  every bus itself;
* served: ``motorbus serve BUS_FILE`` in its own process, and N / ``--per-client``
  client processes (``motorbus.connect``), each running the load on its
  ``--per-client`` buses (32 buses: four clients of 8).

A **bus-tick** is one 10 ms period of one bus whose status request got its reply; the
CPU per bus-tick of a process is its CPU time (user + system, from
``/proc/PID/stat``, every thread) over the measuring window divided by the bus-ticks
done in that window on every bus.  The round trip is that of each status request in
the window (``InspireLA.status``, from the call to the decoded reply), p50/p99.

The deadman: each client moved its buses' actuator first (so it holds a lease on
each); after the window, with the other clients still running their load, client 1
(later kills: a fresh client on the same buses) is killed with SIGKILL; the time from
the signal to the last of its buses' pause frames arriving at the simulators (their
own arrival timestamps, on the machine's monotonic clock).

Everything runs on this machine (its cores are shared by the server, the clients and
the simulators; the table shows each one's CPU).  Prints a table and writes
``benchmarks/results/serve_scale.json``.  ``--quick``: 4 buses, 2 clients, 1 s, one
kill (a smoke test of the script, no figures).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import os
import platform
import queue
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from harness import write_report

HERE = Path(__file__).resolve().parent
DEFAULT_OUT = HERE / "results" / "serve_scale.json"
BAUD = 921600
PERIOD_S = 0.01  # 100 Hz per bus
WARMUP_S = 1.5
READY_TIMEOUT_S = 60.0


# -- the load (a child process: embedded, or one client) -----------------------------------


class Record:
    def __init__(self) -> None:
        self.ticks = 0
        self.skipped = 0
        self.errors = 0
        self.first_error = ""
        self.rtts: list[float] = []


async def drive(bus: Any, phase: float, window: tuple[float, float], stop: asyncio.Event,
                rec: Record) -> None:  # fmt: skip
    from motorbus import InspireLA

    actuator = InspireLA(bus, 1)
    start = time.monotonic() + phase
    # The window's ticks by their index on the grid: exactly window / period of them.
    first = math.ceil((window[0] - start) / PERIOD_S)
    end = first + round((window[1] - window[0]) / PERIOD_S)
    k = 0
    while not stop.is_set():
        due = start + k * PERIOD_S
        now = time.monotonic()
        if due > now:
            await asyncio.sleep(due - now)
        sent = time.monotonic()
        try:
            await actuator.status()
        except Exception as err:  # counted and shown; the load goes on
            rec.errors += 1
            rec.first_error = rec.first_error or f"{type(err).__name__}: {err}"
        else:
            done = time.monotonic()
            if first <= k < end:
                rec.ticks += 1
                rec.rtts.append(done - sent)
        k += 1
        now = time.monotonic()
        next_k = int((now - start) / PERIOD_S) + 1
        if next_k > k:
            rec.skipped += max(0, min(next_k, end) - max(k, first))
            k = next_k


async def first_move(bus: Any, target: int) -> None:
    """Move the bus's actuator (the client then holds its lease); a reply lost on a
    swamped machine is asked again, a few times."""
    from motorbus import InspireLA, ReplyTimeoutError

    for attempt in range(5):
        try:
            await InspireLA(bus, 1).move_to(target)
            return
        except ReplyTimeoutError:
            if attempt == 4:
                raise


async def load(args: argparse.Namespace) -> None:
    import motorbus

    names = args.names.split(",")
    async with contextlib.AsyncExitStack() as stack:
        if args.endpoint:
            site = await stack.enter_async_context(
                motorbus.connect(args.endpoint, name=f"load{args.index}")
            )
            buses = [site.bus(n) for n in names]
        else:
            manager = await stack.enter_async_context(motorbus.BusManager.from_toml(args.bus_file))
            buses = [manager.bus(n) for n in names]
        if args.move:
            await asyncio.gather(*(first_move(b, 1000 + 37 * i) for i, b in enumerate(buses)))
        print("ready", flush=True)
        line = (await asyncio.to_thread(sys.stdin.readline)).split()
        t0, seconds = float(line[1]), float(line[2])
        stop = asyncio.Event()
        rec = Record()
        window = (t0, t0 + seconds)
        # Spread over the period, as BusManager's streamers phase their ticks.
        offset = args.index * len(names)
        tasks = [
            asyncio.ensure_future(
                drive(b, ((offset + i) % args.total) * PERIOD_S / args.total, window, stop, rec)
            )
            for i, b in enumerate(buses)
        ]
        if seconds > 0:
            await asyncio.sleep(max(0.0, window[1] - time.monotonic()) + 0.2)
            result = {k: v for k, v in vars(rec).items()}
            print("result " + json.dumps(result), flush=True)
        await asyncio.to_thread(sys.stdin.readline)  # "stop" (or EOF)
        stop.set()
        await asyncio.gather(*tasks, return_exceptions=True)


# -- the parent -------------------------------------------------------------------------------


class Child:
    """A child process; its stdout lines go to a queue (every wait bounded)."""

    def __init__(self, args: list[str], *, stdin: bool = True) -> None:
        self.stderr = tempfile.TemporaryFile("w+", encoding="utf-8")  # noqa: SIM115  (the child's life)
        self.proc = subprocess.Popen(
            args,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=self.stderr,
            text=True,
            start_new_session=True,
        )
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))
        self.lines.put("")  # EOF

    def expect(self, prefix: str, timeout: float = READY_TIMEOUT_S) -> str:
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = self.lines.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                raise RuntimeError(
                    f"{self.proc.args[1:4]!r} printed no {prefix!r}: {self.error_tail()}"
                ) from None
            if line.startswith(prefix):
                return line
            if line == "":
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self.proc.wait(5)
                raise RuntimeError(
                    f"{self.proc.args[1:4]!r} ended before {prefix!r}: {self.error_tail()}"
                )

    def error_tail(self) -> str:
        self.stderr.seek(0)
        return self.stderr.read()[-2000:]

    def tell(self, line: str) -> None:
        assert self.proc.stdin is not None
        with contextlib.suppress(BrokenPipeError):
            self.proc.stdin.write(line + "\n")
            self.proc.stdin.flush()

    def end(self, sig: int = signal.SIGTERM) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.proc.pid, sig)
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def cpu_seconds(pid: int) -> float:
    """User + system CPU of a process (every thread), from /proc."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def pct(values: list[float], p: float) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(p / 100 * (len(ordered) - 1)))]


def bus_file(path: Path, ports: list[str]) -> list[str]:
    names = [f"b{i:02d}" for i in range(len(ports))]
    text = "".join(
        f'[[bus]]\nname = "{n}"\nurl = "{p}"\nbaud = {BAUD}\ndevices = ["la:1"]\n'
        "host_margin_ms = 20\n\n"
        for n, p in zip(names, ports, strict=True)
    )
    path.write_text(text, encoding="utf-8")
    return names


class Sims:
    """``sim_many.py``: the simulators, and the safe frames they received."""

    def __init__(self, count: int) -> None:
        self.child = Child([sys.executable, str(HERE / "sim_many.py"), str(count)], stdin=False)
        self.paths = self.child.expect("/dev/").split()
        self.safe: list[tuple[int, float]] = []
        self._lock = threading.Lock()
        threading.Thread(target=self._collect, daemon=True).start()

    def _collect(self) -> None:
        while True:
            line = self.child.lines.get()
            if not line:
                if self.child.proc.poll() is not None:
                    return
                continue
            parts = line.split()
            if parts[0] == "safe":
                with self._lock:
                    self.safe.append((int(parts[1]), float(parts[2])))

    def safe_after(self, t: float) -> list[tuple[int, float]]:
        with self._lock:
            return [s for s in self.safe if s[1] > t]


def measure(children: list[Child], owner: Child, sims: Sims, seconds: float) -> dict[str, Any]:
    """Start every load child's window; CPU of each process over it; their results."""
    t0 = time.monotonic() + WARMUP_S
    for c in children:
        c.tell(f"go {t0:.6f} {seconds}")
    time.sleep(max(0.0, t0 - time.monotonic()))
    pids = {"owner": owner.proc.pid, "sim": sims.child.proc.pid}
    pids |= {f"client{i}": c.proc.pid for i, c in enumerate(children) if c is not owner}
    before = {k: cpu_seconds(p) for k, p in pids.items()}
    start = time.monotonic()
    time.sleep(max(0.0, t0 + seconds - time.monotonic()))
    after = {k: cpu_seconds(p) for k, p in pids.items()}
    wall = time.monotonic() - start
    results = [json.loads(c.expect("result ")[7:]) for c in children]
    ticks = sum(r["ticks"] for r in results)
    rtts = [x for r in results for x in r["rtts"]]
    cpu = {k: after[k] - before[k] for k in pids}
    clients_cpu = sum(v for k, v in cpu.items() if k.startswith("client"))
    us = 1e6
    return {
        "wall_s": wall,
        "bus_ticks": ticks,
        "bus_ticks_due": None,  # filled by the caller (buses x seconds x 100)
        "skipped_ticks": sum(r["skipped"] for r in results),
        "errors": sum(r["errors"] for r in results),
        "first_error": next((r["first_error"] for r in results if r["first_error"]), ""),
        "rtt_ms": {
            "p50": (pct(rtts, 50) or 0) * 1e3,
            "p99": (pct(rtts, 99) or 0) * 1e3,
            "n": len(rtts),
        },
        "cpu_s": cpu,
        "owner_cpu_percent": 100 * cpu["owner"] / wall,
        "owner_cpu_us_per_bus_tick": us * cpu["owner"] / ticks if ticks else None,
        "clients_cpu_us_per_bus_tick": us * clients_cpu / ticks if ticks else None,
        "sim_cpu_percent": 100 * cpu["sim"] / wall,
    }


def load_child(index: int, total: int, names: list[str], *extra: str) -> Child:
    return Child(
        [sys.executable, str(Path(__file__).resolve()), "--role", "load", "--index", str(index),
         "--total", str(total), "--names", ",".join(names), *extra]
    )  # fmt: skip


def deadman(sims: Sims, victim: Child, buses: list[int]) -> dict[str, Any]:
    """SIGKILL ``victim`` (it holds a lease on each of ``buses``); to its last pause."""
    time.sleep(0.3)
    killed = time.monotonic()
    os.kill(victim.proc.pid, signal.SIGKILL)
    deadline = killed + 10
    while time.monotonic() < deadline:
        seen = {i: t for i, t in sims.safe_after(killed) if i in buses}
        if len(seen) == len(buses):
            break
        time.sleep(0.002)
    else:
        raise RuntimeError(f"not every bus of {buses} got a safe frame within 10 s")
    time.sleep(0.2)
    others = [i for i, _ in sims.safe_after(killed) if i not in buses]
    victim.end(signal.SIGKILL)
    first = {i: t for i, t in reversed(sims.safe_after(killed)) if i in buses}
    return {
        "last_ms": (max(first.values()) - killed) * 1e3,
        "first_ms": (min(first.values()) - killed) * 1e3,
        "other_buses_stopped": len(others),
    }


def run_size(buses: int, clients: int, args: argparse.Namespace) -> dict[str, Any]:
    """Embedded, then served, then the deadman: one bus count."""
    per = buses // clients
    report: dict[str, Any] = {"buses": buses, "clients": clients}
    with tempfile.TemporaryDirectory() as tmp:
        sims = Sims(buses)
        try:
            names = bus_file(Path(tmp) / "buses.toml", sims.paths)
            busfile = str(Path(tmp) / "buses.toml")
            # Embedded: one process, every bus.
            emb = load_child(0, buses, names, "--bus-file", busfile)
            try:
                emb.expect("ready")
                report["embedded"] = measure([emb], emb, sims, args.seconds)
                emb.tell("stop")
            finally:
                emb.end()
            # Served: one server, the clients.
            endpoint = free_endpoint()
            server = Child(
                [sys.executable, "-m", "motorbus", "serve", busfile, "--listen", endpoint],
                stdin=False,
            )
            children: list[Child] = []
            try:
                server.expect("serving")
                shares = [names[i * per : (i + 1) * per] for i in range(clients)]
                children = [
                    load_child(i, buses, share, "--endpoint", endpoint, "--move")
                    for i, share in enumerate(shares)
                ]
                for c in children:
                    c.expect("ready")
                report["served"] = measure(children, server, sims, args.seconds)
                kills = []
                victim = children[0]
                for n in range(args.kills):
                    if n:
                        victim = load_child(0, buses, shares[0], "--endpoint", endpoint, "--move")
                        victim.expect("ready")
                        victim.tell(f"go {time.monotonic():.6f} 0")
                    kills.append(deadman(sims, victim, list(range(per))))
                report["deadman"] = {
                    "buses_of_the_victim": per,
                    "kills": kills,
                    "last_ms_median": statistics.median(k["last_ms"] for k in kills),
                    "last_ms_max": max(k["last_ms"] for k in kills),
                    "other_buses_stopped": sum(k["other_buses_stopped"] for k in kills),
                }
                for c in children[1:]:
                    c.tell("stop")
            finally:
                for c in children:
                    c.end()
                server.end()
        finally:
            sims.child.end(signal.SIGINT)
    for side in ("embedded", "served"):
        report[side]["bus_ticks_due"] = round(buses * args.seconds / PERIOD_S)
    return report


def table(sizes: list[dict[str, Any]], seconds: float) -> str:
    def pair(row: dict[str, Any], key: str, fmt: str) -> str:
        a, b = row["embedded"].get(key), row["served"].get(key)
        return "/".join("-" if v is None else format(v, fmt) for v in (a, b))

    lines = [
        f"every bus at 100 Hz (a status request per 10 ms tick), {seconds:g} s window; "
        "embedded/served; owner = the embedded process / the server",
        f"{'buses':>5} {'clients':>7} {'ticks done %':>13} {'rtt p50 ms':>11} {'rtt p99 ms':>11}"
        f" {'owner us/tick':>13} {'owner %core':>11} {'clients us/tick':>15} {'deadman ms':>11}",
    ]
    for row in sizes:
        done = "/".join(
            f"{100 * row[s]['bus_ticks'] / row[s]['bus_ticks_due']:.0f}"
            for s in ("embedded", "served")
        )
        rtt50 = "/".join(f"{row[s]['rtt_ms']['p50']:.1f}" for s in ("embedded", "served"))
        rtt99 = "/".join(f"{row[s]['rtt_ms']['p99']:.1f}" for s in ("embedded", "served"))
        dm = row["deadman"]
        lines.append(
            f"{row['buses']:>5} {row['clients']:>7} {done:>13} {rtt50:>11} {rtt99:>11}"
            f" {pair(row, 'owner_cpu_us_per_bus_tick', '.0f'):>13}"
            f" {pair(row, 'owner_cpu_percent', '.0f'):>11}"
            f" {row['served']['clients_cpu_us_per_bus_tick'] or 0:>15.0f}"
            f" {dm['last_ms_median']:>5.1f}/{dm['last_ms_max']:<5.1f}"
        )
    lines.append(
        "deadman ms: SIGKILL of the client of the first buses -> the last pause at its "
        "simulators, median/max; ticks done %: bus-ticks done of those due"
    )
    stopped = sum(row["deadman"]["other_buses_stopped"] for row in sizes)
    errors = sum(row[s]["errors"] for row in sizes for s in ("embedded", "served"))
    lines.append(f"buses of other clients stopped by a kill: {stopped}; request errors: {errors}")
    return "\n".join(lines)


def parse_counts(parser: argparse.ArgumentParser, text: str, per_client: int) -> list[int]:
    """``--buses 8,16,32``: each a multiple of ``--per-client``, 1..128."""
    if not 1 <= per_client <= 64:
        parser.error(f"--per-client={per_client}: allowed 1..64")
    try:
        counts = [int(part) for part in text.split(",")]
    except ValueError:
        parser.error(f"--buses={text!r}: bus counts separated by commas, e.g. 8,16,32")
    for n in counts:
        if not 1 <= n <= 128 or n % per_client:
            parser.error(
                f"--buses={text!r}: each count 1..128 and a multiple of --per-client={per_client}"
            )
    return counts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument(
        "--buses", default="8,16,32", help="bus counts, comma-separated (default 8,16,32)"
    )
    parser.add_argument("--per-client", type=int, default=8, help="buses per client (8)")
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--kills", type=int, default=3)
    parser.add_argument(
        "--quick", action="store_true", help="4 buses, 2 per client, 1 s, 1 kill (a smoke test)"
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    # The load children's own arguments.
    parser.add_argument(
        "--role", choices=["bench", "load"], default="bench", help=argparse.SUPPRESS
    )
    parser.add_argument("--index", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--total", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--names", default="", help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", default="", help=argparse.SUPPRESS)
    parser.add_argument("--bus-file", default="", help=argparse.SUPPRESS)
    parser.add_argument("--move", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.role == "load":
        asyncio.run(load(args))
        return 0
    if args.quick:
        args.buses, args.per_client, args.seconds, args.kills = "4", 2, 1.0, 1
    counts = parse_counts(parser, args.buses, args.per_client)
    if not 1 <= args.kills <= 20:
        parser.error(f"--kills={args.kills}: allowed 1..20")
    if not 0.5 <= args.seconds <= 600:
        parser.error(f"--seconds={args.seconds}: allowed 0.5..600")
    report = {
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "load_avg_before": list(os.getloadavg()),
        "command": "python benchmarks/bench_serve_scale.py " + " ".join(argv or sys.argv[1:]),
        "seconds": args.seconds,
        "rate_hz": 1 / PERIOD_S,
        "bus_tick": "one 10 ms period of one bus whose status request got its reply",
        "sizes": [run_size(n, n // args.per_client, args) for n in counts],
    }
    report["load_avg_after"] = list(os.getloadavg())
    print(table(report["sizes"], args.seconds))
    write_report(args.out, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
