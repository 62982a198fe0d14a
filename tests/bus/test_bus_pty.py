"""The bus over a real pseudo-terminal, through every serial backend.

``PtySim`` serves the simulated devices from its own thread, at emulated wire times
(``pacing="wire"``) or at once (``"prompt"``, as a USB-CDC device answers); the bus opens
the pty slave with ``SerialTransport`` exactly as it would open a USB adapter.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator, Sequence
from contextlib import asynccontextmanager

import pytest

from motorbus.bus.bus import Bus
from motorbus.bus.events import QuadDone
from motorbus.devices.la import InspireLA
from motorbus.devices.quad_stepper import QuadStepper
from motorbus.protocol import la
from motorbus.protocol.base import Family
from motorbus.sim.bus import Pacing
from motorbus.sim.la import LAModel
from motorbus.sim.model import DeviceModel
from motorbus.sim.pty import PtySim
from motorbus.sim.quad_stepper import QuadStepperModel
from motorbus.transport.serial import BACKENDS, SerialTransport, available_backends
from tests.helpers import PACINGS

LA_BAUD = 921600  # LA "D" interface (docs/protocols.md C.1)
QUAD_BAUD = 9600  # A1-01: the family default
#: Deadlines here carry a generous host margin: a pty hop plus a thread on a shared
#: machine is not what these tests measure (bench_bus.py does).
HOST_MARGIN_S = 0.05
INSTALLED = available_backends()


def require(backend: str) -> None:
    """Skip, naming the missing package, if ``backend`` cannot be imported here."""
    if backend not in INSTALLED:
        try:
            SerialTransport("/dev/null", baudrate=LA_BAUD, backend=backend)
        except ImportError as err:
            pytest.skip(f"serial backend {backend!r} is not installed: {err}")


@pytest.fixture
def pty_sim(request: pytest.FixtureRequest, pacing: Pacing) -> Iterator[PtySim]:
    """A running ``PtySim`` serving ``request.param()`` = (fresh models, baud) at ``pacing``."""
    models, baud = request.param()
    with PtySim(models, baud=baud, pacing=pacing) as sim:
        yield sim
        assert sim.error is None, f"the simulator thread failed: {sim.error!r}"


@asynccontextmanager
async def pty_bus(sim: PtySim, backend: str, families: Sequence[Family]) -> AsyncIterator[Bus]:
    """An open bus on ``sim``'s pty; fails the test if the bus leaves tasks behind."""
    before = set(asyncio.all_tasks())
    transport = SerialTransport(sim.path, baudrate=sim.bus.baud, backend=backend)
    async with Bus(
        transport, name=f"pty-{backend}", families=families, host_margin=HOST_MARGIN_S
    ) as bus:
        yield bus
    await asyncio.sleep(0)
    leaked = [t for t in asyncio.all_tasks() - before if not t.done()]
    assert not leaked, f"the bus leaked tasks: {leaked}"


def la_bus_models() -> tuple[list[DeviceModel], int]:
    return [LAModel(1), LAModel(2, write_reply="ack")], LA_BAUD


@pytest.mark.parametrize("pty_sim", [la_bus_models], indirect=True, ids=["la"])
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_la_request_reply_over_pty(pty_sim: PtySim, backend: str) -> None:
    require(backend)
    one, two = pty_sim.models
    assert isinstance(one, LAModel) and isinstance(two, LAModel)
    async with pty_bus(pty_sim, backend, [Family.LA]) as bus:
        first, second = InspireLA(bus, 1), InspireLA(bus, 2)
        assert (await first.status()).id == 1
        moved = await first.move_to(1300)
        assert moved is not None and (moved.id, moved.target) == (1, 1300)
        assert await first.target() == 1300
        assert isinstance(await first.write(la.Register.OVER_CURRENT_LIMIT, 900), la.Status)
        assert await second.write(la.Register.OVER_CURRENT_LIMIT, 800) == la.WriteAck(
            id=2, index=la.Register.OVER_CURRENT_LIMIT.index, reserved=0
        )
        assert await first.over_current_limit() == 900
        assert await second.over_current_limit() == 800
        assert await second.move_to(250, reply=False) is None
        for frame in la.split_broadcast(la.BroadcastMode.POSITION, {1: 600, 2: 700}):
            await bus.send(frame)
        # Answered after the no-reply frames, so the simulator has taken them by now.
        assert (await second.status()).target == 700
        assert [t for _, _, t in two.received] == [250, 700]
        assert one.received[-1][1:] == (la.CMD_BROADCAST_MOVE, 600)
        stats = bus.stats
        # Nothing confused, nothing lost.  Not "no timeout": a reply later than its
        # deadline, 50 ms of margin and all, is the machine's (CI once timed out one here
        # on a VM whose hypervisor was taking 10 % of its CPU); the bus must retry it and
        # never hand its late reply to another request, which this checks.
        assert (stats.garbage_bytes, stats.unexpected_frames, stats.failed) == (0, 0, 0)
        assert stats.retries == stats.timeouts
        assert stats.requests == pty_sim.bus.stats.requests


def quad_bus_models() -> tuple[list[DeviceModel], int]:
    return [QuadStepperModel()], QUAD_BAUD


@pytest.mark.parametrize("pty_sim", [quad_bus_models], indirect=True, ids=["quad"])
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_quad_stepper_over_pty(pty_sim: PtySim, backend: str) -> None:
    require(backend)
    (model,) = pty_sim.models
    assert isinstance(model, QuadStepperModel)
    async with pty_bus(pty_sim, backend, [Family.QUAD_STEPPER]) as bus:
        quad = QuadStepper(bus)
        # 100 pulses at 600 rpm x 1600 pulses/rev: a 6 ms run.
        await quad.configure(
            1, subdivision=8, step_angle_x100=180, pulses=100, start_hz=1000, accel_hz=0,
            speed_rpm=600,
        )  # fmt: skip
        with bus.events.subscribe(QuadDone) as done:
            await quad.run(1, timeout=5)
            await quad.led(1, True)
            kinds = [(e.kind, e.led) for e in done.pending()]
        assert kinds == [("run", None), ("led", 1)]
        assert not model.motors[1].running and model.leds[0] is True
        await quad.stop_all()
        assert (bus.stats.timeouts, bus.stats.unexpected_frames, bus.stats.events) == (0, 0, 2)
