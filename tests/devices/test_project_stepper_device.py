"""ProjectStepper against the simulated project controller."""

from __future__ import annotations

import asyncio
import gc
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from motorbus.bus.bus import Bus
from motorbus.devices.project_stepper import ProjectStepper, ProjectStopped
from motorbus.errors import LocalProtocolError, ReplyTimeoutError
from motorbus.protocol import project_stepper as ps
from motorbus.protocol.base import Family
from motorbus.sim.bus import Pacing
from motorbus.sim.project_stepper import ProjectStepperModel
from motorbus.transport.memory import memory_pair
from tests.devices.variants import PROJECT_VARIANTS
from tests.helpers import PACINGS, sim_bus
from tests.waiting import eventually

ROOT = Path(__file__).resolve().parents[2]


def small_project(number: int = 2, *, repeat: int = 0, delay_ms: int = 20) -> ps.Project:
    step = ps.StepSpec(
        run_distance=1,
        direction=ps.RotationDirection.FORWARD,
        start_hz=1000,
        accel_hz=300,
        speed_rpm=600,
        delay_ms=delay_ms,
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
@pytest.mark.parametrize("variant", PROJECT_VARIANTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_upload_verify_and_run_to_ee_dd(
    variant: dict[str, Any], delivery: str, pacing: Pacing
) -> None:
    model = ProjectStepperModel(**variant)
    async with sim_bus([model], baud=115200, delivery=delivery, pacing=pacing) as (bus, _):
        stepper = ProjectStepper(bus)
        project = small_project()
        dump = await stepper.upload(project)
        assert dump is not None and dump.to_project() == project
        await stepper.run_project(2, timeout=10)
        assert bus.stats.events == 1
        assert bus.stats.timeouts == 0


@pytest.mark.parametrize("variant", PROJECT_VARIANTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_stop_ends_a_forever_project_with_project_stopped(
    variant: dict[str, Any], pacing: Pacing
) -> None:
    model = ProjectStepperModel(**variant)
    async with sim_bus([model], baud=115200, pacing=pacing) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(small_project(1, repeat=255), verify=False, save=False)
        run = asyncio.create_task(stepper.run_project(1, timeout=10))
        await eventually(lambda: model.running, "the project running")
        await stepper.stop_project()
        with pytest.raises(ProjectStopped):
            await run
        assert not model.running


@pytest.mark.parametrize("variant", PROJECT_VARIANTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_run_timeout_and_bad_input(variant: dict[str, Any], pacing: Pacing) -> None:
    model = ProjectStepperModel(**variant)
    async with sim_bus([model], baud=115200, pacing=pacing) as (bus, _):
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


async def test_the_stop_of_a_timed_out_run_is_the_lease_keepers() -> None:
    # One sender of safe actions (issue 40): the run's stop is asked of the keeper, which
    # sends it at emergency priority with the safe stops' retries.
    model = ProjectStepperModel()
    async with sim_bus([model], baud=115200) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(small_project(1, repeat=255), verify=False, save=False)
        keeper = bus.lease_keeper
        asked: list[tuple[str, ...]] = []
        send_stop = keeper.send_stop

        async def recording(commands: Any, *, who: str) -> list[object]:
            asked.append(tuple(type(c).__name__ for c in commands))
            return await send_stop(commands, who=who)

        keeper.send_stop = recording  # type: ignore[method-assign]
        with pytest.raises(ReplyTimeoutError, match="stopped it"):
            await stepper.run_project(1, timeout=0.05)
        assert asked == [("StopProject",)]
        assert not model.running


@pytest.mark.parametrize("stale_first", [False, True], ids=["ee-dd-after", "ee-dd-before"])
async def test_an_ee_dd_read_with_the_start_acknowledgement_is_judged_by_its_place(
    stale_first: bool,
) -> None:
    # A short project's EE DD follows the start's acknowledgement closely: a loaded host
    # reads both in one chunk, and the EE DD behind the acknowledgement is the run's end
    # (it was taken for one from before the start, and the run waited out its timeout).
    # One in front of the acknowledgement is from before the start: the run waits on.
    host, peer = memory_pair(baudrate=115200)
    model = ProjectStepperModel()
    start = ps.StartProject(1).encode()

    def answer(data: bytes) -> None:
        replies = b"".join(model.handle(data, 0.0))
        if data == start:
            replies = (
                ps.PROJECT_FINISHED + replies if stale_first else replies + ps.PROJECT_FINISHED
            )
        peer.send(replies)

    peer.set_receiver(answer)
    async with Bus(host, families=[Family.PROJECT_STEPPER]) as bus:
        run = asyncio.create_task(ProjectStepper(bus).run_project(1, timeout=5))
        if stale_first:
            await asyncio.sleep(0.05)
            assert not run.done()  # the EE DD in front was not taken for the run's end
            peer.send(ps.PROJECT_FINISHED)
        await asyncio.wait_for(run, 5)


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
                await eventually(lambda: model.running, "the project running")
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
            await eventually(lambda: model.running, "the project running")
            await stepper.stop_project()
            with pytest.raises(ProjectStopped):
                await asyncio.wait_for(run, 5)


@pytest.mark.parametrize("variant", PROJECT_VARIANTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_settings_are_acknowledged_and_stored(
    variant: dict[str, Any], pacing: Pacing
) -> None:
    model = ProjectStepperModel(**variant)
    async with sim_bus([model], baud=115200, pacing=pacing) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(small_project(1), verify=False, save=False)
        await stepper.set_stop_mode(1)
        try:
            await stepper.set_mode4(2)
            await stepper.set_power_on_homing(True)
        except ReplyTimeoutError as err:  # no source-based traceback: see below
            pytest.fail(f"{type(err).__name__}: {err}", pytrace=False)
        dump = await stepper.read_project(1)
        assert (dump.stop_mode, dump.mode4, dump.power_on_homing) == (1, 2, 1)
        assert bus.stats.timeouts == 0 and bus.stats.unexpected_frames == 0


async def stop_then_run_again(variant: dict[str, Any], pacing: Pacing) -> str:
    """Run a forever project, stop it, run a finite one; return what went wrong, or ""."""
    model = ProjectStepperModel(**variant)
    async with sim_bus([model], baud=115200, pacing=pacing) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(small_project(1, repeat=255), verify=False, save=False)
        # Long enough (two 150 ms step delays) that a stale EE DD lands inside the run.
        await stepper.upload(small_project(2, delay_ms=150), verify=False, save=False)
        run = asyncio.create_task(stepper.run_project(1, timeout=10))
        await eventually(lambda: model.running, "the project running")
        await stepper.stop_project()
        try:
            await run
        except ProjectStopped:
            pass
        else:
            return "run_project(1) did not raise ProjectStopped"
        await stepper.run_project(2, timeout=10)
        if model.running:
            return "run_project(2) returned while project 2 was still running"
        steps = [t.step for t in model.trace if t.project == 2]
        return "" if steps == [1, 2] else f"project 2 ran steps {steps}"


@pytest.mark.parametrize("variant", PROJECT_VARIANTS)
@pytest.mark.parametrize("pacing", PACINGS)
def test_a_run_after_a_stop_waits_for_its_own_finish(
    variant: dict[str, Any], pacing: Pacing
) -> None:
    """``run_project`` returns when *its* project ends, not on an EE DD the stop caused.

    Run in a child interpreter, as a guard: when this failed, it left a task ending with an
    unretrieved StopAsyncIteration (fixed in ``Subscription.next``), after which CPython
    3.11.7's ``compile`` raised "AST constructor recursion depth mismatch" and took the rest
    of the session down with it.
    """
    code = (
        "import asyncio, sys\n"
        "from tests.devices.test_project_stepper_device import stop_then_run_again\n"
        f"print('RESULT', repr(asyncio.run(stop_then_run_again({variant!r}, {pacing!r}))))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr[-3000:]
    results = [line for line in out.stdout.splitlines() if line.startswith("RESULT ")]
    assert results, out.stdout[-2000:] + out.stderr[-2000:]
    problem = results[-1].removeprefix("RESULT ")
    assert problem == "''", problem
