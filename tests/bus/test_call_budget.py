"""How many function calls one stream tick and one status request cost (issue 40).

Counted with ``sys.setprofile``: every Python call and every C call made while the
innermost code on the stack, apart from the standard library and motorbus's protocol
modules, is motorbus's own bus side (not its simulator, not the in-memory wire).  The
protocol counts for whoever calls it: the bus encoding a frame counts, the simulated
devices decoding it do not.  A call the bus makes into asyncio counts, and so does what
asyncio does for it; the event loop's own turn-taking and the test's fake clock do not.
A count is behaviour, not speed: it does not move with the machine, and a path that
grows back (another layer, a rebuilt frame, a spin on the clock) fails here.

Issue 40 asks for 150 each.  Before it, on this count: 315 calls a tick and 258 a
request on the fake clock; on the default timer ~1,100 and ~550 (the spin before each
precise deadline read the clock hundreds of times; it is off by default now).  After the
one send path and the pure core (BusCore): 204 a tick and 241 a request.  Then the
protocol's share: a broadcast's bytes from a list, not a generator (one call, not one a
byte: -46 a tick), a frame checked once on the bus's path (``decode_matched`` after
``matches_reply``; the checksum inline), families hashed in C: 149 a tick and 203 a
request on the fake clock, 189 and 232 on the default timer (timerfd re-arms).  Then
the timer's and the bus's small calls: the C clock itself where no spin needs noting
it, the queued re-arm one handle appended to asyncio's ready queue (not a ``call_soon``
and a Handle a re-arm, still once a loop turn), no hold or pump around a direct write,
the occupancy worked out once, comparisons for ``max``/``min``/``get``: 123 calls a
tick and 140 a request on the fake clock, 136 and 126-148 on the default timer (a
request that waits out the spacing takes a timer wake-up more than one that need not).
Then a tick's 0xF3 frames cut from each stream's pairs and their entries packed in C
(2026-12-07): 126 a tick (``starmap`` is a call) and 142 a request on the fake clock, 139
and 149 on the default timer.  Then the LA fast path's checksum asked of the rulebook
(``la_sum_ok``, the judge's) instead of a sum written a second time (2026-12-07): a
request 143 on the fake clock and 150 on the default timer.  Then a motion frame's
devices worked out once, at its lease claim, and reused by its write (2026-12-07): 122
a tick on the fake clock, 135 on the default timer.  Then a reply's deadline watched
by the loop's own timer until its last 2 ms (``Timer.call_at_lazily``: no timerfd
re-arming for a reply that comes before then, at six calls of asyncio's own), a Status
made by the tuple's constructor, and a timer wake-up that reads the clock again only
for a deadline not yet due by the last reading (2026-12-07): a request 141 on the fake
clock and 150 on the default timer (156 with the lazy deadline alone).  Then a tick
planned and sent from timer callbacks, without a turn of the streamer's task
(2026-12-07): 112 a tick on the fake clock; 119 once the planning waits, in a second
timer callback at the same deadline, for the writes of every bus due then; 113 with the
timer kept by the streamer and the next deadline found once a tick; 114 with one place
that serves a stream's targets (an ``isinstance`` for the awaited ones).  Then the
e-stop latch (2026-12-08): every answered command asks whether it sets or clears an
LA's latch (``safety.latch_change``), so that a safe action never lifts one: 143 a
request on the fake clock; 144 with the noting shared with an unanswered request's.
The fake clock's bounds are what the bus reaches now, with a small margin."""

from __future__ import annotations

import os
import sys
import sysconfig
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

import pytest

import motorbus
from motorbus.bus.timer import default_timer
from motorbus.devices.la import InspireLA
from motorbus.protocol import la
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim
from motorbus.streams import Streamer
from tests.fakeclock import rig
from tests.waiting import eventually

#: Calls of one 10 ms tick of 15 actuators (one 0xF3 broadcast), steady state.
TICK_BUDGET = 118
#: Calls of one ``bus.request`` of an LA status, from the call to its decoded reply.
REQUEST_BUDGET = 145
#: The same on the default timer with default settings: no spin on the clock (126 a
#: tick, 117-150 a request here, with the requests that wait out the spacing; ~1,100
#: and ~550 while it spun by default).  The fake clock's bounds above are the exact
#: guard of the path; real time moves these counts from run to run (a tick or request
#: that meets a timer wake-up more), so their bounds guard against the spin, with room
#: for a loaded machine, and the issue's 150 is the figure the test prints.
TIMER_TICK_BUDGET = 180
TIMER_REQUEST_BUDGET = 180

_PACKAGE = os.path.dirname(motorbus.__file__) + os.sep
_EXCLUDED = (
    os.path.join(_PACKAGE, "sim") + os.sep,
    os.path.join(_PACKAGE, "transport", "memory.py"),
)
#: Code that works for whoever calls it: the standard library, and motorbus's protocol
#: (which the simulated devices use too, to decode what the bus wrote).
_SHARED = (
    sysconfig.get_paths()["stdlib"] + os.sep,
    "<frozen ",
    os.path.join(_PACKAGE, "protocol") + os.sep,
)


def _owner(frame: FrameType | None) -> bool:
    """Whether the innermost frame from ``frame`` up that is not shared code (``_SHARED``)
    is motorbus's own: the bus side, not the simulator or the in-memory wire."""
    while frame is not None:
        name = frame.f_code.co_filename
        if not name.startswith(_SHARED):
            return name.startswith(_PACKAGE) and not name.startswith(_EXCLUDED)
        frame = frame.f_back
    return False


class CallCounter:
    """Counts the calls motorbus's code makes (see the module docstring)."""

    def __init__(self) -> None:
        self.calls = 0

    def _profile(self, frame: FrameType, event: str, arg: Any) -> None:
        if event in ("call", "c_call") and _owner(frame):
            self.calls += 1

    @contextmanager
    def counting(self) -> Iterator[None]:
        sys.setprofile(self._profile)
        try:
            yield
        finally:
            sys.setprofile(None)


def _rows(ticks: int) -> list[list[int]]:
    return [[1000 + (k * 7 + i) % 300 for i in range(15)] for k in range(ticks)]


async def _tick_calls(
    bus: motorbus.Bus,
    wait: Callable[[Callable[[], bool]], Any],
    ticks: int = 20,
    source: Any = None,
) -> float:
    actuators = [InspireLA(bus, i) for i in range(1, 16)]
    streamer = Streamer(bus)
    # Rows for far more ticks than are counted: ticks a loaded machine skips use rows up,
    # and a stream that ran out of rows before ``ticks`` were sent would never get there.
    stream = streamer.follow(
        actuators, _rows(ticks * 50) if source is None else source, period=0.01
    )
    await wait(lambda: stream.stats.ticks >= 5)
    counter = CallCounter()
    with counter.counting():
        first = stream.stats.ticks
        await wait(lambda: stream.stats.ticks >= first + ticks)
        done = stream.stats.ticks - first
    await streamer.close(hold=True)
    assert bus.stats.no_reply_frames >= done  # one broadcast a tick
    return counter.calls / done


async def _request_calls(bus: motorbus.Bus, n: int = 20) -> float:
    query = [la.Control(1 + k % 15, la.ControlAction.QUERY_STATUS) for k in range(n + 1)]
    await bus.request(query[0])  # warm: the first of a kind fills caches
    counter = CallCounter()
    with counter.counting():
        for cmd in query[1:]:
            await bus.request(cmd)
    return counter.calls / n


async def test_a_stream_tick_and_a_request_on_the_fake_clock_stay_within_budget() -> None:
    # Fake time: deterministic, the same count on every machine.
    async with rig() as r:

        async def wait(cond: Callable[[], bool]) -> None:
            # Polled in real time (the fake clock jumps meanwhile), and bounded.
            await eventually(cond, "the stream's ticks", poll=0.0005, timeout=30)

        per_tick = await _tick_calls(r.bus, wait)
        per_request = await _request_calls(r.bus)
    print(f"fake clock: {per_tick:.0f} calls a tick, {per_request:.0f} a request")
    assert per_tick <= TICK_BUDGET, per_tick
    assert per_request <= REQUEST_BUDGET, per_request


async def test_a_tick_from_a_target_function_stays_within_the_same_budget() -> None:
    # Most programs stream from a function f(t, statuses), not a list of rows: its plain
    # list is used as it is (an awaitable check on it cost six calls a tick: 129).
    async with rig() as r:

        async def wait(cond: Callable[[], bool]) -> None:
            await eventually(cond, "the stream's ticks", poll=0.0005, timeout=30)

        def targets(t: float, statuses: object) -> list[int]:
            return [1000 + (round(t * 100) * 7 + i) % 300 for i in range(15)]

        per_tick = await _tick_calls(r.bus, wait, source=targets)
    print(f"fake clock, a target function: {per_tick:.0f} calls a tick")
    assert per_tick <= TICK_BUDGET, per_tick


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the default timer there")
async def test_the_default_timer_adds_no_spin_to_a_tick_or_a_request() -> None:
    # The real default timer (timerfd) with default settings: a spin on the clock before
    # each deadline would add hundreds of clock reads to each tick and request.
    timer = default_timer()
    models = [LAModel(i) for i in range(1, 16)]
    sim_start = MemorySim.start(models, timer=timer)  # type: ignore[arg-type]
    async with sim_start as sim, motorbus.Bus(sim.transport, families=[motorbus.Family.LA]) as bus:

        async def wait(cond: Callable[[], bool]) -> None:
            await eventually(cond, "the stream's ticks", poll=0.005, timeout=30)

        per_tick = await _tick_calls(bus, wait)
        per_request = await _request_calls(bus)
    print(f"default timer: {per_tick:.0f} calls a tick, {per_request:.0f} a request")
    assert per_tick <= TIMER_TICK_BUDGET, per_tick
    assert per_request <= TIMER_REQUEST_BUDGET, per_request
