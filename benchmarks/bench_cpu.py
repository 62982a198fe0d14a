"""CPU per bus-tick: motorbus against hand-written loops doing the same work.

The work per bus and per 10 ms tick: one 0xF3 follow broadcast of 15 entries (targets
from a trajectory, encoded every tick) and one LA status query (IDs round-robin) whose
22-byte reply is read.  For 1, 16, 32 and 64 buses, in the same run and on the same
ptys (one ``pty_recorder.py --answer`` process answers every bus at once):

* ``ours``: ``BusManager`` buses, a ``Streamer.follow`` per bus and a task per bus that
  awaits ``InspireLA.status()`` once a tick (3 ms after the tick, on the bus's timer);
* ``timerfd`` (issue 23's baseline (b), the floor): ``baselines.polled_timerfd_loop``,
  one timerfd per tick phase (the buses spread over ours's phases, so the same wake-ups)
  that ``os.write``s each bus's broadcast at its tick and its query 3 ms later, and an
  ``add_reader`` callback per pty that reads replies;
* ``timerfd_spin`` (baseline (c), the precision floor): the same, armed
  ``baselines.SPIN_S`` before each tick and busy-waiting the rest;
* ``minimal``: one event loop, ``loop.call_at`` per tick and bus (each bus on a phase of
  its own) that ``os.write``s the broadcast, a second ``call_at`` 1.5 ms later that writes
  the query, and an ``add_reader`` callback per pty that reads replies.

None of the baselines frames, matches, times out or keeps a spacing rule: the least a
program can do for the same writes.

CPU is this process's user + system time over the run's wall time (100 % = one core).
Each case runs in ``--rounds`` rounds of ``seconds / rounds``, the four loops taking turns
(each goes first in its round, ``turn_order``), and each side's CPU is its total over
its total wall time: a slow spell of a shared machine then falls on all alike (run one
after the other, 10 s each, the ratio at 16 buses moved from 2.6 to 3.7 between full
runs of the same code).  ``round_ratios_timerfd`` and ``round_ratios`` keep each round's
own ratio to (b) and to the minimal loop.
``spin_percent`` is the part of ours that the bus timer spent spinning before precise
deadlines (its ``spin_seconds``; 0 where the timer does not spin): what the tick
precision costs, apart from the Python that does the work.  ``timer_arms_per_tick``
counts the bus timer's ``timerfd_settime`` calls per tick sent (its ``arms``; a tick here
is a broadcast and a poll): each one for the near future reprograms the CPU's timer,
which costs a VM tens of us (``bench_pieces.py``).  A count moves far less with the
machine than CPU time does (``ab_cpu.py`` says how much).
Goals (issue 23): ours / (b) <= 1.5 at 1, 16 and 32 buses, and 32 buses under 35 %
of a core.  (Until 2026-12-03 the ratio goal was read against ``minimal``, which is not
the issue's (b): it wakes once per bus, not once per phase.)

Larger counts (``run.py`` adds 128) show where one core saturates: this process has one
thread, so it never uses more than one core; past that point it sends
fewer ticks than it should.  Ours "keeps up" with a bus count when it sent at least 99 %
of its ticks and no stream ended with an error; ``max_buses_keeping_up`` is the largest
count up to which it kept up with every measured count.  Falling behind at well under
100 % CPU means the machine did not give this process its core (the responder and any
other load share the machine's cores).  ``ratio_per_tick`` divides each side's CPU by
the ticks it sent: the same as ``ratio`` (to the minimal loop) while ours keeps up, the
honest figure once it does not.

    python benchmarks/bench_cpu.py [--quick] [--seconds 10] [--rounds 5]
        [--buses 1,16,32,64] [--polls tick|shared|none] [--phase-groups N] [--out PATH]

``--polls none`` leaves the status queries out of every loop: the streams alone, the
work issue 40's first CPU goal (ours / (b) <= 1.2) is read against; with the queries
(the default), the goal is 1.5.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import operator
import os
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import tty
from array import array
from pathlib import Path
from typing import Any

from baselines import SPIN_S, PolledWork, polled_result, polled_timerfd_loop
from harness import TimerProbe, write_report
from motorbus import manager
from motorbus.bus.stats import LatencyHistogram
from motorbus.errors import MotorbusError
from motorbus.manager import BusManager
from motorbus.protocol import la

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "cpu.json"
PERIOD_S = 0.010
N_ACTUATORS = 15
BAUD = 921600
#: Where in the tick the minimal loop writes its query (after the 1 ms spacing).
MINIMAL_POLL_OFFSET_S = 0.0015
#: Where in the tick our poll task asks for a status (leaves room for the broadcast).
OURS_POLL_OFFSET_S = 0.003
REPLY_BYTES = la.STATUS_FRAME_SIZE
#: The status queries of the baselines, one a tick, round-robin over the IDs.
QUERIES = tuple(
    la.Control(i, la.ControlAction.QUERY_STATUS).encode() for i in range(1, N_ACTUATORS + 1)
)
GOAL_RATIO = 1.5
#: The goal with no status queries (``--polls none``): the streams alone (issue 40).
GOAL_RATIO_NO_POLLS = 1.2
#: The bus counts the ratio goal is set at (issue 23); others are reported only.
GOAL_RATIO_BUSES = (1, 16, 32)
GOAL_32_CPU_PERCENT = 35.0
#: Share of its ticks ours must send to keep up with a bus count.
KEEPS_UP_TICKS_SENT_PCT = 99.0
#: The loops of each case, measured in turn (see the module docstring).
SIDES = ("ours", "timerfd", "timerfd_spin", "minimal")
#: The baseline the ratio goal is read against: issue 23's (b), the floor.
GOAL_BASELINE = "timerfd"
#: File descriptors a bus count needs here, per bus (ours and the minimal loop open one
#: pty each; the responder, a child that inherits the limit, holds two), plus room.
FDS_PER_BUS = 2
FDS_SPARE = 64
#: Start-up room before the first tick.
LEAD_S = 0.05
#: The per-bus-count lists of cpu.json, one entry per ``--buses`` count (run.py publishes
#: them all under ``cpu.*``).
ROW_KEYS = (
    "buses",
    "cpu_percent",
    "spin_percent",
    "timer_arms_per_tick",
    "tick_p99_us",
    "timerfd_cpu_percent",
    "ratio_timerfd",
    "round_ratios_timerfd",
    "timerfd_spin_cpu_percent",
    "ratio_timerfd_spin",
    "minimal_cpu_percent",
    "ratio",
    "ratio_per_tick",
    "ticks",
    "minimal_ticks",
    "replies",
    "minimal_replies",
    "timerfd_replies",
    "timerfd_spin_replies",
    "late_ticks",
    "skipped_ticks",
    "ticks_sent_pct",
    "stream_errors",
    "keeps_up",
    "round_ratios",
)


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def raise_fd_limit(buses: int) -> None:
    """Raise the soft RLIMIT_NOFILE to the hard limit if ``buses`` could need more."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = FDS_PER_BUS * buses + FDS_SPARE
    if soft != resource.RLIM_INFINITY and soft < need:
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
        if hard != resource.RLIM_INFINITY and hard < need:
            raise SystemExit(f"{buses} buses need about {need} file descriptors; limit {hard}")


def merged(histograms: list[Any]) -> Any:
    """One ``LatencyHistogram`` of every sample of ``histograms`` (each stream keeps its
    own): the p99 over all ticks, where one stream's p99 of a short run is its slowest
    few ticks (its start-up).  Here, not a method of the histogram: ``ab_cpu.py`` runs
    this workload against older trees, whose histogram has no such method."""
    out = type(histograms[0])() if histograms else LatencyHistogram()
    for h in histograms:
        if not h.count:
            continue
        out.counts = array(out.counts.typecode, map(operator.add, out.counts, h.counts))
        out.count += h.count
        out.total += h.total
        out.min = min(out.min, h.min)
        out.max = max(out.max, h.max)
    return out


def trajectory(t: float) -> list[float]:
    return [
        1000 + 600 * math.sin(2 * math.pi * 0.5 * t + 2 * math.pi * i / N_ACTUATORS)
        for i in range(N_ACTUATORS)
    ]


def broadcast_bytes(t: float) -> bytes:
    targets = {i + 1: round(v) for i, v in enumerate(trajectory(t))}
    return la.split_broadcast(la.BroadcastMode.FOLLOW, targets)[0].encode()


async def minimal(paths: list[str], seconds: float, polls: bool = True) -> dict[str, Any]:
    """The hand-written loop (see the module docstring); CPU %, ticks, polls, replies.
    Without ``polls``, it writes the broadcasts only."""
    loop = asyncio.get_running_loop()
    fds = []
    for path in paths:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(fd)
        fds.append(fd)
    received = [0] * len(fds)
    counts = {"ticks": 0, "polls": 0}
    n = len(fds)
    origin = loop.time() + LEAD_S
    end = origin + seconds
    done = loop.create_future()
    pending = [n]

    def on_readable(i: int) -> None:
        with contextlib.suppress(BlockingIOError):
            received[i] += len(os.read(fds[i], 4096))

    def poll(i: int, k: int) -> None:
        os.write(fds[i], QUERIES[k % len(QUERIES)])
        counts["polls"] += 1

    def tick(i: int, k: int) -> None:
        t = origin + i * PERIOD_S / n + k * PERIOD_S
        os.write(fds[i], broadcast_bytes(k * PERIOD_S))
        counts["ticks"] += 1
        if polls:
            loop.call_at(t + MINIMAL_POLL_OFFSET_S, poll, i, k)
        if t + PERIOD_S < end:
            loop.call_at(t + PERIOD_S, tick, i, k + 1)
        else:
            pending[0] -= 1
            if pending[0] == 0:
                loop.call_at(t + 2 * MINIMAL_POLL_OFFSET_S, done.set_result, None)

    for i, fd in enumerate(fds):
        loop.add_reader(fd, on_readable, i)
        loop.call_at(origin + i * PERIOD_S / n, tick, i, 0)
    wall0, cpu0 = time.monotonic(), cpu_seconds()
    await done
    wall, cpu = time.monotonic() - wall0, cpu_seconds() - cpu0
    for fd in fds:
        loop.remove_reader(fd)
        os.close(fd)
    return polled_result(cpu, wall, counts, sum(received) // REPLY_BYTES)


#: Where ``ours``'s poll tasks ask for a status: ``tick``, 3 ms after their own bus's tick
#: (the polls stay clear of the ticks); ``shared``, every bus's poll task on one clock
#: started with the run, as a user's own poll loop is, whatever the streams' phases (the
#: polls of all buses come in one burst, which lands on some buses' ticks); ``none``, no
#: poll task and no queries in the baselines either: the streams alone.
POLL_PHASES = ("tick", "shared", "none")


async def ours(
    paths: list[str], seconds: float, polls: str = "tick", phase_groups: int | None = None
) -> dict[str, Any]:
    """motorbus doing the same work; CPU %, ticks, polls, replies.

    ``polls`` is one of ``POLL_PHASES``.  ``phase_groups`` replaces the manager's
    ``PHASE_GROUPS`` for this run (an experiment: how many tick phases the buses are
    spread over, each with its own wake-ups; None keeps the library's).
    """
    if polls not in POLL_PHASES:
        raise ValueError(f"polls must be one of {', '.join(POLL_PHASES)}, got {polls!r}")
    if phase_groups is not None and (
        isinstance(phase_groups, bool) or not isinstance(phase_groups, int) or phase_groups < 1
    ):
        raise ValueError(f"phase_groups must be an integer >= 1, got {phase_groups!r}")
    library_groups = manager.PHASE_GROUPS
    if phase_groups is not None:
        manager.PHASE_GROUPS = phase_groups
    try:
        return await _ours(paths, seconds, polls)
    finally:
        manager.PHASE_GROUPS = library_groups


async def _ours(paths: list[str], seconds: float, polls: str) -> dict[str, Any]:
    mgr = BusManager(safe_stop=False)
    for i, path in enumerate(paths):
        mgr.add_bus(f"bus{i}", path, baud=BAUD, devices=[f"la:1-{N_ACTUATORS}"])
    async with mgr:
        names = list(mgr.buses)
        answered = [0]
        failed = [0]
        end = [math.inf]
        streams = []
        for name in names:
            actuators = [mgr.la(name, i) for i in range(1, N_ACTUATORS + 1)]
            streams.append(
                mgr.streamer(name).follow(
                    actuators,
                    lambda t, s: None if t >= seconds else trajectory(t),
                    period=PERIOD_S,
                )
            )

        async def poller(name: str, origin: float) -> None:
            bus = mgr.bus(name)
            actuators = [mgr.la(name, i) for i in range(1, N_ACTUATORS + 1)]
            k = 0
            # Bounded by time as well: a saturated loop must not poll on past the run.
            while origin + k * PERIOD_S < origin + seconds and bus.timer.now() < end[0]:
                # As the minimal loop's loop.call_at: on time, not to the microsecond.
                await bus.timer.sleep_until(
                    origin + k * PERIOD_S + OURS_POLL_OFFSET_S, precise=False
                )
                try:
                    await actuators[k % N_ACTUATORS].status()
                    answered[0] += 1
                except MotorbusError:
                    failed[0] += 1
                k += 1

        # The buses of one loop share its timer: each distinct timer is probed once.
        timers = {id(t): t for t in (mgr.bus(name).timer for name in names)}.values()
        probes = [TimerProbe(t) for t in timers]
        wall0, cpu0 = time.monotonic(), cpu_seconds()
        end[0] = max(s.origin for s in streams) + seconds + PERIOD_S
        shared = min(s.origin for s in streams)
        poll_origins = [s.origin if polls == "tick" else shared for s in streams]
        tasks = [
            asyncio.create_task(poller(name, origin))
            for name, origin in zip(names, poll_origins, strict=True)
            if polls != "none"
        ]
        # A saturated loop falls behind and a stream may end with a gap: that is a figure
        # (stream_errors), not a failure of the benchmark.
        outcomes = await asyncio.gather(
            *(s.wait() for s in streams), *tasks, return_exceptions=True
        )
        wall, cpu = time.monotonic() - wall0, cpu_seconds() - cpu0
        spin, arms = sum(p.spin_s for p in probes), sum(p.arms for p in probes)
        errors = [o for o in outcomes if isinstance(o, BaseException)]
        for err in errors:
            if not isinstance(err, MotorbusError):
                raise err
        # The bus's own view of each tick's write against its deadline (the kernel's is
        # bench_stream.py's): what a CPU saving must not cost.
        ticks_late = merged([s.stats.jitter for s in streams])
        return {
            "tick_p99_us": 1e6 * ticks_late.percentile(99) if ticks_late.count else None,
            "tick_max_us": 1e6 * ticks_late.max if ticks_late.count else None,
            "cpu_percent": 100 * cpu / wall,
            "spin_percent": 100 * spin / wall,
            "cpu_s": cpu,
            "wall_s": wall,
            "spin_s": spin,
            "timer_arms": arms,
            "ticks": sum(s.stats.ticks for s in streams),
            "polls": answered[0] + failed[0],
            "replies": answered[0],
            "late_ticks": sum(s.stats.late for s in streams),
            "skipped_ticks": sum(s.stats.skipped for s in streams),
            # Reply deadlines that ran out (each attempt): each retry then waits out its
            # device's late guard (20 ms), which must hold nothing else.
            "reply_timeouts": sum(mgr.bus(name).stats.timeouts for name in names),
            "stream_errors": len(errors),
            # How many distinct tick phases the buses were spread over (phase_groups).
            "tick_phases": len({mgr.streamer(name).phase for name in names}),
            # How many distinct clocks the poll tasks kept (1 with polls="shared").
            "poll_clocks": len(set(poll_origins)),
            "first_error": str(errors[0]) if errors else None,
        }


class Responder:
    """``pty_recorder.py N OUT --answer`` in a child process: N ptys that answer."""

    def __init__(self, count: int, out: Path) -> None:
        script = HERE / "pty_recorder.py"
        self.proc = subprocess.Popen(
            [sys.executable, str(script), str(count), str(out), "--answer"],
            stdout=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        assert self.proc.stdout is not None
        self.paths = self.proc.stdout.readline().split()

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGINT)
        self.proc.wait(30)


def combine(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """One side's rounds as one run: counts summed, CPU % over the total wall time, the
    first error kept."""
    wall = sum(r["wall_s"] for r in rounds)
    out: dict[str, Any] = {
        "cpu_percent": 100 * sum(r["cpu_s"] for r in rounds) / wall,
        "first_error": next((r["first_error"] for r in rounds if r.get("first_error")), None),
    }
    if "spin_s" in rounds[0]:
        out["spin_percent"] = 100 * sum(r["spin_s"] for r in rounds) / wall
    for key in (
        "ticks",
        "polls",
        "replies",
        "late_ticks",
        "skipped_ticks",
        "stream_errors",
        "timer_arms",
    ):
        if key in rounds[0]:
            out[key] = sum(r[key] for r in rounds)
    p99s = [r["tick_p99_us"] for r in rounds if r.get("tick_p99_us") is not None]
    if p99s:  # percentiles do not add up: the median round's
        out["tick_p99_us"] = statistics.median(p99s)
    return out


def turn_order(r: int) -> tuple[str, ...]:
    """The order of the sides in round ``r``: each takes its turn first, so that a slow
    spell of a shared machine does not always fall on the same one."""
    k = r % len(SIDES)
    return SIDES[k:] + SIDES[:k]


def polled_work(phases: int, polls: bool = True) -> PolledWork:
    """This benchmark's work for ``baselines.polled_timerfd_loop``: the broadcast of
    ``broadcast_bytes``, then (with ``polls``) a status query ``OURS_POLL_OFFSET_S``
    later, as ours."""
    return PolledWork(
        frame=lambda k: broadcast_bytes(k * PERIOD_S),
        queries=QUERIES if polls else (),
        reply_size=REPLY_BYTES,
        period=PERIOD_S,
        poll_offset=OURS_POLL_OFFSET_S,
        phases=phases,
    )


def run_side(
    side: str, paths: list[str], seconds: float, polls: str, phase_groups: int | None
) -> dict[str, Any]:
    """One round of one side (``SIDES``) on ``paths``, in an event loop of its own.

    The timerfd baselines spread their buses over ours's tick phases (``phase_groups``,
    else the library's ``PHASE_GROUPS``): the same tick times, so the same wake-ups.
    """
    if side == "ours":
        return asyncio.run(ours(paths, seconds, polls, phase_groups))
    if side == "minimal":
        return asyncio.run(minimal(paths, seconds, polls != "none"))
    if side not in SIDES:
        raise ValueError(f"side must be one of {', '.join(SIDES)}, got {side!r}")
    work = polled_work(
        manager.PHASE_GROUPS if phase_groups is None else phase_groups, polls != "none"
    )
    spin = SPIN_S if side == "timerfd_spin" else 0.0
    return asyncio.run(polled_timerfd_loop(paths, work, seconds, spin=spin))


def cpu_ratio(mine: dict[str, Any], base: dict[str, Any]) -> float | None:
    """Ours's CPU over a baseline's, both over their own wall time (2 decimals)."""
    if not base["cpu_percent"]:
        return None
    return round(mine["cpu_percent"] / base["cpu_percent"], 2)


def add_row(
    rows: dict[str, list[Any]], n: int, runs: dict[str, list[dict[str, Any]]], ticks_per_bus: int
) -> None:
    """Append the ``n``-bus case (each side's rounds, ``runs``) to ``rows`` and print it."""
    mine = combine(runs["ours"])
    base = {side: combine(runs[side]) for side in SIDES if side != "ours"}
    minimal_ratio = cpu_ratio(mine, base["minimal"])
    rows["buses"].append(n)
    rows["cpu_percent"].append(round(mine["cpu_percent"], 1))
    rows["spin_percent"].append(round(mine["spin_percent"], 1))
    # timerfd_settime calls per tick sent (each bus-tick also polls once): the CPU's timer
    # reprogrammed, which a VM pays tens of us for (bench_pieces.py).
    arms_per_tick = mine["timer_arms"] / mine["ticks"] if mine["ticks"] else None
    rows["timer_arms_per_tick"].append(None if arms_per_tick is None else round(arms_per_tick, 2))
    p99 = mine.get("tick_p99_us")
    rows["tick_p99_us"].append(None if p99 is None else round(p99))
    for side in ("timerfd", "timerfd_spin"):
        rows[f"{side}_cpu_percent"].append(round(base[side]["cpu_percent"], 1))
        rows[f"ratio_{side}"].append(cpu_ratio(mine, base[side]))
        rows[f"{side}_replies"].append(base[side]["replies"])
    rows["round_ratios_timerfd"].append(
        [cpu_ratio(m, b) for b, m in zip(runs[GOAL_BASELINE], runs["ours"], strict=True)]
    )
    rows["minimal_cpu_percent"].append(round(base["minimal"]["cpu_percent"], 1))
    rows["ratio"].append(minimal_ratio)
    rows["round_ratios"].append(
        [cpu_ratio(m, b) for b, m in zip(runs["minimal"], runs["ours"], strict=True)]
    )
    # The same per tick sent: differs from ``ratio`` once ours falls behind.
    per_tick = (
        minimal_ratio * base["minimal"]["ticks"] / mine["ticks"]
        if mine["ticks"] and minimal_ratio is not None
        else None
    )
    rows["ratio_per_tick"].append(None if per_tick is None else round(per_tick, 2))
    rows["ticks"].append(mine["ticks"])
    rows["minimal_ticks"].append(base["minimal"]["ticks"])
    rows["replies"].append(mine["replies"])
    rows["minimal_replies"].append(base["minimal"]["replies"])
    rows["late_ticks"].append(mine["late_ticks"])
    rows["skipped_ticks"].append(mine["skipped_ticks"])
    sent_pct = 100 * mine["ticks"] / (n * ticks_per_bus)
    keeps_up = sent_pct >= KEEPS_UP_TICKS_SENT_PCT and mine["stream_errors"] == 0
    rows["ticks_sent_pct"].append(round(sent_pct, 1))
    rows["stream_errors"].append(mine["stream_errors"])
    rows["keeps_up"].append(keeps_up)
    print(
        f"  {n:3d} buses: ours {mine['cpu_percent']:5.1f} % (spin "
        f"{mine['spin_percent']:4.1f} %, {rows['timer_arms_per_tick'][-1]} timer arms a "
        f"tick); (b) timerfd {base['timerfd']['cpu_percent']:5.1f} %, "
        f"ratio {rows['ratio_timerfd'][-1]}; (c) timerfd + spin "
        f"{base['timerfd_spin']['cpu_percent']:5.1f} %, ratio {rows['ratio_timerfd_spin'][-1]}; "
        f"minimal {base['minimal']['cpu_percent']:5.1f} %, ratio {minimal_ratio}\n"
        f"             ticks {mine['ticks']} / {n * ticks_per_bus} ({sent_pct:.1f} % sent), "
        f"replies {mine['replies']} / {base['timerfd']['replies']} (b); tick p99 (ours's "
        f"view) {rows['tick_p99_us'][-1]} us; {'keeps up' if keeps_up else 'FALLS BEHIND'}",
        flush=True,
    )
    if mine["first_error"]:
        print(f"        {mine['stream_errors']} ended: {mine['first_error']}")


def max_buses_keeping_up(buses: list[int], kept_up: list[bool]) -> int:
    """The largest count up to which ours kept up with every measured count; 0 if it did
    not with the smallest."""
    best = 0
    for n, ok in sorted(zip(buses, kept_up, strict=True)):
        if not ok:
            break
        best = n
    return best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="run length per case")
    parser.add_argument("--buses", default="1,16,32,64")
    parser.add_argument(
        "--rounds", type=int, default=5, help="turns of the two loops per case (>= 1)"
    )
    parser.add_argument(
        "--polls",
        choices=POLL_PHASES,
        default="tick",
        help="ours's polls: 3 ms after each bus's tick, on one clock for every bus, or "
        "none (the streams alone, in every loop)",
    )
    parser.add_argument(
        "--phase-groups",
        type=int,
        default=None,
        help="spread ours's buses over this many tick phases (default: the library's "
        f"{manager.PHASE_GROUPS})",
    )
    parser.add_argument("--quick", action="store_true", help="2 s per case, 2 rounds")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.quick:
        args.seconds = 2.0
        args.rounds = 2
    try:
        counts = [int(x) for x in args.buses.split(",") if x]
    except ValueError:
        parser.error(f"--buses must be comma-separated integers, got {args.buses!r}")
    if args.seconds <= 0 or not counts or min(counts) < 1:
        parser.error("--seconds must be > 0 and --buses list counts >= 1")
    if args.rounds < 1:
        parser.error(f"--rounds must be >= 1, got {args.rounds}")
    if args.phase_groups is not None and args.phase_groups < 1:
        parser.error(f"--phase-groups must be >= 1, got {args.phase_groups}")
    groups = manager.PHASE_GROUPS if args.phase_groups is None else args.phase_groups
    rows: dict[str, list[Any]] = {k: [] for k in ROW_KEYS}
    raise_fd_limit(max(counts))
    ticks_per_bus = round(args.seconds / PERIOD_S)
    print(
        f"CPU per bus-tick, {args.seconds:g} s per case in {args.rounds} rounds, "
        f"{PERIOD_S * 1e3:.0f} ms ticks, ours's polls: {args.polls}, phase groups: {groups}"
    )
    with tempfile.TemporaryDirectory(prefix="motorbus-cpu-") as tmp:
        for n in counts:
            responder = Responder(n, Path(tmp) / f"cpu{n}.json")
            runs: dict[str, list[dict[str, Any]]] = {side: [] for side in SIDES}
            try:
                for r in range(args.rounds):
                    for side in turn_order(r):
                        runs[side].append(
                            run_side(
                                side,
                                responder.paths,
                                args.seconds / args.rounds,
                                args.polls,
                                args.phase_groups,
                            )
                        )
            finally:
                responder.stop()
            add_row(rows, n, runs, ticks_per_bus)
    at32 = rows["buses"].index(32) if 32 in rows["buses"] else None
    goal_ratios = [
        r
        for b, r in zip(rows["buses"], rows["ratio_timerfd"], strict=True)
        if b in GOAL_RATIO_BUSES and r is not None
    ]
    minimal_ratios = [r for r in rows["ratio"] if r is not None]
    result: dict[str, Any] = {
        **rows,
        "max_ratio_timerfd_1_16_32": max(goal_ratios) if goal_ratios else None,
        "max_ratio": max(minimal_ratios) if minimal_ratios else None,
        "max_buses_keeping_up": max_buses_keeping_up(rows["buses"], rows["keeps_up"]),
        "cpu_percent_at_32": None if at32 is None else rows["cpu_percent"][at32],
        "seconds": args.seconds,
        "polls": args.polls,
        "phase_groups": groups,
        "spin_s_timerfd_spin": SPIN_S,
    }
    print(f"largest bus count ours keeps up with: {result['max_buses_keeping_up']}")
    alone = args.polls == "none"
    goal_ratio = GOAL_RATIO_NO_POLLS if alone else GOAL_RATIO
    goal_key = f"ratio_le_{goal_ratio:g}x_timerfd" + ("_no_polls" if alone else "")
    result["goals"] = {
        goal_key: None if not goal_ratios else max(goal_ratios) <= goal_ratio,
        "32_buses_lt_35pct": None
        if at32 is None
        else rows["cpu_percent"][at32] < GOAL_32_CPU_PERCENT,
    }
    for name, ok in result["goals"].items():
        print(f"goal {name:24} {'not measured' if ok is None else 'met' if ok else 'NOT met'}")
    write_report(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
