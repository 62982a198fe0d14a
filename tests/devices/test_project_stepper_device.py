"""ProjectStepper against the simulated project controller."""

from __future__ import annotations

import asyncio

import pytest

from motorbus.devices.project_stepper import ProjectStepper, ProjectStopped
from motorbus.errors import LocalProtocolError, ReplyTimeoutError
from motorbus.protocol import project_stepper as ps
from motorbus.sim.bus import Pacing
from motorbus.sim.project_stepper import ProjectStepperModel
from tests.conftest import PACINGS, sim_bus


def small_project(number: int = 2, *, repeat: int = 0) -> ps.Project:
    step = ps.StepSpec(
        run_distance=1,
        direction=ps.RotationDirection.FORWARD,
        start_hz=50,
        accel_hz=30,
        speed_rpm=600,
        delay_ms=20,
    )
    return ps.Project(
        number=number,
        subdivision=8,
        step_angle_x100=180,
        distance_per_rev=1,
        steps=(step, step),
        repeat_count=repeat,
    )


@pytest.mark.parametrize("delivery", ["whole", "bytewise", "random"])
@pytest.mark.parametrize("pacing", PACINGS)
async def test_upload_verify_and_run_to_ee_dd(delivery: str, pacing: Pacing) -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=115200, delivery=delivery, pacing=pacing) as (bus, _):
        stepper = ProjectStepper(bus)
        project = small_project()
        dump = await stepper.upload(project)
        assert dump is not None and dump.to_project() == project
        await stepper.run_project(2, timeout=10)
        assert bus.stats.events == 1
        assert bus.stats.timeouts == 0


@pytest.mark.parametrize("pacing", PACINGS)
async def test_stop_ends_a_forever_project_with_project_stopped(pacing: Pacing) -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=115200, pacing=pacing) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(small_project(1, repeat=255), verify=False, save=False)
        run = asyncio.create_task(stepper.run_project(1, timeout=10))
        while not model.running:
            await asyncio.sleep(0.005)
        await stepper.stop_project()
        with pytest.raises(ProjectStopped):
            await run
        assert not model.running


@pytest.mark.parametrize("pacing", PACINGS)
async def test_run_timeout_and_bad_input(pacing: Pacing) -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=115200, pacing=pacing) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(small_project(3, repeat=255), verify=False, save=False)
        with pytest.raises(ReplyTimeoutError, match="ProjectFinished"):
            await stepper.run_project(3, timeout=0.05)
        await stepper.stop_project()
        sent = bus.stats.requests
        with pytest.raises(LocalProtocolError, match="project"):
            await stepper.run_project(5)
        with pytest.raises(LocalProtocolError, match="motor"):
            ProjectStepper(bus, motor=0x2E)
        assert bus.stats.requests == sent
        assert await stepper.read_input(1) is False
        model.set_input(1, True, asyncio.get_running_loop().time())
        assert await stepper.read_input(1) is True
