"""ProjectStepper against the simulated project controller."""

from __future__ import annotations

import asyncio
import gc

import pytest

from motorbus.devices.project_stepper import ProjectStepper, ProjectStopped
from motorbus.errors import LocalProtocolError, ReplyTimeoutError
from motorbus.protocol import project_stepper as ps
from motorbus.sim.project_stepper import ProjectStepperModel
from tests.conftest import sim_bus


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
async def test_upload_verify_and_run_to_ee_dd(delivery: str) -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=115200, delivery=delivery) as (bus, _):
        stepper = ProjectStepper(bus)
        project = small_project()
        dump = await stepper.upload(project)
        assert dump is not None and dump.to_project() == project
        await stepper.run_project(2, timeout=10)
        assert bus.stats.events == 1
        assert bus.stats.timeouts == 0


async def test_stop_ends_a_forever_project_with_project_stopped() -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=115200) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(small_project(1, repeat=255), verify=False, save=False)
        run = asyncio.create_task(stepper.run_project(1, timeout=10))
        while not model.running:
            await asyncio.sleep(0.005)
        await stepper.stop_project()
        with pytest.raises(ProjectStopped):
            await run
        assert not model.running


async def test_run_timeout_and_bad_input() -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=115200) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(small_project(3, repeat=255), verify=False, save=False)
        with pytest.raises(ReplyTimeoutError, match="no EE DD"):
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


async def test_a_run_that_times_out_is_stopped_and_says_so() -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=115200) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(small_project(1, repeat=255), verify=False, save=False)
        with pytest.raises(ReplyTimeoutError) as info:
            await stepper.run_project(1, timeout=0.05)
        assert str(info.value) == (
            "project 1 did not finish (no EE DD) within 0.05 s: stopped it (0x5E sent)"
        )
        assert not model.running


async def test_keep_running_leaves_a_timed_out_run_going_and_says_how_to_stop() -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=115200) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(small_project(1, repeat=255), verify=False, save=False)
        with pytest.raises(ReplyTimeoutError) as info:
            await stepper.run_project(1, timeout=0.05, keep_running=True)
        assert str(info.value).endswith(": still running; `motorbus project stop` ends it")
        assert model.running
        await stepper.stop_project()
        assert not model.running


async def test_cancelled_runs_stop_the_project_and_leave_no_unretrieved_exception() -> None:
    loop = asyncio.get_running_loop()
    reports: list[dict[str, object]] = []
    previous = loop.get_exception_handler()
    loop.set_exception_handler(lambda _loop, context: reports.append(context))
    model = ProjectStepperModel()
    running_after_cancel: list[bool] = []
    try:
        async with sim_bus([model], baud=115200) as (bus, _):
            stepper = ProjectStepper(bus)
            await stepper.upload(small_project(1, repeat=255), verify=False, save=False)
            for _ in range(5):
                run = asyncio.create_task(stepper.run_project(1, timeout=10))
                while not model.running:
                    await asyncio.sleep(0.005)
                run.cancel()
                with pytest.raises(asyncio.CancelledError):
                    await run
                running_after_cancel.append(model.running)
                if model.running:
                    await stepper.stop_project()
        # Unretrieved task exceptions are reported when the task is collected.
        gc.collect()
        await asyncio.sleep(0)
    finally:
        loop.set_exception_handler(previous)
    assert [str(c.get("message")) for c in reports] == []
    assert running_after_cancel == [False] * 5  # each cancellation sent stop project


async def test_stop_project_ends_a_waiting_run_at_once() -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=115200) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(small_project(1, repeat=255), verify=False, save=False)
        for _ in range(3):
            run = asyncio.create_task(stepper.run_project(1, timeout=30))
            while not model.running:
                await asyncio.sleep(0.005)
            await stepper.stop_project()
            with pytest.raises(ProjectStopped):
                await asyncio.wait_for(run, 5)
