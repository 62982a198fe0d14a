"""QuadStepper against the simulated controller over the in-memory link."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from motorbus.devices.quad_stepper import QuadStepper
from motorbus.errors import LocalProtocolError
from motorbus.sim.bus import Pacing
from motorbus.sim.quad_stepper import QuadStepperModel
from tests.conftest import PACINGS, sim_bus
from tests.devices.variants import QUAD_VARIANTS


@pytest.mark.parametrize("delivery", ["whole", "bytewise", "random"])
@pytest.mark.parametrize("variant", QUAD_VARIANTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_run_waits_for_done(variant: dict[str, Any], delivery: str, pacing: Pacing) -> None:
    model = QuadStepperModel(**variant)
    async with sim_bus([model], baud=115200, delivery=delivery, pacing=pacing) as (bus, _):
        quad = QuadStepper(bus)
        await quad.configure(
            1,
            subdivision=8,
            step_angle_x100=180,
            pulses=400,
            start_hz=50,
            accel_hz=0,
            speed_rpm=600,
        )
        await quad.run(1, timeout=5)
        assert model.motors[1].position == 400
        assert not model.motors[1].running
        await quad.led(2, True)
        assert model.leds[1] is True
        assert bus.stats.timeouts == 0
        assert bus.stats.events == 2


@pytest.mark.parametrize("variant", QUAD_VARIANTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_stop_all_and_bad_input_sends_nothing(
    variant: dict[str, Any], pacing: Pacing
) -> None:
    model = QuadStepperModel(**variant)
    async with sim_bus([model], baud=115200, pacing=pacing) as (bus, _):
        quad = QuadStepper(bus)
        sent = bus.stats.requests
        with pytest.raises(LocalProtocolError, match="motor"):
            await quad.run(5)
        with pytest.raises(LocalProtocolError, match="led"):
            await quad.led(6, True)
        assert bus.stats.requests == sent
        await quad.stop_all()
        await quad.save()


@pytest.mark.parametrize("variant", QUAD_VARIANTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_run_all_then_traffic_goes_on(variant: dict[str, Any], pacing: Pacing) -> None:
    """Run-all has no documented completion (A1-04): done replies or none, the bus copes."""
    model = QuadStepperModel(**variant)
    async with sim_bus([model], baud=115200, pacing=pacing) as (bus, sim):
        quad = QuadStepper(bus)
        for motor in (1, 2, 3, 4):
            await quad.configure(
                motor,
                subdivision=8,
                step_angle_x100=180,
                pulses=40 * motor,
                start_hz=2000,
                accel_hz=0,
                speed_rpm=600,
            )
        await quad.run_all()
        loop = asyncio.get_running_loop()
        give_up = loop.time() + 5.0
        while any(model.motors[m].running for m in (1, 2, 3, 4)):
            assert loop.time() < give_up, "run-all never ended"
            await quad.led(1, True)  # traffic while the motors run and finish
        await quad.led(2, True)
        assert [model.motors[m].position for m in (1, 2, 3, 4)] == [40, 80, 120, 160]
        # A request that reaches the controller while it sends a done reply is not heard
        # (half duplex; only on a paced wire do the two overlap): the bus retries it.
        # Every timeout must be such a miss, and every call must have succeeded.
        assert bus.stats.timeouts == sim.bus.stats.ignored_while_transmitting
        assert bus.stats.failed == 0 and bus.stats.unexpected_frames == 0
        # Run-all completions are no reply the bus awaits (A1-04): discarded, and counted.
        done_frames = 4 if variant["run_all_done"] == "each" else 0
        assert bus.stats.garbage_bytes <= 6 * done_frames
