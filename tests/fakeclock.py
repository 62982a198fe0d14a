"""A fake clock for deterministic timing tests: time moves only when the loop is idle.

``AutojumpTimer`` is a :class:`motorbus.bus.timer.Timer` whose ``now()`` is a number the
test controls.  While the event loop has work to do, time stands still; when nothing is
runnable, the clock jumps to the earliest scheduled deadline and its callbacks run
(trio's "autojump clock").  The bus, the streamer and ``MemorySim`` all take the timer, so
a whole bus with its simulated devices runs in fake time, the same way on a loaded CI
machine as on an idle one: rules such as ">= 1 ms between writes" can then be asserted
exactly, and no test depends on the machine's speed.

``TimedTransport`` wraps a transport and records the fake-clock time before and after
each write, and can make a write "take" time (a preempted process), which is exactly what
the spacing rule must survive.
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import random
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass, field

from motorbus.bus.bus import Bus
from motorbus.bus.timer import Timer
from motorbus.sim.bus import LogRecord, Pacing
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim
from motorbus.sim.model import DeviceModel
from motorbus.transport.base import DataCallback, LostCallback, Transport

#: Loop turns in a row with nothing runnable before the clock jumps.
IDLE_TURNS = 3


class AutojumpTimer(Timer):
    """A :class:`Timer` on a fake clock that jumps to the next deadline when idle.

    Use ``async with AutojumpTimer.running() as timer:``; time starts at ``start``.
    """

    name = "fake"

    def __init__(self, loop: asyncio.AbstractEventLoop, start: float = 1000.0) -> None:
        super().__init__(loop)
        self.t = start
        self._task: asyncio.Task[None] | None = None

    def now(self) -> float:
        return self.t

    def advance(self, seconds: float) -> None:
        """Move the clock forward without running callbacks (a write that takes time)."""
        self.t += seconds

    def _arm(self, deadline: float) -> None:
        pass  # the autojump task wakes the timer

    def _disarm(self) -> None:
        pass

    def _release(self) -> None:
        pass

    def start(self) -> None:
        self._task = self.loop.create_task(self._autojump(), name="autojump clock")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        self.close()

    async def _autojump(self) -> None:
        loop = self.loop
        while True:
            idle = 0
            while idle < IDLE_TURNS:
                await asyncio.sleep(0)
                # CPython's loop keeps its runnable callbacks in ``_ready``: empty means
                # nothing but this task wants to run (the links are in memory: no I/O).
                idle = idle + 1 if not loop._ready else 0  # type: ignore[attr-defined]
            heap = self._heap
            while heap and heap[0][2].cancelled():
                heapq.heappop(heap)
                self._cancelled_in_heap -= 1
            if not heap:
                await asyncio.sleep(0.001)  # nothing scheduled: let real time pass
                continue
            self.t = max(self.t, heap[0][0])
            self._wake()


@dataclass
class WriteRecord:
    """One write as the fake clock saw it."""

    before: float
    after: float
    data: bytes


@dataclass
class TimedTransport(Transport):
    """Wraps ``inner``; records each write and makes it take ``write_time()`` seconds."""

    inner: Transport
    timer: AutojumpTimer
    write_time: Callable[[], float] = lambda: 0.0
    writes: list[WriteRecord] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.url = self.inner.url
        self.baudrate = self.inner.baudrate
        self.stats = self.inner.stats

    async def open(self, on_data: DataCallback, on_lost: LostCallback) -> None:
        await self.inner.open(on_data, on_lost)

    def write(self, data: bytes) -> None:
        before = self.timer.now()
        self.timer.advance(self.write_time())
        self.inner.write(data)
        self.writes.append(WriteRecord(before, self.timer.now(), bytes(data)))

    def drain_input(self) -> None:
        self.inner.drain_input()

    async def close(self) -> None:
        await self.inner.close()

    @property
    def is_open(self) -> bool:
        return self.inner.is_open


def preempted_writes(seed: int, worst: float = 400e-6) -> Callable[[], float]:
    """Write durations of a busy host: mostly quick, sometimes preempted for ``worst``."""
    rng = random.Random(seed)

    def duration() -> float:
        return worst * rng.random() if rng.random() < 0.3 else 20e-6

    return duration


@dataclass
class Rig:
    """A bus on the fake clock, its simulated devices, the timed wire and the sim's log."""

    bus: Bus
    sim: MemorySim
    timer: AutojumpTimer
    wire: TimedTransport
    log: list[LogRecord]


@contextlib.asynccontextmanager
async def rig(
    ids: range = range(1, 16),
    *,
    models: Sequence[DeviceModel] | None = None,
    write_time: Callable[[], float] = lambda: 20e-6,
    turnaround: float = 120e-6,
    pacing: Pacing = "wire",
    **bus_options: object,
) -> AsyncIterator[Rig]:
    """A bus in fake time talking to LA models (IDs ``ids``) or ``models`` in memory."""
    loop = asyncio.get_running_loop()
    timer = AutojumpTimer(loop)
    timer.start()
    records: list[LogRecord] = []
    if models is None:
        models = [LAModel(i, turnaround_typical=turnaround, turnaround_max=turnaround) for i in ids]
    try:
        async with MemorySim.start(models, timer=timer, log=records.append, pacing=pacing) as sim:
            wire = TimedTransport(sim.transport, timer, write_time)
            bus_options.setdefault("host_margin", 2e-3)
            families = {m.family for m in models}
            bus = Bus(wire, name="fake", families=families, timer=timer, **bus_options)  # type: ignore[arg-type]
            async with bus:
                yield Rig(bus, sim, timer, wire, records)
    finally:
        await timer.stop()
