"""InspireLA: waiting for arrival (the LA has no in-position flag) and millimetres."""

from __future__ import annotations

import pytest

from motorbus.bus.bus import Bus
from motorbus.devices.la import InspireLA
from motorbus.errors import ArrivalTimeoutError, LocalProtocolError
from motorbus.protocol import la
from motorbus.sim.la import LAModel
from motorbus.transport.memory import memory_pair
from tests.helpers import sim_bus


async def test_move_to_wait_returns_once_the_position_is_within_tolerance() -> None:
    model = LAModel(1, stroke_speed=4000.0)
    async with sim_bus([model]) as (bus, _):
        a = InspireLA(bus, 1)
        await a.enable()
        first = await a.move_to(1500)
        assert first is not None and abs(first.position - 1500) > 100  # not there yet
        requests = bus.stats.requests
        arrived = await a.move_to(500, wait=True, tolerance=5)
        assert arrived is not None
        assert arrived.target == 500 and abs(arrived.position - 500) <= 5
        assert abs(model.position - 500) <= 5
        assert model.received[-1][1:] == (la.CMD_MOVE, 500)
        # The move, then status queries: two in a row within tolerance at least.
        assert bus.stats.requests - requests >= 3


async def test_move_to_wait_times_out_naming_actuator_target_and_last_position() -> None:
    model = LAModel(3)
    async with sim_bus([model]) as (bus, _):
        a = InspireLA(bus, 3)
        await a.estop()  # position commands are ignored until "work" (manual 3.5.4)
        with pytest.raises(ArrivalTimeoutError, match=r"la:3 did not reach 1800 .*last position"):
            await a.move_to(1800, wait=True, timeout=0.1)


async def test_bad_wait_arguments_are_refused_before_sending() -> None:
    model = LAModel(1)
    async with sim_bus([model]) as (bus, _):
        a = InspireLA(bus, 1)
        before = len(model.received)
        with pytest.raises(LocalProtocolError, match=r"tolerance=500 .*0\.\.200"):
            await a.move_to(100, wait=True, tolerance=500)
        with pytest.raises(LocalProtocolError, match="timeout"):
            await a.move_to(100, wait=True, timeout=-1)
        assert len(model.received) == before


async def test_millimetres_map_linearly_onto_0_to_2000() -> None:
    model = LAModel(2, stroke_speed=4000.0)
    async with sim_bus([model]) as (bus, _):
        a = InspireLA(bus, 2, stroke_mm=30)
        assert a.from_mm(15) == 1000 and a.to_mm(2000) == 30.0
        await a.enable()
        moved = await a.move_to_mm(7.5, wait=True, tolerance=2)
        assert moved is not None and moved.target == 500
        assert abs(await a.position_mm() - 7.5) <= 2 * 30 / 2000
        before = len(model.received)
        with pytest.raises(LocalProtocolError, match=r"mm=31 is out of range: allowed 0\.\.30"):
            await a.move_to_mm(31)
        with pytest.raises(LocalProtocolError, match="no stroke_mm"):
            await InspireLA(bus, 2).move_to_mm(3)
        assert len(model.received) == before


def test_a_bad_stroke_is_refused_at_construction() -> None:
    with pytest.raises(LocalProtocolError, match=r"stroke_mm=0 is out of range: allowed 1\.\.1000"):
        InspireLA(Bus(memory_pair()[0]), 1, stroke_mm=0)
