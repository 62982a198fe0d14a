"""The path of a tick (issue 40): planned without awaiting, sent by the timer callback.

A tick of plain target sources (a list, an iterator, a function) is planned, written at
its deadline and counted from the timer callback of the tick before it, without a turn
of the streamer's task; whatever must be awaited (an async source, a gap, an end) goes
back to the task, before the tick it belongs to is sent.  On the fake clock.
"""

from __future__ import annotations

import asyncio
import contextvars
import inspect
from collections.abc import AsyncIterator
from typing import Any

import pytest

from motorbus.bus.bus import Bus
from motorbus.devices.la import InspireLA
from motorbus.protocol import la
from motorbus.protocol.base import Family
from motorbus.sim.la import LAModel, PowerState
from motorbus.sim.memory import MemorySim
from motorbus.streaming.model import StreamStats
from motorbus.streaming.targets import Pending, TargetAdapter
from motorbus.streaming.tick import AWAIT, ENDED, FAILED, GAP, Tick, abandon, plan_tick
from motorbus.streams import StreamEnded, Streamer
from tests.fakeclock import rig
from tests.waiting import eventually

TICKS = 30


def _follow_targets(model: LAModel) -> list[int]:
    return [t for _, cmd, t in model.received if cmd == la.CMD_BROADCAST_FOLLOW]


async def test_a_steady_stream_takes_no_task_turn_a_tick(monkeypatch: pytest.MonkeyPatch) -> None:
    turns = [0]
    real = Streamer._serve_tick

    async def counted(self: Streamer, tick: Any) -> Any:
        turns[0] += 1
        return await real(self, tick)

    monkeypatch.setattr(Streamer, "_serve_tick", counted)
    models = [LAModel(i) for i in range(1, 16)]
    rows = [[100 + 10 * k + i for i in range(15)] for k in range(TICKS)]
    async with rig(models=models) as r:
        streamer = Streamer(r.bus)
        stream = streamer.follow(
            [InspireLA(r.bus, i) for i in range(1, 16)], rows, period=0.01, safe_action="pause"
        )
        await asyncio.wait_for(stream.wait(), 5)
        await streamer.close()
    # The task served the first tick, the timer callback every other; the tick after the
    # last row went back to the task, which ended the stream (its safe action) and had
    # nothing left to send.  Before the one path: a task turn a tick.
    assert turns[0] == 2, turns
    assert stream.stats.ticks == TICKS and stream.stats.slipped == stream.stats.late == 0
    for i, model in enumerate(models):
        assert _follow_targets(model) == [row[i] for row in rows]
        assert model.power_state is PowerState.PAUSED


async def _agen(values: list[int]) -> AsyncIterator[int]:
    for v in values:
        await asyncio.sleep(0)
        yield v


def _sources(values: list[int]) -> dict[str, Any]:
    """One source of ``values`` (one a tick, then the end) of each kind that is awaited."""
    it = iter(values)

    async def coroutine_function(t: float, statuses: object) -> int | None:
        await asyncio.sleep(0)
        return next(it, None)

    def returns_a_future(t: float, statuses: object) -> asyncio.Future[int | None]:
        future: asyncio.Future[int | None] = asyncio.get_running_loop().create_future()
        future.set_result(next(it, None))
        return future

    return {
        "async-iterator": _agen(values),
        "coroutine-function": coroutine_function,
        "function-returning-a-future": returns_a_future,
    }


@pytest.mark.parametrize(
    "kind", ["async-iterator", "coroutine-function", "function-returning-a-future"]
)
async def test_awaited_sources_share_a_frame_with_plain_ones(kind: str) -> None:
    # An awaited source is served by the task, before its tick is sent: its targets go
    # out in the same 0xF3 frame as those of a plain stream due then, every tick.
    awaited = [300 + k for k in range(TICKS)]
    plain = [[900 + k] for k in range(TICKS)]
    models = [LAModel(1), LAModel(2)]
    async with rig(models=models) as r:
        streamer = Streamer(r.bus)
        first = streamer.follow(InspireLA(r.bus, 1), _sources(awaited)[kind], period=0.01)
        second = streamer.follow(InspireLA(r.bus, 2), plain, period=0.01)
        await asyncio.wait_for(asyncio.gather(first.wait(), second.wait()), 5)
        await streamer.close()
    assert _follow_targets(models[0]) == awaited
    assert _follow_targets(models[1]) == [row[0] for row in plain]
    assert first.stats.ticks == second.stats.ticks == TICKS
    assert r.bus.stats.no_reply_frames == TICKS  # one frame a tick for both


async def test_a_plain_stream_started_beside_a_running_one_joins_its_frames() -> None:
    # A stream started while the timer callback serves another is picked up by it.
    models = [LAModel(1), LAModel(2)]
    async with rig(models=models) as r:
        streamer = Streamer(r.bus)
        first = streamer.follow(InspireLA(r.bus, 1), lambda t, s: 500, period=0.01)
        await eventually(lambda: first.stats.ticks >= 5, "5 ticks", poll=0.0005, timeout=30)
        second = streamer.follow(InspireLA(r.bus, 2), [600 + k for k in range(10)], period=0.01)
        await asyncio.wait_for(second.wait(), 5)
        await streamer.close()
    assert _follow_targets(models[1]) == [600 + k for k in range(10)]
    assert first.stats.ticks >= 15 and first.stats.slipped == 0


# -- the planner alone (pure) ------------------------------------------------------------


class _Stream:
    """What ``plan_tick`` reads of a stream."""

    def __init__(self, source: Any, *, ids: tuple[int, ...] = (1,)) -> None:
        self.ids = ids
        self.source = TargetAdapter(ids, source)
        self.origin, self.period, self.next_tick, self.index_base = 0.0, 0.01, 0, 0
        self.sending, self.feedback, self.poll_status = True, False, False
        self.disconnects_seen = 0
        self.stats = StreamStats()
        self.statuses: dict[int, Any] = {}
        self.last_targets: dict[int, int] = {}
        self.ramp: dict[int, float] | None = None
        self.max_speed = 500.0
        self.skipped_mark = 0


def test_the_planner_leaves_what_must_be_awaited_to_the_task() -> None:
    def fails(t: float, statuses: object) -> int:
        raise RuntimeError("sensor gone")

    async def later(t: float, statuses: object) -> int:
        return 5

    plain, ended, failed, pending = (
        _Stream([700, 710]),
        _Stream([]),
        _Stream(fails),
        _Stream(later),
    )
    behind, outage = _Stream([1, 2, 3, 4, 5]), _Stream([1])
    outage.disconnects_seen = -1
    streams: list[Any] = [plain, ended, failed, pending, behind, outage]
    behind.origin = -0.035  # three and a half ticks behind at deadline 0
    tick = plan_tick(streams, 0.0, 0.0, bus_up=True, disconnects=0)
    assert tick.served == [plain] and plain.last_targets == {1: 700}  # type: ignore[comparison-overlap]
    kinds = {id(s): (kind, value) for s, kind, value in tick.later}
    assert kinds[id(ended)] == (ENDED, None)
    assert kinds[id(failed)][0] == FAILED and str(kinds[id(failed)][1]) == "sensor gone"
    assert kinds[id(pending)][0] == AWAIT and type(kinds[id(pending)][1]) is Pending
    assert kinds[id(behind)] == (GAP, "behind") and behind.next_tick == 4
    assert kinds[id(outage)] == (GAP, "outage")
    abandon(tick)  # the task never awaits it: closed, no "never awaited" warning
    assert tick.later == []
    assert inspect.getcoroutinestate(kinds[id(pending)][1].awaitable) == inspect.CORO_CLOSED


def test_the_planner_skips_the_slots_past_and_runs_the_grid_on_while_the_bus_is_down() -> None:
    s: Any = _Stream([10, 20, 30, 40, 50, 60])
    tick = plan_tick([s], 0.0, 0.025, bus_up=True, disconnects=0)  # two slots past
    assert s.stats.skipped == 2 and s.last_targets == {1: 30} and s.next_tick == 3
    nothing = plan_tick([s], 0.03, 0.03, bus_up=False, disconnects=0)
    assert nothing.served == [] and nothing.later == [] and s.next_tick == 4
    assert s.stats.skipped == 3
    assert isinstance(tick, Tick)


async def test_every_bus_due_writes_before_any_plans_its_next_tick() -> None:
    # Buses of one phase group share a timer and a deadline: each one's tick callback
    # writes, and the planning of the next tick (targets, frames) waits until every
    # bus due then has written; else it would make the later buses' writes late.
    events: list[tuple[str, str, float]] = []
    async with (
        rig(models=[LAModel(1)]) as r,
        MemorySim.start([LAModel(1)], timer=r.timer) as sim,
        Bus(sim.transport, name="second", families={Family.LA}, timer=r.timer) as second,
    ):
        buses = [r.bus, second]
        for bus in buses:
            prepare, send = bus.prepare, bus.send_prepared

            def prepared(*args: Any, b: Bus = bus, real: Any = prepare, **kw: Any) -> Any:
                events.append(("prepare", b.name, r.timer.now()))
                return real(*args, **kw)

            def sent(ready: Any, b: Bus = bus, real: Any = send) -> Any:
                events.append(("send", b.name, r.timer.now()))
                return real(ready)

            bus.prepare = prepared  # type: ignore[method-assign]
            bus.send_prepared = sent  # type: ignore[method-assign,assignment]
        streamers = [Streamer(b) for b in buses]
        streams = [
            s.follow(InspireLA(b, 1), [700 + k for k in range(10)], period=0.01)
            for s, b in zip(streamers, buses, strict=True)
        ]
        await asyncio.wait_for(asyncio.gather(*(s.wait() for s in streams)), 5)
        for s in streamers:
            await s.close()
    # The sends of one deadline (the first bus's write takes 20 us of the fake clock),
    # and what came between them.
    sends = [i for i, (kind, _, _) in enumerate(events) if kind == "send"]
    groups = [sends[i : i + 2] for i in range(0, len(sends), 2)]
    assert len(groups) == 10, events
    for first, last in groups:
        assert events[last][2] - events[first][2] < 1e-3, events  # one deadline
        between = [kind for kind, _, _ in events[first:last]]
        assert "prepare" not in between, events[first : last + 1]


async def test_a_target_function_raising_stop_async_iteration_fails_its_stream() -> None:
    # An async iterator's StopAsyncIteration is its end; a target function's is an error
    # (as any other exception it raises): the stream ends with it, and its safe action.
    async def targets(t: float, statuses: object) -> int:
        if t >= 0.03:
            raise StopAsyncIteration
        return 800

    model = LAModel(1)
    async with rig(models=[model]) as r:
        streamer = Streamer(r.bus)
        stream = streamer.follow(InspireLA(r.bus, 1), targets, period=0.01, safe_action="pause")
        with pytest.raises(StreamEnded):
            await asyncio.wait_for(stream.wait(), 5)
        await streamer.close()
    assert type(stream.error) is StopAsyncIteration
    assert _follow_targets(model) == [800, 800, 800]
    assert model.power_state is PowerState.PAUSED


REQUEST_ID: contextvars.ContextVar[str] = contextvars.ContextVar("request_id", default="unset")


async def test_a_target_function_sees_the_context_it_was_started_in_on_every_path() -> None:
    """As in a task: a target function reads the context variables set where its stream
    was started, on the ticks the timer callback plans and on those the task does (the
    first, and the one after a source that must be awaited)."""
    seen: list[str] = []

    def target(t: float, _status: object) -> list[int] | None:
        seen.append(REQUEST_ID.get())
        return None if len(seen) > TICKS else [500 + len(seen)]

    async with rig(models=[LAModel(1)]) as r:
        token = REQUEST_ID.set("arm-7")
        try:
            streamer = Streamer(r.bus)
            stream = streamer.follow([InspireLA(r.bus, 1)], target, period=0.01)
        finally:
            REQUEST_ID.reset(token)
        await asyncio.wait_for(stream.wait(), 5)
        await streamer.close()
    assert len(seen) == TICKS + 1 and set(seen) == {"arm-7"}, seen


async def test_a_paused_stream_reserves_no_window_on_the_bus() -> None:
    """The window the streamer asks the bus to keep free (its reservation source) is the
    next tick of a stream that sends: a paused one needs no slot, so user requests are
    not held for it."""
    async with rig(models=[LAModel(1), LAModel(2)]) as r:
        streamer = Streamer(r.bus)
        fast = streamer.follow([InspireLA(r.bus, 1)], lambda t, s: 500, period=0.01)
        slow = streamer.follow([InspireLA(r.bus, 2)], lambda t, s: 600, period=0.05)
        await eventually(lambda: fast.stats.ticks >= 3, "three ticks")
        now = r.bus.timer.now()
        assert streamer._reservation(now) is not None
        fast.pause()
        window = streamer._reservation(now + 0.02)  # past the tick in progress, if any
        assert window is not None and window[0] == slow.origin + slow.next_tick * slow.period
        slow.pause()
        assert streamer._reservation(now + 0.06) is None
        await streamer.close()
