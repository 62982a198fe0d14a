"""``Bus.add_observer``: every write and every accepted reply, with the bus's own times."""

from __future__ import annotations

from typing import Any

import pytest

from motorbus.protocol import la
from motorbus.protocol.base import Command
from motorbus.sim.la import LAModel
from tests.bus.test_bus_memory import logged_sim_bus

pytestmark = pytest.mark.asyncio


class Recorder:
    def __init__(self) -> None:
        self.writes: list[tuple[Command[object], float]] = []
        self.replies: list[tuple[Command[object], Any, float, float]] = []

    def on_write(self, cmd: Command[object], at: float) -> None:
        self.writes.append((cmd, at))

    def on_reply(
        self, cmd: Command[object], value: Any, written_at: float, replied_at: float
    ) -> None:
        self.replies.append((cmd, value, written_at, replied_at))


async def test_observer_sees_writes_and_replies_with_ordered_times() -> None:
    async with logged_sim_bus([LAModel(1), LAModel(2)]) as (bus, _sim, trace):
        rec = Recorder()
        bus.add_observer(rec)
        query = la.Control(1, la.ControlAction.QUERY_STATUS)
        status = await bus.request(query)
        await bus.send(la.Broadcast(la.BroadcastMode.FOLLOW, ((2, 700),)))
        await bus.request(la.Control(2, la.ControlAction.QUERY_STATUS))
        bus.remove_observer(rec)
        await bus.request(query)
    assert [type(c).__name__ for c, _ in rec.writes] == ["Control", "Broadcast", "Control"]
    # The bus's own times: the completed write, after the moment the write began.
    starts = trace.tx_times[:3]
    ats = [at for _, at in rec.writes]
    assert all(s <= a for s, a in zip(starts, ats, strict=True))
    assert all(a < s for a, s in zip(ats, starts[1:], strict=False))
    assert len(rec.replies) == 2
    cmd, value, written_at, replied_at = rec.replies[0]
    assert cmd == query and value == status
    assert written_at == rec.writes[0][1] < replied_at <= rec.writes[1][1]


async def test_a_failing_observer_is_removed_and_the_bus_goes_on(
    caplog: pytest.LogCaptureFixture,
) -> None:
    class Broken(Recorder):
        def on_write(self, cmd: Command[object], at: float) -> None:
            raise RuntimeError("observer bug")

    async with logged_sim_bus([LAModel(1)]) as (bus, _sim, _trace):
        broken, good = Broken(), Recorder()
        bus.add_observer(broken)
        bus.add_observer(good)
        query = la.Control(1, la.ControlAction.QUERY_STATUS)
        # A long reply deadline: a worker stalled on a loaded machine (90 ms was seen)
        # must not add a retry's write to the two this test counts.
        await bus.request(query, timeout=2.0)
        await bus.request(query, timeout=2.0)
    assert "observer" in caplog.text and "removed" in caplog.text
    assert len(good.writes) == 2 and len(good.replies) == 2
    assert broken.replies == []
