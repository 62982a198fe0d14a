"""What a stream tick's CPU is made of, found by taking parts of the bus's work out.

Profilers disagree about where ``bench_cpu.py``'s gap to the least loop goes (cProfile
adds the same cost to every call, py-spy's samples land at system calls).  This asks
without one: it runs ``bench_cpu.py``'s ``ours`` workload (a follow stream of 15
actuators per bus, one 0xF3 broadcast each 10 ms tick, on ptys one ``pty_recorder.py
--answer`` process reads) as it is and with parts of the bus replaced from outside by
doing nothing, and the least loop (``timerfd``, issue 23's baseline (b)) beside them:

* ``no_leases``: the lease rule (``LeaseKeeper.claim``, at each frame's preparation) and
  the owed safe actions (``LeaseTable.moved``, after each write) do nothing;
* ``no_stats``: the bus's and the streams' statistics (``BusCore.count_sent`` for each
  frame, ``BusCore.accepted`` for each reply, ``LatencyHistogram.record``) do nothing;
* ``direct_write``: a frame that expects no reply, on a bus with nothing queued and no
  reply owed, goes from ``BusEngine.queue`` straight to its write (``_transmit``, with
  everything it records) without asking the scheduler whether it may start (no
  spacing rule, no reservations, no sequence number);
* ``without_all``: the three together;
* ``bare_write``: the tick's frames prepared through the bus as ever (``Bus.prepare``:
  the checks, the lease rule, the job), but written by the streamer's timer callback
  itself with ``os.write`` on the port's file descriptor: no ``send_prepared``, no
  engine, no scheduler, no transport, nothing recorded of the write;
* ``bare_tick``: the bus's path taken out whole: the streamer encodes each tick's 0xF3
  frame itself (the same builder) and writes it with ``os.write``.  What is left is the
  streamer, its timer and the target source: the stream's own structure.

What a variant saves is what that part costs, whatever a profiler would say.  The
variants break the bus's guarantees (that is the point): they exist only in this
benchmark's process, for its run.  Every round runs each side once, in an order that
rotates from round to round (a slow spell of the shared machine falls on all alike);
the figures are each side's CPU (user + system over wall) over the rounds, and the
median over the rounds of its ratio to ``ours`` and to (b) in the same round.
``ticks_min``, the fewest ticks a side sent in a round, says whether it kept up: a side
that fell behind did less work, and its CPU says less.  ``--polls tick`` adds ``bench_cpu.py``'s
status query each tick to every side.

    python benchmarks/bench_cpu_parts.py [--buses 16] [--seconds 3] [--rounds 4]
        [--polls none|tick] [--out PATH]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import bench_cpu
from harness import write_report
from motorbus.bus.core import BusCore
from motorbus.bus.engine import BusEngine
from motorbus.bus.lease_shell import LeaseKeeper
from motorbus.bus.leases import LeaseTable
from motorbus.bus.stats import LatencyHistogram
from motorbus.streaming.model import broadcast_builder, broadcast_parts
from motorbus.streaming.tick import record_sent
from motorbus.streams import Streamer

RESULTS = Path(__file__).resolve().parent / "results" / "cpu_parts.json"
PARTS = ("no_leases", "no_stats", "direct_write")
#: Sides that take the bus's path for a stream frame out, in part or whole.
BARE = ("bare_write", "bare_tick")
SIDES = ("ours", *PARTS, "without_all", *BARE, "timerfd")


def _nothing(*_args: Any, **_kwargs: Any) -> None:
    return None


def _direct_queue(real: Callable[..., None]) -> Callable[..., None]:
    def queue(self: BusEngine, job: Any, start_by: float | None, *, checked: bool = False) -> None:
        if job.expects or self.core.schedule.heap or self.core.matcher.pending is not None:
            real(self, job, start_by, checked=checked)
            return
        self._transmit(job, checked=checked)  # the write and its bookkeeping, as queue's

    return queue


def _port_fd(streamer: Streamer) -> int:
    """The file descriptor of the streamer's port (pyserial's, under the backend)."""
    fd: int = streamer.bus._engine.transport._transport._serial.fd  # type: ignore[attr-defined]
    return fd


def _bare_prepare(self: Streamer, tick: Any) -> None:
    """``Streamer._prepare_tick`` without the bus: the tick's 0xF3 frames, encoded."""
    parts = [(s, s.last_targets) for s in tick.served if not s.feedback]
    frames = [broadcast_builder(p)() for p in broadcast_parts(parts)] if parts else []
    tick.prepared = [f.encode() for f in frames if f is not None]


def _bare_fire(self: Streamer) -> None:
    """``Streamer._fire`` for a steady tick, each frame written with ``os.write``:
    ``job.raw`` of a job ``Bus.prepare`` made (``bare_write``), or the bytes
    themselves (``bare_tick``).  Counted as ``_fire`` counts a tick written whole."""
    handback, tick = self._handback, self._armed
    self._armed = self._fire_handle = None
    if handback is None or handback.done() or tick is None:
        return
    fd = _port_fd(self)
    for ready in tick.prepared or ():
        os.write(fd, ready if type(ready) is bytes else ready.job.raw)
    record_sent(tick, self._timer.now(), False, 1)
    self._active = None
    self._fire_handle = self._timer.call_at(tick.deadline, self._advance)


@contextlib.contextmanager
def without(parts: tuple[str, ...]) -> Iterator[None]:
    """The bus with ``parts`` (``PARTS``, ``BARE``) doing nothing, until the block ends."""
    patches: list[tuple[type, str, Any]] = []
    if "bare_write" in parts or "bare_tick" in parts:
        patches.append((Streamer, "_fire", _bare_fire))
    if "bare_tick" in parts:
        patches.append((Streamer, "_prepare_tick", _bare_prepare))
    if "no_leases" in parts:
        patches += [(LeaseKeeper, "claim", _nothing), (LeaseTable, "moved", _nothing)]
    if "no_stats" in parts:
        patches += [(BusCore, "count_sent", _nothing), (BusCore, "accepted", _nothing)]
        patches.append((LatencyHistogram, "record", _nothing))
    if "direct_write" in parts:
        patches.append((BusEngine, "queue", _direct_queue(BusEngine.queue)))
    saved = [(cls, name, cls.__dict__[name]) for cls, name, _ in patches]
    try:
        for cls, name, value in patches:
            setattr(cls, name, value)
        yield
    finally:
        for cls, name, value in saved:
            setattr(cls, name, value)


def run_once(side: str, paths: list[str], seconds: float, polls: str) -> dict[str, Any]:
    if side == "timerfd":
        return bench_cpu.run_side("timerfd", paths, seconds, polls, None)
    parts = PARTS if side == "without_all" else tuple(p for p in PARTS + BARE if p == side)
    with without(parts):
        return bench_cpu.run_side("ours", paths, seconds, polls, None)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--buses", type=int, default=16)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--polls", choices=("none", "tick"), default="none")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.buses < 1 or args.seconds <= 0 or args.rounds < 1:
        parser.error("--buses and --rounds must be at least 1, --seconds above 0")
    bench_cpu.raise_fd_limit(args.buses)
    runs: dict[str, list[dict[str, Any]]] = {side: [] for side in SIDES}
    with tempfile.TemporaryDirectory() as tmp:
        responder = bench_cpu.Responder(args.buses, Path(tmp) / "recorded.json")
        try:
            for r in range(args.rounds):
                order = SIDES[r % len(SIDES) :] + SIDES[: r % len(SIDES)]
                for side in order:
                    runs[side].append(run_once(side, responder.paths, args.seconds, args.polls))
        finally:
            responder.stop()

    def cpu(side: str) -> float:  # the side's CPU over all its rounds' wall time
        done = runs[side]
        return float(100 * sum(x["cpu_s"] for x in done) / sum(x["wall_s"] for x in done))

    def paired(side: str, base: str) -> float:  # the median of the rounds' own ratios
        pairs = zip(runs[side], runs[base], strict=True)
        return float(statistics.median(x["cpu_percent"] / y["cpu_percent"] for x, y in pairs))

    rows = []
    for side in SIDES:
        ticks = [x["ticks"] for x in runs[side]]
        rows.append(
            {
                "side": side,
                "cpu_percent": round(cpu(side), 2),
                "over_ours": round(paired(side, "ours"), 3),
                "over_timerfd": round(paired(side, "timerfd"), 3),
                "round_cpu_percent": [round(x["cpu_percent"], 2) for x in runs[side]],
                "ticks_min": min(ticks),
            }
        )
    print(
        f"{args.buses} buses, polls: {args.polls}, {args.rounds} rounds of "
        f"{args.seconds:g} s a side"
    )
    print("| side | CPU | / ours | / (b) timerfd | each round's CPU | fewest ticks |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        each = ", ".join(f"{c:.1f}" for c in row["round_cpu_percent"])
        print(
            f"| {row['side']} | {row['cpu_percent']:.1f} % | {row['over_ours']:.2f} | "
            f"{row['over_timerfd']:.2f} | {each} | {row['ticks_min']} |"
        )
    write_report(
        args.out,
        {
            "buses": args.buses,
            "seconds": args.seconds,
            "rounds": args.rounds,
            "polls": args.polls,
            "rows": rows,
        },
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
