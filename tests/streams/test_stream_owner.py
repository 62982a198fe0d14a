"""A stream owns its actuators: no one else moves them while it runs, and its end lets
them go as it says (safe action, hold, or hand-over to the bus until close)."""

from __future__ import annotations

import asyncio

import pytest

from motorbus import InspireLA, Streamer
from motorbus.errors import LeaseConflictError, LocalProtocolError
from motorbus.sim.la import LAModel, PowerState
from tests.helpers import sim_bus
from tests.waiting import eventually

pytestmark = pytest.mark.asyncio


async def test_another_owner_is_refused_while_a_stream_runs() -> None:
    # A lease another part of the program holds (not this task: bind=False) refuses
    # the stream at follow(); a lease this task holds would be the stream's
    # (test_stream_under_lease.py).
    async with sim_bus([LAModel(1)], pacing="prompt") as (bus, _sim):
        mine = bus.lease(["la:1"], owner="rig", bind=False)
        with pytest.raises(LeaseConflictError, match="la:1 is leased by 'rig'"):
            Streamer(bus).follow(InspireLA(bus, 1), lambda t, s: 900, period=0.01)
        await mine.release(hold=True)

    async with sim_bus([LAModel(1), LAModel(2)], pacing="prompt") as (bus, _sim):
        stream = Streamer(bus).follow(
            InspireLA(bus, 1), lambda t, s: 900, period=0.01, safe_action="pause"
        )
        await eventually(lambda: stream.stats.ticks >= 3, "three ticks")
        with pytest.raises(LeaseConflictError, match="la:1 is leased by 'stream on"):
            await InspireLA(bus, 1).move_to(200)
        with pytest.raises(LeaseConflictError):
            bus.lease(["la:1"], owner="rig")
        with pytest.raises(LocalProtocolError, match="already streamed"):
            Streamer(bus).follow(InspireLA(bus, 1), lambda t, s: 100, period=0.01)
        await InspireLA(bus, 2).move_to(200)  # not the stream's: free
        await stream.stop()
        await InspireLA(bus, 1).move_to(300)  # the stream ended: free again


@pytest.mark.parametrize(
    ("safe_action", "hold", "paused_at_close"),
    [("hold", False, True), ("pause", True, False), ("hold", True, False)],
)
async def test_a_stream_s_end_decides_what_the_bus_close_does(
    safe_action: str, hold: bool, paused_at_close: bool
) -> None:
    model = LAModel(1)
    async with sim_bus([model], pacing="prompt") as (bus, _sim):
        stream = Streamer(bus).follow(
            InspireLA(bus, 1), lambda t, s: 900, period=0.01, safe_action=safe_action
        )
        await eventually(lambda: stream.stats.ticks >= 3, "three ticks")
        await stream.stop(hold=hold)
        await asyncio.sleep(0.02)
        assert model.power_state is PowerState.WORKING  # held until the bus closes
    assert (model.power_state is PowerState.PAUSED) is paused_at_close
