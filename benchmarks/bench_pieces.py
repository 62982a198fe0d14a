"""What the pieces of a bus-tick cost, one at a time: where a CPU saving could come from.

``bench_cpu.py`` says how far motorbus's CPU per bus-tick is from a minimal loop, and
``profile_tick.py`` where a profiled tick spends it.  A profiler inflates small calls and
a sampler on a two-core machine sees few samples; this times each piece of the hot path
alone, in a tight loop (``timeit``, the best of ``--repeat`` runs: the least a piece
costs on this machine, not what it costs inside a busy tick):

* ``timerfd_settime`` armed for a deadline 200 us ahead (the kind the bus arms: it becomes
  the CPU's earliest timer, and a VM reprograms its timer for it), 1 s ahead, and
  disarmed;
* ``Timer.call_at`` of a status poll's reply deadline and its ``cancel`` a loop turn
  later (what every reply deadline costs when its reply comes: two re-arms, one after
  each turn);
* ``Bus.prepare`` of a stream tick's 15-entry 0xF3 broadcast (checks, lease rule,
  encoding, the job and its future), and the encoding alone;
* ``LeaseTable.moved`` for that broadcast (what each written motion frame owes);
* a 22-byte status reply through the reassembler, and its match and decoding;
* the baseline: one asyncio future resolved by a ``call_soon`` callback and awaited,
  the least a request/reply round trip can cost in asyncio.

Prints a table and writes ``benchmarks/results/pieces.json``.

    python benchmarks/bench_pieces.py [--number 20000] [--repeat 5] [--out PATH]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time
import timeit
from collections.abc import Callable
from pathlib import Path
from typing import Any

from motorbus.bus.bus import Bus, Priority
from motorbus.bus.timer import Timer, default_timer, timerfd_available
from motorbus.protocol import la
from motorbus.protocol.base import Family
from motorbus.protocol.reassembler import Reassembler
from motorbus.transport.memory import memory_pair

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "pieces.json"
sys.path.insert(0, str(HERE))

from harness import write_report  # noqa: E402

N_ACTUATORS = 15
NEAR_S = 200e-6


def best_us(call: Callable[[], object], number: int, repeat: int) -> float:
    """The least time one ``call()`` took, in microseconds (best of ``repeat`` loops)."""
    return 1e6 * min(timeit.repeat(call, number=number, repeat=repeat)) / number


def broadcasts(count: int) -> list[la.Broadcast]:
    """``count`` distinct 15-entry follow broadcasts, as a stream builds them."""
    return [
        la.Broadcast.prevalidated(
            la.BroadcastMode.FOLLOW,
            tuple((i, (7 * k + 13 * i) % 2001) for i in range(1, N_ACTUATORS + 1)),
        )
        for k in range(count)
    ]


def timerfd_pieces(number: int, repeat: int) -> dict[str, float]:
    """``timerfd_settime`` near, far and disarming (empty where there is no timerfd)."""
    if not timerfd_available():
        return {}
    from motorbus.bus import timerfd

    api = timerfd.api()  # the bus's own settime path (os or ctypes)
    fd = api.create()
    flip = [0]

    def armed(ahead: float) -> Callable[[], None]:
        def arm() -> None:
            flip[0] ^= 1  # a new value each call: the kernel has work to do each time
            api.set_absolute_ns(fd, round((time.monotonic() + ahead) * 1e9) + flip[0])

        return arm

    try:
        return {
            "settime_near_us": best_us(armed(NEAR_S), number, repeat),
            "settime_far_us": best_us(armed(1.0), number, repeat),
            "settime_disarm_us": best_us(lambda: api.set_absolute_ns(fd, 0), number, repeat),
        }
    finally:
        os.close(fd)


async def bus_pieces(number: int, repeat: int) -> dict[str, float]:
    """The bus's pieces, on a bus over an in-memory link nobody answers."""
    host, _peer = memory_pair(baudrate=921600)
    bus = Bus(host, name="pieces", families=[Family.LA])
    out: dict[str, float] = {}
    async with bus:
        timer = bus.timer
        keys = [f"la:{i}" for i in range(1, N_ACTUATORS + 1)]
        lease = bus.lease(keys, owner="bench", bind=False)
        frames = iter(broadcasts(number * repeat))

        def prepare() -> None:
            bus.prepare(next(frames), priority=Priority.HIGH, reserved=True, lease=lease)

        out["prepare_broadcast_us"] = best_us(prepare, number, repeat)
        unencoded = iter(broadcasts(number * repeat))
        out["encode_broadcast_us"] = best_us(lambda: next(unencoded).encode(), number, repeat)
        frame = broadcasts(1)[0]
        table = bus._lease_keeper.table  # the bus's lease table (what _transmit feeds)
        out["leases_moved_us"] = best_us(lambda: table.moved(frame), number, repeat)

        # The deadline a status poll gets on this bus (the bus owns the budget).  Beyond
        # the timer's spin lead: a nearer one would wake the loop to spin instead.
        query = la.control_frame(1, la.ControlAction.QUERY_STATUS)
        poll_budget = bus.reply_budget(query)
        out["reply_deadline_ahead_ms"] = 1e3 * poll_budget
        out["timer_call_at_cancel_us"] = await reply_deadline_us(timer, poll_budget, number, repeat)
        reply = la.encode_status(1, target=1000, position=998)
        reassembler = Reassembler(families=frozenset([Family.LA]))

        def read_reply() -> None:
            for item in reassembler.feed(reply):
                if query.matches_reply(item.raw):
                    query.decode_reply(item.raw)

        out["reply_feed_match_decode_us"] = best_us(read_reply, number, repeat)
        # Nothing was written, and nobody would answer the safe stops ``moved`` made
        # owed: let the actuators go as they are.
        await lease.release(hold=True)
    return out


def _nothing() -> None:
    pass


async def reply_deadline_us(timer: Timer, ahead: float, number: int, repeat: int) -> float:
    """A reply deadline as a bus arms it (us): ``call_at`` in one loop turn and
    ``cancel`` (its reply came) in a later one, the timer's re-arm after each turn
    included, less the same two loop turns without it (best of ``repeat`` loops each)."""

    async def turns(arm: bool) -> float:
        best = float("inf")
        for _ in range(repeat):
            start = time.perf_counter()
            for _ in range(number):
                handle = timer.call_at(timer.now() + ahead, _nothing) if arm else None
                await asyncio.sleep(0)
                if handle is not None:
                    handle.cancel()
                await asyncio.sleep(0)
            best = min(best, time.perf_counter() - start)
        return best

    return 1e6 * (await turns(True) - await turns(False)) / number


async def future_round_trip(number: int, repeat: int) -> float:
    """The baseline: create a future, resolve it from a callback, await it (us)."""
    loop = asyncio.get_running_loop()
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        for _ in range(number):
            future = loop.create_future()
            loop.call_soon(future.set_result, None)
            await future
        best = min(best, time.perf_counter() - start)
    return 1e6 * best / number


async def measure(number: int, repeat: int) -> dict[str, Any]:
    figures: dict[str, Any] = timerfd_pieces(number, repeat)
    figures.update(await bus_pieces(number, repeat))
    figures["future_round_trip_us"] = await future_round_trip(number, repeat)
    figures["timer"] = type(default_timer()).__name__
    return figures


LABELS = {
    "settime_near_us": "timerfd_settime, 200 us ahead (reprograms the CPU's timer)",
    "settime_far_us": "timerfd_settime, 1 s ahead",
    "settime_disarm_us": "timerfd_settime, disarm",
    "timer_call_at_cancel_us": "Timer.call_at a poll's deadline ahead, cancel next turn",
    "prepare_broadcast_us": "Bus.prepare, 15-entry 0xF3 broadcast",
    "encode_broadcast_us": "  of which: encoding it",
    "leases_moved_us": "LeaseTable.moved, that broadcast",
    "reply_feed_match_decode_us": "status reply: reassemble, match, decode",
    "future_round_trip_us": "baseline: asyncio future round trip",
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--number", type=int, default=20000, help="calls per timed loop")
    parser.add_argument("--repeat", type=int, default=5, help="timed loops (best kept)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.number < 1 or args.repeat < 1:
        parser.error(f"--number and --repeat must be >= 1, got {args.number}, {args.repeat}")
    figures = asyncio.run(measure(args.number, args.repeat))
    print(f"the pieces of a bus-tick, best of {args.repeat} loops of {args.number} calls")
    for key, label in LABELS.items():
        if key in figures:
            print(f"  {label:62s} {figures[key]:7.2f} us")
    write_report(args.out, {**figures, "number": args.number, "repeat": args.repeat})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
