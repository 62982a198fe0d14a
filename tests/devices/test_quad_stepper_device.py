"""QuadStepper against the simulated controller over the in-memory link."""

from __future__ import annotations

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
