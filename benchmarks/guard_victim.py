"""A program to kill: streams follow targets to LA actuators until it is killed.

Used by ``bench_guard.py`` and ``tests/guard/test_guard.py``::

    python benchmarks/guard_victim.py --port /dev/pts/5 --port /dev/pts/6 --ids 1-3 --guard

It enables the actuators, streams a slow ramp to each at 100 Hz with
``safe_action="pause"``, and prints ``streaming`` once every bus has sent targets; then
it streams on until it is killed.  With ``--guard`` it runs under
``motorbus.run(..., guard=True)``: the stream's lease tells the guard what to pause.
"""

from __future__ import annotations

import argparse
import asyncio
import sys

import motorbus
from motorbus.protocol import la
from motorbus.protocol.ids import parse_id_list

BAUD = 921600
PERIOD_S = 0.01
HOST_MARGIN_S = 0.05


async def one_bus(port: str, ids: list[int], started: asyncio.Event) -> None:
    transport = motorbus.open_transport(port, baudrate=BAUD)
    # A generous reply margin: this machine may be loaded, and a timed-out "work" would
    # end the program before there is anything to kill.
    async with motorbus.Bus(
        transport, families=[motorbus.Family.LA], host_margin=HOST_MARGIN_S
    ) as bus:
        actuators = [motorbus.InspireLA(bus, i) for i in ids]
        for a in actuators:
            await a.enable()

        def targets(t: float, statuses: dict[int, la.Status]) -> list[float]:
            if t > 0.05:
                started.set()
            return [100 + (50 * t + 10 * n) % 1500 for n in range(len(ids))]

        streamer = motorbus.Streamer(bus)
        async with streamer.follow(
            actuators, targets, period=PERIOD_S, safe_action="pause"
        ) as stream:
            await stream.wait()


async def main(ports: list[str], ids: list[int]) -> None:
    events = [asyncio.Event() for _ in ports]
    tasks = [asyncio.create_task(one_bus(p, ids, e)) for p, e in zip(ports, events, strict=True)]
    waits = [asyncio.create_task(e.wait()) for e in events]
    pending: set[asyncio.Task[object]] = {*tasks, *waits}
    while not all(e.is_set() for e in events):
        done, pending = await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
        for task in done & set(tasks):
            task.result()  # a bus that failed (a silent actuator...) ends the program
            raise RuntimeError("a stream ended before it was killed")
    print("streaming", flush=True)
    await asyncio.gather(*tasks)


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--port", action="append", required=True)
    p.add_argument("--ids", default="1-3")
    p.add_argument("--guard", action="store_true")
    args = p.parse_args()
    id_list = list(parse_id_list(args.ids))
    motorbus.run(main(args.port, id_list), guard=args.guard)
    sys.exit(0)
