"""Bus round trip, sustained command rate and deadline precision over a real pty.

Every phase talks to ``PtySim`` serving Inspire LA models at an emulated 921600 bit/s
(the simulator delivers each reply when its last byte would have arrived on a UART).

(a) Round trip of an LA status query (8-byte request, 22-byte reply), three ways, on the
    same pty: ours (``Bus`` + ``InspireLA.status``); a minimal hand-written asyncio client
    on the same serial backend (a Protocol that writes the query and resolves a future
    once 22 bytes arrived); a blocking pyserial client (``write`` + ``read(22)``).  Every
    client is paced at one call per ``PACE_S`` (start to start), so the bus's 1 ms
    spacing rule never delays a measured call: the figures are pure round trips.
(b) Sustained rate: status queries back to back on one bus with the default 1 ms
    spacing for ``--seconds``; commands/s, and the smallest start-to-start gap between
    two requests as the SIMULATOR saw them (its log: end of the request on the emulated
    wire minus the request's wire time).  The smallest gap as the bus's own clock saw it
    is reported beside it: the simulator's figure also contains the pty hop and the
    simulator thread's wake-up, which the bus does not control.
(c) Deadline precision: status queries to an ID nobody answers, ``host_margin=0``,
    ``timeout=BUDGET_S`` (800 us), no retries, no late guard.  Lateness =
    (time.monotonic() when ``ReplyTimeoutError`` reaches the caller) - (the bus's clock
    reading at transmission, captured by wrapping its timer and transport) - budget.
    Negative lateness would be a deadline that fired early.

Prints a table with the goals and writes ``benchmarks/results/bus.json``.

The simulator runs in a child process by default (``--sim thread`` runs it in this
process, where it competes with the bus for the GIL).  ``--profile`` prints a cProfile of
the rate run.

Usage: ``python benchmarks/bench_bus.py [--quick] [--n 2000] [--backend fast]
[--loop asyncio|uvloop] [--seconds 3] [--sim process|thread] [--profile] [--out PATH]
[--samples PATH]``
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import cProfile
import datetime
import importlib
import io
import itertools
import json
import multiprocessing
import os
import platform
import pstats
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import serial

from motorbus.bus.bus import Bus
from motorbus.bus.timer import Timer, TimerHandle, default_timer
from motorbus.devices.la import InspireLA
from motorbus.errors import ReplyTimeoutError
from motorbus.protocol import la
from motorbus.protocol.base import Family, wire_time
from motorbus.sim.la import LAModel
from motorbus.sim.pty import PtySim
from motorbus.transport.serial import BACKENDS, DEFAULT_BACKEND, SerialTransport

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "bus.json"
#: LA "D" interface rate (docs/protocols.md C.1).
BAUD = 921600
#: IDs the simulator serves, and one it does not (for the deadline phase).
LA_IDS = (1, 2, 3)
SILENT_ID = 9
#: Start-to-start pacing of measured round trips: above the bus's 1 ms spacing.
PACE_S = 1.5e-3
#: Reply budget of the deadline phase (the LA worst-case turnaround, manual 3.4.2).
BUDGET_S = 800e-6
#: Pacing of the deadline phase: budget + lateness + spacing fit well inside.
DEADLINE_PACE_S = 2.5e-3
QUERY = la.Control(1, la.ControlAction.QUERY_STATUS)
QUERY_BYTES = QUERY.encode()
REPLY_SIZE = la.STATUS_FRAME_SIZE
#: Blocking client read timeout: far above any round trip, only to avoid a hang.
BLOCKING_TIMEOUT_S = 0.5
#: How long to wait for the simulator process to start or stop.
SIM_START_TIMEOUT_S = 10.0
#: Goals of the issue.
GOAL_RATIO = 1.3
GOAL_RATE = 970.0
GOAL_MIN_GAP_US = 1000.0
GOAL_EARLY = 0
GOAL_LATE_P99_US = 150.0
#: Importable module of each backend (same mapping as motorbus.transport.serial).
BACKEND_MODULES = {
    "fast": "serial_asyncio_fast",
    "serialx": "serialx",
    "pyserial-asyncio": "serial_asyncio",
}


def percentile(values: list[float], q: float) -> float:
    """Nearest-rank ``q`` quantile (0..1) of ``values``; NaN if empty."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q * (len(ordered) - 1))))]


class RecordingClock:
    """Wraps a timer; remembers the last clock reading it gave out (the bus's tx time).

    ``fired`` collects, for every callback scheduled through it, how late the callback
    ran relative to its deadline (seconds): the timer's own share of a deadline's lateness.
    """

    def __init__(self, inner: Timer) -> None:
        self.inner = inner
        self.last = 0.0
        self.fired: list[float] = []

    def now(self) -> float:
        """Read the inner clock and remember it."""
        self.last = self.inner.now()
        return self.last

    def call_at(
        self, deadline: float, callback: Callable[[], None], *, precise: bool = True
    ) -> TimerHandle:
        """Delegate to the inner timer, noting how late the callback runs."""
        inner = self.inner

        def run() -> None:
            self.fired.append(inner.now() - deadline)
            callback()

        return inner.call_at(deadline, run, precise=precise)


def record_tx(bus: Bus, clock: RecordingClock, into: list[float]) -> None:
    """Append the bus's clock reading to ``into`` at every frame it writes."""
    write = bus.transport.write

    def timed_write(data: bytes) -> None:
        into.append(clock.last)  # the bus reads its clock in _transmit, then writes
        write(data)

    bus.transport.write = timed_write  # type: ignore[method-assign]


# -- (a) round trips -------------------------------------------------------------------------


async def rtt_ours(path: str, backend: str, n: int) -> list[float]:
    """Round trips of ``InspireLA.status`` on a ``Bus`` (seconds)."""
    timer = default_timer()
    # A round trip is measured, not judged: a generous margin so that one slow reply on
    # a loaded machine is a long sample, not an aborted run.
    bus = Bus(
        SerialTransport(path, baudrate=BAUD, backend=backend),
        families=[Family.LA],
        host_margin=0.05,
    )
    samples: list[float] = []
    async with bus:
        actuator = InspireLA(bus, 1)
        await actuator.status()  # warm-up
        origin = timer.now() + PACE_S
        for k in range(n):
            await timer.sleep_until(origin + k * PACE_S)
            t0 = time.perf_counter()
            await actuator.status()
            samples.append(time.perf_counter() - t0)
    return samples


class _MinimalProtocol(asyncio.Protocol):
    """The least a client can do: collect bytes, resolve a future at 22."""

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.waiter: asyncio.Future[bytes] | None = None
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        if len(self.buffer) >= REPLY_SIZE and self.waiter is not None:
            if not self.waiter.done():
                self.waiter.set_result(bytes(self.buffer[:REPLY_SIZE]))
            del self.buffer[:REPLY_SIZE]


async def rtt_minimal(path: str, backend: str, n: int) -> list[float]:
    """Round trips of the minimal asyncio client on ``backend`` (seconds)."""
    module = importlib.import_module(BACKEND_MODULES[backend])
    loop = asyncio.get_running_loop()
    timer = default_timer()
    transport, protocol = await module.create_serial_connection(
        loop, _MinimalProtocol, path, baudrate=BAUD
    )
    samples: list[float] = []
    try:

        async def once() -> None:
            protocol.waiter = loop.create_future()
            transport.write(QUERY_BYTES)
            reply = await asyncio.wait_for(protocol.waiter, BLOCKING_TIMEOUT_S)
            assert reply[3] == 1, reply.hex(" ")

        await once()  # warm-up
        origin = timer.now() + PACE_S
        for k in range(n):
            await timer.sleep_until(origin + k * PACE_S)
            t0 = time.perf_counter()
            await once()
            samples.append(time.perf_counter() - t0)
    finally:
        transport.close()
        await asyncio.sleep(0.01)  # let the backend release the port
    return samples


def rtt_blocking(path: str, n: int) -> list[float]:
    """Round trips of a blocking pyserial client (seconds)."""
    samples: list[float] = []
    with serial.Serial(path, BAUD, timeout=BLOCKING_TIMEOUT_S) as port:
        port.write(QUERY_BYTES)
        port.read(REPLY_SIZE)  # warm-up
        origin = time.monotonic() + PACE_S
        for k in range(n):
            delay = origin + k * PACE_S - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            t0 = time.perf_counter()
            port.write(QUERY_BYTES)
            reply = port.read(REPLY_SIZE)
            samples.append(time.perf_counter() - t0)
            if len(reply) != REPLY_SIZE:
                raise RuntimeError(f"blocking client got {len(reply)} bytes, expected 22")
    return samples


# -- (b) sustained rate ----------------------------------------------------------------------


async def sustained_rate(path: str, backend: str, seconds: float) -> dict[str, Any]:
    """Status queries back to back for ``seconds``; returns count, elapsed, bus-side gaps."""
    clock = RecordingClock(default_timer())
    bus = Bus(
        SerialTransport(path, baudrate=BAUD, backend=backend),
        families=[Family.LA],
        timer=clock,  # type: ignore[arg-type]
    )
    tx_times: list[float] = []
    async with bus:
        record_tx(bus, clock, tx_times)
        actuators = [InspireLA(bus, i) for i in LA_IDS]
        await actuators[0].status()  # warm-up
        tx_times.clear()
        counts = [0] * len(actuators)
        t0 = time.monotonic()
        end = t0 + seconds

        async def worker(k: int) -> None:
            # One query in flight per actuator: the queue always holds the next frame,
            # so the rate is the bus's, not the caller's turn-around.
            while time.monotonic() < end:
                await actuators[k].status()
                counts[k] += 1

        await asyncio.gather(*(worker(k) for k in range(len(actuators))))
        count = sum(counts)
        elapsed = time.monotonic() - t0
        timeouts = bus.stats.timeouts
    gaps = [b - a for a, b in itertools.pairwise(tx_times)]
    return {
        "count": count,
        "elapsed": elapsed,
        "min_gap_bus_us": min(gaps) * 1e6 if gaps else float("nan"),
        "gap_bus_p50_us": statistics.median(gaps) * 1e6 if gaps else float("nan"),
        "timer_late_p50_us": statistics.median(clock.fired) * 1e6 if clock.fired else 0.0,
        "timeouts": timeouts,
    }


# -- (c) deadline precision -------------------------------------------------------------------


async def deadline_precision(path: str, backend: str, n: int) -> dict[str, Any]:
    """Lateness of ``ReplyTimeoutError`` after tx + budget, in seconds (see the docstring)."""
    clock = RecordingClock(default_timer())
    bus = Bus(
        SerialTransport(path, baudrate=BAUD, backend=backend),
        families=[Family.LA],
        host_margin=0.0,
        late_guard=0.0,
        retries=0,
        timer=clock,  # type: ignore[arg-type]
    )
    tx_times: list[float] = []
    lateness: list[float] = []
    query = la.Control(SILENT_ID, la.ControlAction.QUERY_STATUS)
    async with bus:
        record_tx(bus, clock, tx_times)
        origin = clock.now() + DEADLINE_PACE_S
        for k in range(n):
            await clock.inner.sleep_until(origin + k * DEADLINE_PACE_S)
            sent = len(tx_times)
            try:
                await bus.request(query, timeout=BUDGET_S)
            except ReplyTimeoutError:
                raised = time.monotonic()
            else:
                raise RuntimeError(f"ID {SILENT_ID} answered: the benchmark needs it silent")
            if len(tx_times) != sent + 1:
                raise RuntimeError("expected exactly one transmission per request")
            lateness.append(raised - (tx_times[-1] + BUDGET_S))
    return {"lateness": lateness, "timer_lateness": clock.fired}


# -- driver ------------------------------------------------------------------------------------


def _serve(conn: Connection, log_file: str | None) -> None:
    """Child process: serve the LA models on a pty until told to stop."""
    models = [LAModel(i) for i in LA_IDS]
    # Not busy-polling (PtySim(spin=True)): on 2 cores a spinning simulator takes the
    # core the bus needs, and it did not change the smallest gap the simulator saw.
    with PtySim(models, baud=BAUD, log_file=log_file) as sim:
        conn.send(sim.path)
        conn.recv()
        error = sim.error
    conn.send(None if error is None else repr(error))


@contextlib.contextmanager
def served(where: str, log_file: Path | None) -> Iterator[str]:
    """Serve the LA models on a pty (in a child process or a thread); yield its path.

    Raises:
        RuntimeError: the simulator did not start or failed while serving.
    """
    if where == "thread":
        models = [LAModel(i) for i in LA_IDS]
        with PtySim(models, baud=BAUD, log_file=log_file) as sim:
            yield sim.path
        if sim.error is not None:
            raise RuntimeError("the simulator thread failed") from sim.error
        return
    context = multiprocessing.get_context("spawn")
    parent, child = context.Pipe()
    process = context.Process(
        target=_serve, args=(child, None if log_file is None else str(log_file)), daemon=True
    )
    process.start()
    error: str | None = None
    try:
        if not parent.poll(SIM_START_TIMEOUT_S):
            raise RuntimeError("the simulator process did not start")
        yield parent.recv()
    finally:
        parent.send("stop")
        error = parent.recv() if parent.poll(SIM_START_TIMEOUT_S) else "it did not answer"
        process.join(SIM_START_TIMEOUT_S)
        if process.is_alive():
            process.terminate()
    if error is not None:
        raise RuntimeError(f"the simulator process failed: {error}")


def request_starts(log_file: Path) -> list[float]:
    """Start times (s) of the requests in a simulator log: end on the wire minus wire time."""
    wire = wire_time(len(QUERY_BYTES), BAUD)
    starts = []
    with log_file.open(encoding="utf-8") as f:
        for line in f:
            record = json.loads(line)
            if record.get("direction") == "request":  # frame-log records, not the header
                starts.append(float(record["t"]) - wire)
    return starts


async def timer_name() -> str:
    """The class of the bus's default timer on this loop."""
    return type(default_timer()).__name__


def loop_factory(name: str) -> Callable[[], asyncio.AbstractEventLoop]:
    """The event loop factory for ``--loop``."""
    if name == "uvloop":
        import uvloop

        return uvloop.new_event_loop
    return asyncio.new_event_loop


def goal(met: bool) -> str:
    return "met" if met else "NOT MET"


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; return the process exit status (0 even if a goal is missed)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--quick", action="store_true", help="300 round trips, 1 s rate run")
    parser.add_argument("--n", type=int, default=None, help="round trips per client (2000)")
    parser.add_argument("--seconds", type=float, default=None, help="rate run length (3 s)")
    parser.add_argument("--backend", choices=BACKENDS, default=DEFAULT_BACKEND)
    parser.add_argument("--loop", choices=("asyncio", "uvloop"), default="asyncio")
    parser.add_argument(
        "--sim",
        choices=("process", "thread"),
        default="process",
        help="run PtySim in a child process (default) or in a thread of this one, where it "
        "competes with the bus for the GIL",
    )
    parser.add_argument("--profile", action="store_true", help="cProfile the rate run")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON output path")
    parser.add_argument(
        "--samples",
        type=Path,
        default=None,
        help="also write the raw samples (seconds) to this JSON file, for plots",
    )
    args = parser.parse_args(argv)
    if args.n is None:
        args.n = 300 if args.quick else 2000
    if args.seconds is None:
        args.seconds = 1.0 if args.quick else 3.0
    if args.n < 1 or args.seconds <= 0:
        parser.error("--n must be >= 1 and --seconds > 0")

    with asyncio.Runner(loop_factory=loop_factory(args.loop)) as runner:
        res: dict[str, Any] = {}
        with served(args.sim, None) as path:
            blocking = rtt_blocking(path, args.n)
            res["ours"] = runner.run(rtt_ours(path, args.backend, args.n))
            res["minimal"] = runner.run(rtt_minimal(path, args.backend, args.n))
        with tempfile.TemporaryDirectory() as tmp:
            log_file = Path(tmp) / "rate.jsonl"
            with served(args.sim, log_file) as path:
                profiler = cProfile.Profile() if args.profile else None
                if profiler is not None:
                    profiler.enable()
                res["rate"] = runner.run(sustained_rate(path, args.backend, args.seconds))
                if profiler is not None:
                    profiler.disable()
                    text = io.StringIO()
                    pstats.Stats(profiler, stream=text).sort_stats("tottime").print_stats(25)
                    res["profile"] = text.getvalue()
            sim_starts = request_starts(log_file)
        with served(args.sim, None) as path:
            res["deadline"] = runner.run(deadline_precision(path, args.backend, args.n))
        res["timer"] = runner.run(timer_name())

    ours, minimal = res["ours"], res["minimal"]
    rate, lateness = res["rate"], res["deadline"]["lateness"]
    timer_late = res["deadline"]["timer_lateness"]
    # The warm-up query of the rate phase is logged too; the gap to it is not a measured one.
    starts = sim_starts[1:]
    sim_gaps = [b - a for a, b in itertools.pairwise(starts)]
    ours_p50 = statistics.median(ours)
    minimal_p50 = statistics.median(minimal)
    report: dict[str, Any] = {
        "rtt_p50_us": ours_p50 * 1e6,
        "rtt_p99_us": percentile(ours, 0.99) * 1e6,
        "rtt_minimal_client_p50_us": minimal_p50 * 1e6,
        "rtt_minimal_client_p99_us": percentile(minimal, 0.99) * 1e6,
        "rtt_blocking_pyserial_p50_us": statistics.median(blocking) * 1e6,
        "rtt_blocking_pyserial_p99_us": percentile(blocking, 0.99) * 1e6,
        "rtt_ratio_vs_minimal": ours_p50 / minimal_p50,
        "commands_per_s": rate["count"] / rate["elapsed"],
        "min_gap_us": min(sim_gaps) * 1e6 if sim_gaps else float("nan"),
        "gaps_under_1000us": sum(1 for g in sim_gaps if g < GOAL_MIN_GAP_US * 1e-6),
        "min_gap_bus_clock_us": rate["min_gap_bus_us"],
        "rate_gap_bus_clock_p50_us": rate["gap_bus_p50_us"],
        "rate_timer_fire_late_p50_us": rate["timer_late_p50_us"],
        "rate_timeouts": rate["timeouts"],
        "timeout_late_p50_us": statistics.median(lateness) * 1e6,
        "timeout_late_p99_us": percentile(lateness, 0.99) * 1e6,
        "timeout_late_max_us": max(lateness) * 1e6,
        "timeout_early_count": sum(1 for v in lateness if v < 0),
        "timeout_timer_fire_late_p50_us": statistics.median(timer_late) * 1e6,
        "timeout_timer_fire_late_p99_us": percentile(timer_late, 0.99) * 1e6,
        "n": args.n,
        "rate_seconds": args.seconds,
        "backend": args.backend,
        "loop": args.loop,
        "timer": res["timer"],
        "machine": f"{platform.platform()}, {os.cpu_count()} cpus, Python {sys.version.split()[0]}",
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    print_table(report)
    if "profile" in res:
        print("\ncProfile of the rate run (sorted by own time):\n")
        print(res["profile"])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    print(f"\nwrote {args.out}")
    if args.samples is not None:
        samples = {
            "unit": "s",
            "rtt_ours": ours,
            "rtt_minimal_client": minimal,
            "rtt_blocking_pyserial": blocking,
            "timeout_lateness": lateness,
            "timeout_timer_fire_lateness": timer_late,
            "rate_sim_gaps": sim_gaps,
        }
        args.samples.parent.mkdir(parents=True, exist_ok=True)
        args.samples.write_text(json.dumps(samples) + "\n", encoding="utf-8")
        print(f"wrote {args.samples}")
    return 0


def print_table(r: dict[str, Any]) -> None:
    """Print the results with their goals."""
    rows = [
        ("(a) RTT ours p50 / p99", f"{r['rtt_p50_us']:.0f} / {r['rtt_p99_us']:.0f} us", ""),
        (
            "(a) RTT minimal asyncio p50 / p99",
            f"{r['rtt_minimal_client_p50_us']:.0f} / {r['rtt_minimal_client_p99_us']:.0f} us",
            "",
        ),
        (
            "(a) RTT blocking pyserial p50 / p99",
            f"{r['rtt_blocking_pyserial_p50_us']:.0f} / {r['rtt_blocking_pyserial_p99_us']:.0f} us",
            "",
        ),
        (
            "(a) ratio ours / minimal (p50)",
            f"{r['rtt_ratio_vs_minimal']:.2f}",
            f"<= {GOAL_RATIO}: {goal(r['rtt_ratio_vs_minimal'] <= GOAL_RATIO)}",
        ),
        (
            "(b) commands/s at 1 ms spacing",
            f"{r['commands_per_s']:.0f}",
            f">= {GOAL_RATE:.0f}: {goal(r['commands_per_s'] >= GOAL_RATE)}",
        ),
        (
            "(b) min start gap, simulator",
            f"{r['min_gap_us']:.0f} us ({r['gaps_under_1000us']} under 1000)",
            f">= {GOAL_MIN_GAP_US:.0f}: {goal(r['min_gap_us'] >= GOAL_MIN_GAP_US)}",
        ),
        ("(b) min start gap, bus clock", f"{r['min_gap_bus_clock_us']:.0f} us", ""),
        (
            "(b) tx gap p50 / timer firing p50",
            f"{r['rate_gap_bus_clock_p50_us']:.0f} / {r['rate_timer_fire_late_p50_us']:.0f} us",
            "",
        ),
        (
            "(c) deadline early count",
            f"{r['timeout_early_count']}",
            f"== {GOAL_EARLY}: {goal(r['timeout_early_count'] == GOAL_EARLY)}",
        ),
        (
            "(c) deadline lateness p50 / p99",
            f"{r['timeout_late_p50_us']:.0f} / {r['timeout_late_p99_us']:.0f} us",
            f"p99 <= {GOAL_LATE_P99_US:.0f}: {goal(r['timeout_late_p99_us'] <= GOAL_LATE_P99_US)}",
        ),
        (
            "(c) of which the timer firing p50 / p99",
            f"{r['timeout_timer_fire_late_p50_us']:.0f} / "
            f"{r['timeout_timer_fire_late_p99_us']:.0f} us",
            "",
        ),
    ]
    print(
        f"bench_bus: backend={r['backend']} loop={r['loop']} timer={r['timer']} n={r['n']} "
        f"rate run {r['rate_seconds']:.1f} s\n{r['machine']}\n"
    )
    width = max(len(name) for name, _, _ in rows)
    for name, value, target in rows:
        print(f"{name:<{width}}  {value:>28}  {target}")
    print(
        "\n(c) lateness = when ReplyTimeoutError reached the caller - (bus clock at tx + "
        f"{BUDGET_S * 1e6:.0f} us budget); host_margin=0, no retries, no late guard."
    )


if __name__ == "__main__":
    sys.exit(main())
