"""Shared fixtures.  ``sim_bus`` fails a test whose bus leaves tasks running behind it.

``PACINGS`` are the simulator pacings every bus-facing test runs against: ``"wire"``
(replies when their last byte would arrive at the baud, as on a UART) and ``"prompt"``
(replies the moment a request is complete, as from a USB-CDC device or a TCP bridge).
A test that passes only against one of them shares an assumption with the bus.
"""

from __future__ import annotations

import asyncio
import gc
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from typing import Any

import pytest

from motorbus.bus.bus import Bus
from motorbus.bus.timer import default_timer
from motorbus.protocol.base import Family
from motorbus.sim.bus import PACING_MODES, Pacing
from motorbus.sim.memory import MemorySim
from motorbus.sim.model import DeviceModel

#: Simulator pacings, for ``pytest.mark.parametrize("pacing", PACINGS)``.
PACINGS: list[Pacing] = list(PACING_MODES)


@asynccontextmanager
async def sim_bus(
    models: Sequence[DeviceModel],
    *,
    baud: int | None = None,
    delivery: str = "whole",
    faults: Any = None,
    seed: int = 0,
    pacing: Pacing = "wire",
    **bus_options: Any,
) -> AsyncIterator[tuple[Bus, MemorySim]]:
    """A bus talking to simulated devices over the in-memory link.

    ``pacing`` is the simulator's (``MemorySim.start``): ``"wire"`` or ``"prompt"``.
    """
    timer = default_timer()
    before = set(asyncio.all_tasks())
    async with MemorySim.start(
        models,
        baud=baud,
        delivery=delivery,
        faults=faults,
        seed=seed,
        timer=timer,  # type: ignore[arg-type]
        pacing=pacing,
    ) as sim:
        families = {m.family for m in models} or set(Family)
        # Tests assert behaviour, not speed: a generous host margin keeps a loaded CI
        # machine from turning a slow reply into a timeout.  Timeout tests pass their own.
        bus_options.setdefault("host_margin", 0.05)
        bus = Bus(sim.transport, name="sim", families=families, timer=timer, **bus_options)
        async with bus:
            yield bus, sim
    await asyncio.sleep(0)
    leaked = [t for t in asyncio.all_tasks() - before if not t.done()]
    assert not leaked, f"the bus leaked tasks: {leaked}"


@pytest.fixture
def make_sim_bus() -> Callable[..., Any]:
    return sim_bus


def pytest_collection_finish(session: pytest.Session) -> None:
    """Freeze what collection built: full garbage collections over the suite's large heap
    took 60-137 ms, long enough to turn an on-time reply into a late one (the bus decides
    lateness by time, as it must)."""
    gc.collect()
    gc.freeze()
