"""What a served bus's frame feed (``capture --connect``) costs the bus, in one run.

    python benchmarks/bench_wire_tap.py [--requests 4000] [--rounds 5] [--out FILE]

The server taps its bus only while someone subscribes to ``motorbus/v1/bus/{bus}/frames``
(``motorbus.serve.tools_server``).  Measured here, in this process:

* the wire-tap call on the bus's path, per chunk: with no tap (the ``if`` every bus pays
  now) and with the frame feed's tap (one append), by ``timeit``;
* a status round trip on a bus over ``MemorySim`` (``pacing="prompt"``: no wire time, so
  the host's cost is all there is), p50 per request, without and with the feed tapping,
  in alternating rounds of ``--requests`` each (the same run, the same loop);
* the feed's publication work per chunk (``frames_batch`` and JSON, in batches of 40:
  20 ms of a 1 ms-spaced bus), which runs from a timer task, off the bus's path.

Prints a table and writes ``benchmarks/results/wire_tap.json``.
"""

from __future__ import annotations

import argparse
import asyncio
import platform
import statistics
import time
import timeit
from pathlib import Path

from harness import write_report
from motorbus import Bus, InspireLA
from motorbus.bus.engine import BusEngine
from motorbus.bus.timer import default_timer
from motorbus.protocol import la
from motorbus.serve import keys as k
from motorbus.serve.tools_server import FrameFeed, frames_batch
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "wire_tap.json"
QUERY = la.Control(1, la.ControlAction.QUERY_STATUS).encode()


class _NoPublisher:
    def put(self, payload: bytes) -> None:
        pass


def tap_call_ns(number: int) -> dict[str, float]:
    """ns per ``tap_wire`` decision: no tap (the check only), and the feed's tap."""
    bus = Bus.__new__(Bus)  # only the engine's tap list is used
    bus._engine = BusEngine.__new__(BusEngine)
    bus._engine.name = "bench"
    bus._engine.wire_taps = []
    empty = min(
        timeit.repeat(
            "bus._engine.wire_taps and bus._engine.tap_wire(True, raw, 1.0)",
            globals={"bus": bus, "raw": QUERY},
            number=number,
            repeat=5,
        )
    )
    feed = FrameFeed(bus, _NoPublisher())
    bus._engine.wire_taps = [feed.tap]
    bus.name = "bench"

    def one() -> None:
        if bus._engine.wire_taps:
            bus._engine.tap_wire(True, QUERY, 1.0)
        if len(feed.items) > 4096:
            feed.items.clear()

    tapped = min(timeit.repeat(one, number=number, repeat=5))
    return {"no_tap_ns": empty / number * 1e9, "feed_tap_ns": tapped / number * 1e9}


def publish_ns(batches: int) -> float:
    """ns per chunk to build and encode a batch of 40 chunks (off the bus's path)."""
    items = [(float(i), i % 2 == 0, QUERY) for i in range(40)]
    t = min(
        timeit.repeat(lambda: k.encode_json(frames_batch(1.0, items)), number=batches, repeat=5)
    )
    return t / (batches * len(items)) * 1e9


async def round_trips(requests: int, rounds: int) -> dict[str, list[float]]:
    """p50 status round trip (us) per round, alternating without and with the tap."""
    out: dict[str, list[float]] = {"without": [], "with": []}
    async with MemorySim.start(
        [LAModel(1)], baud=921600, timer=default_timer(), pacing="prompt"
    ) as sim:
        bus = Bus(sim.transport, name="bench", host_margin=0.05, reconnect=False)
        async with bus:
            feed = FrameFeed(bus, _NoPublisher())
            actuator = InspireLA(bus, 1)
            for _ in range(50):
                await actuator.status()  # warm up
            for _ in range(rounds):
                for label in ("without", "with"):
                    feed.set_active(label == "with")
                    times = []
                    for _ in range(requests):
                        t0 = time.perf_counter()
                        await actuator.status()
                        times.append(time.perf_counter() - t0)
                    feed.set_active(False)
                    out[label].append(statistics.median(times) * 1e6)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=4000)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args()
    calls = tap_call_ns(200_000)
    publish = publish_ns(2000)
    trips = asyncio.run(round_trips(args.requests, args.rounds))
    without, with_tap = statistics.median(trips["without"]), statistics.median(trips["with"])
    rows = [
        ("tap decision, no subscriber (per chunk)", f"{calls['no_tap_ns']:.0f} ns"),
        ("feed tap, subscribed (per chunk)", f"{calls['feed_tap_ns']:.0f} ns"),
        ("status round trip p50, no tap", f"{without:.1f} us"),
        ("status round trip p50, feed tapping", f"{with_tap:.1f} us"),
        ("publication work per chunk (off the path)", f"{publish:.0f} ns"),
    ]
    width = max(len(r[0]) for r in rows)
    for name, value in rows:
        print(f"{name:<{width}}  {value:>10}")
    report = {
        "benchmark": "wire_tap",
        "python": platform.python_version(),
        "requests": args.requests,
        "rounds": args.rounds,
        "tap_call_ns": calls,
        "publish_ns_per_chunk": publish,
        "round_trip_p50_us": {"without": trips["without"], "with": trips["with"]},
        "round_trip_p50_us_median": {"without": without, "with": with_tap},
    }
    write_report(args.out, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
