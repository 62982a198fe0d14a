"""InspireLA against simulated actuators over the in-memory link, every variant and pacing."""

from __future__ import annotations

from typing import Any

import pytest

from motorbus.devices.calibration import Calibration
from motorbus.devices.la import InspireLA, scan
from motorbus.errors import LocalProtocolError, ReplyTimeoutError
from motorbus.protocol import la
from motorbus.sim.bus import Pacing
from motorbus.sim.la import LAModel, PowerState
from tests.devices.variants import LA_VARIANTS
from tests.helpers import PACINGS, sim_bus


@pytest.mark.parametrize("delivery", ["whole", "bytewise", "random"])
@pytest.mark.parametrize("variant", LA_VARIANTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_status_move_and_registers(
    variant: dict[str, Any], delivery: str, pacing: Pacing
) -> None:
    models = [LAModel(i, **variant) for i in (1, 2, 3)]
    async with sim_bus(models, delivery=delivery, pacing=pacing) as (bus, _):
        a = InspireLA(bus, 2)
        status = await a.status()
        assert status.id == 2
        moved = await a.move_to(1300)
        assert moved is not None and moved.target == 1300
        assert await a.target() == 1300
        await a.set_over_current_limit(1000)
        assert await a.over_current_limit() == 1000
        await a.set_temperature_limits(70.5, 60.5)
        assert await a.temperature_limits() == (70.5, 60.5)
        assert models[1].received[-1][2] == 1300
        assert bus.stats.timeouts == 0 and bus.stats.garbage_bytes == 0


@pytest.mark.parametrize("variant", LA_VARIANTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_estop_needs_enable_and_pause_resumes(
    variant: dict[str, Any], pacing: Pacing
) -> None:
    model = LAModel(1, **variant)
    async with sim_bus([model], pacing=pacing) as (bus, _):
        a = InspireLA(bus, 1)
        await a.estop()
        await a.move_to(500)
        assert model.target != 500  # ignored after e-stop (manual 3.5.4)
        await a.enable()
        await a.move_to(500)
        assert model.target == 500
        await a.pause()
        await a.move_to(600)
        assert model.target == 600  # after pause a move resumes directly


@pytest.mark.parametrize("variant", LA_VARIANTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_change_id_and_scan(variant: dict[str, Any], pacing: Pacing) -> None:
    async with sim_bus([LAModel(1, **variant), LAModel(4, **variant)], pacing=pacing) as (bus, _):
        found: list[int] = []
        assert await scan(bus, range(1, 6), progress=lambda i, n, hit: found.append(i)) == [1, 4]
        assert sorted(found) == [1, 2, 3, 4, 5]  # once per ID, when final (two passes)
        moved = await InspireLA(bus, 4).change_id(7)
        assert (await moved.status()).id == 7
        with pytest.raises(ReplyTimeoutError, match="la:4"):
            await InspireLA(bus, 4).status()


@pytest.mark.parametrize("variant", LA_VARIANTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_bad_input_is_refused_before_sending(variant: dict[str, Any], pacing: Pacing) -> None:
    async with sim_bus([LAModel(1, **variant)], pacing=pacing) as (bus, _):
        a = InspireLA(bus, 1)
        with pytest.raises(LocalProtocolError, match=r"position=2500 .*0\.\.2000"):
            await a.move_to(2500)
        with pytest.raises(LocalProtocolError, match=r"300\.\.1500"):
            await a.set_over_current_limit(200)
        with pytest.raises(LocalProtocolError):
            await a.set_temperature_limits(50, 48)
        with pytest.raises(LocalProtocolError, match="id"):
            InspireLA(bus, 255)
        with pytest.raises(LocalProtocolError, match=r"read-only|writable"):
            await a.write(la.Register.POSITION, 5)
        assert bus.stats.requests == 0


@pytest.mark.parametrize("pacing", PACINGS)
async def test_change_id_whose_answer_is_lost_is_confirmed_at_the_new_id(pacing: Pacing) -> None:
    # The write takes effect at once (manual 3.6); with its answer lost, a retry to the old
    # ID can never be answered: the change is confirmed by asking the new ID.
    async with sim_bus([LAModel(4, silent_replies=1)], pacing=pacing, host_margin=2e-3) as (
        bus,
        _,
    ):
        moved = await InspireLA(bus, 4).change_id(7)
        assert moved.id == 7 and (await moved.status()).id == 7
        assert bus.stats.timeouts >= 1
        with pytest.raises(ReplyTimeoutError, match="la:4"):
            await InspireLA(bus, 4).status()


async def test_recover_re_enables_an_estopped_actuator_and_resends_its_target() -> None:
    model = LAModel(1)
    async with sim_bus([model]) as (bus, _sim):
        a = InspireLA(bus, 1)
        await a.move_to(1300)
        await a.estop()
        assert model.power_state is PowerState.ESTOPPED
        status = await a.recover()
        assert model.power_state is PowerState.WORKING
        assert status.target == 1300 and model.received[-1][2] == 1300


@pytest.mark.parametrize("target", [1950, 50, 5000, 1.5e300, 1.5])
async def test_recover_checks_its_target_before_it_enables_the_actuator(target: float) -> None:
    # A target the soft limits refuse used to be refused only after the "work" frame: an
    # e-stopped actuator was powered again, and the error said "nothing sent".
    model = LAModel(1)
    async with sim_bus([model]) as (bus, sim):
        a = InspireLA(bus, 1, calibration=Calibration(limits=(100, 1900)))
        await a.estop()
        sent = sim.bus.stats.requests
        with pytest.raises(LocalProtocolError, match=r"position.*(out of range|integer)"):
            await a.recover(target=target)
        assert sim.bus.stats.requests == sent  # nothing at all: not even the query
        assert model.power_state is PowerState.ESTOPPED


async def test_recover_resends_the_reported_target_in_raw_units_on_a_calibrated_actuator() -> None:
    # The status reports the target raw; it was re-sent in the actuator's own unit (mm
    # here), so raw 1000 became 1000 mm: refused after the actuator was enabled, and a
    # small raw target would have moved it elsewhere.
    model = LAModel(1)
    async with sim_bus([model]) as (bus, _sim):
        a = InspireLA(bus, 1, calibration=Calibration(stroke_mm=30, unit="mm"))
        await a.move_to(15.0)  # raw 1000
        await a.estop()
        status = await a.recover()
        assert status.target == 1000 and model.received[-1][2] == 1000
        assert model.power_state is PowerState.WORKING
