"""Issue 19: an upload holds a lease whose safe action clears the project it writes, so a
guard process can clear a half-written project after a SIGKILL (tests/guard has the kill)."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from motorbus.bus.leases import LeaseInfo
from motorbus.devices.project_stepper import ProjectStepper
from motorbus.errors import LeaseConflictError, LocalProtocolError, ProjectInvalidError
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol.base import Command
from motorbus.sim.project_stepper import ProjectStepperModel
from motorbus.sim.project_stepper_memory import cleared_image
from tests.helpers import sim_bus
from tests.waiting import eventually

KEY = "project_stepper"
CLEAR_1 = ps.ClearProject(1)
STOPS = (ps.StopProject(), ps.ManualStop(motor=ps.DEFAULT_MOTOR))


def ten_steps(number: int = 1, *, distance: int = 3) -> ps.Project:
    step = ps.StepSpec(run_distance=distance, speed_rpm=120, delay_ms=5)
    return ps.Project(
        number=number, subdivision=8, step_angle_x100=180, distance_per_rev=1, steps=(step,) * 10
    )


def short(number: int = 1) -> ps.Project:
    """Two steps of 5 ms: a run that ends (EE DD) at once."""
    step = ps.StepSpec(run_distance=1, speed_rpm=600, delay_ms=5)
    return ps.Project(
        number=number, subdivision=8, step_angle_x100=180, distance_per_rev=1, steps=(step,) * 2
    )


class Written:
    """A bus observer: every command the bus wrote, in order."""

    def __init__(self) -> None:
        self.commands: list[Command[object]] = []

    def on_write(self, cmd: Command[object], at: float) -> None:
        self.commands.append(cmd)

    def on_reply(self, cmd: Command[object], value: Any, written: float, replied: float) -> None:
        pass


def upload_lease(*safe: Command[object], number: int = 1) -> LeaseInfo:
    return LeaseInfo(KEY, f"upload project {number}", tuple(c.encode() for c in safe))


async def test_the_upload_leases_the_controller_with_the_clear_and_ends_it_quietly() -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=9600) as (bus, _):
        written = Written()
        bus.add_observer(written)
        snapshots: list[tuple[LeaseInfo, ...]] = []
        bus.add_lease_listener(snapshots.append)
        stepper = ProjectStepper(bus)
        project = ten_steps()
        total = len(ps.project_commands(project)) + 1  # and the save
        task = asyncio.create_task(stepper.upload(project, verify=False))
        await eventually(lambda: len(written.commands) >= 5, "5 upload frames written")
        assert bus.leases == (upload_lease(CLEAR_1),)  # what a guard would send: the clear
        assert await task is None
        assert bus.leases == ()
        assert snapshots == [(upload_lease(CLEAR_1),), ()]  # acquired before the first frame
        assert len(written.commands) == total
        assert not any(isinstance(c, ps.ClearProject) for c in written.commands)
        assert await stepper.check_project(1) == project
        n = len(written.commands)
    assert len(written.commands) == n  # the close sent nothing either


async def test_a_cancelled_upload_clears_once_and_ends_its_lease() -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=9600) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(ten_steps(distance=9))  # a valid project 1, saved
        written = Written()
        bus.add_observer(written)
        keeper, asked = bus.lease_keeper, []
        send_stop = keeper.send_stop

        async def recording(commands: Any, *, who: str) -> list[object]:
            asked.extend(commands)  # the one sender of safe actions sends the clear
            return await send_stop(commands, who=who)

        keeper.send_stop = recording  # type: ignore[method-assign]
        task = asyncio.create_task(stepper.upload(ten_steps()))
        await eventually(lambda: len(written.commands) >= 12, "12 upload frames written")
        assert bus.leases == (upload_lease(CLEAR_1),)
        task.cancel()
        with pytest.raises(asyncio.CancelledError) as info:
            await task
        message = str(info.value)
        assert message.startswith("project 1: upload interrupted after "), message
        assert message.endswith(
            " of 76 frames; the project on the device is invalid (cleared, 0x1E sent): "
            "upload it again"
        ), message
        assert bus.leases == ()
        clears = [c for c in written.commands if isinstance(c, ps.ClearProject)]
        assert clears == [CLEAR_1] and written.commands[-1] == CLEAR_1  # once, last
        assert asked == [CLEAR_1]
        with pytest.raises(ProjectInvalidError):
            await stepper.check_project(1)
        n = len(written.commands)
    assert len(written.commands) == n  # the close owed nothing


async def test_an_upload_is_refused_while_another_owner_leases_the_controller() -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=9600) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(short())
        written = Written()
        bus.add_observer(written)
        async with bus.lease(KEY, owner="rig"):
            with pytest.raises(LeaseConflictError) as info:
                await stepper.upload(ten_steps())
            assert (info.value.key, info.value.owner) == (KEY, "rig")
            assert info.value.refused == "upload project 1"
            assert [i.owner for i in bus.leases] == ["rig"]  # the holder's lease is untouched
        assert [type(c) for c in written.commands] == [type(c) for c in STOPS]  # the rig's end
        assert await stepper.check_project(1) == short()  # nothing of the upload was sent


async def test_motion_from_elsewhere_is_refused_while_an_upload_writes() -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=9600) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(short(2))
        written = Written()
        bus.add_observer(written)
        task = asyncio.create_task(stepper.upload(ten_steps()))
        await eventually(lambda: len(written.commands) >= 3, "3 upload frames written")
        with pytest.raises(LeaseConflictError) as info:
            await stepper.start_project(2)
        assert info.value.owner == "upload project 1"
        await task
        assert not any(isinstance(c, ps.StartProject) for c in written.commands)


async def test_a_controller_the_program_moved_goes_back_to_it_after_the_upload() -> None:
    """The upload takes the controller over from the implicit lease: it owes that lease's
    stop too while it writes, and hands the controller back, so the close stops it."""
    model = ProjectStepperModel()
    async with sim_bus([model], baud=9600) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(short(2))
        await stepper.run_project(2, timeout=10)  # motion outside any lease
        assert [(i.key, i.owner) for i in bus.leases] == [(KEY, "program")]
        written = Written()
        bus.add_observer(written)
        task = asyncio.create_task(stepper.upload(ten_steps()))
        await eventually(lambda: len(written.commands) >= 3, "3 upload frames written")
        assert bus.leases == (upload_lease(*STOPS, CLEAR_1),)
        await task
        assert [(i.key, i.owner) for i in bus.leases] == [(KEY, "program")]
        n = len(written.commands)
    assert written.commands[n:] == list(STOPS)  # the implicit lease's end: the stop


async def test_the_bus_closing_under_an_upload_sends_the_clear_as_the_leases_end() -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=9600) as (bus, _):
        stepper = ProjectStepper(bus)
        await stepper.upload(ten_steps(distance=9))
        written = Written()
        bus.add_observer(written)
        task = asyncio.create_task(stepper.upload(ten_steps()))
        await eventually(lambda: len(written.commands) >= 12, "12 upload frames written")
        await bus.close()
        with pytest.raises(Exception) as info:
            await task
        notes = getattr(info.value, "__notes__", [])
        assert len(notes) == 1 and notes[0].startswith("project 1: upload failed after "), notes
        assert "the bus closed under it and sent the upload's safe action, the clear" in notes[0]
        assert [c for c in written.commands if isinstance(c, ps.ClearProject)] == [CLEAR_1]
        assert model.stored_image(1) == cleared_image(1)
        assert model.stored_image(1, flash=True) == cleared_image(1)


# -- the lease layer's own safe commands ----------------------------------------------------


async def test_own_safe_commands_are_checked_by_name() -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=9600) as (bus, _):
        bad: list[tuple[object, str]] = [
            (["0x1E"], "is not a motorbus Command"),
            ([ps.StartProject(1)], "StartProject starts motion"),
            ([la.Control(3, la.ControlAction.PAUSE)], "addresses la:3, which the lease"),
        ]
        for commands, message in bad:
            with pytest.raises(LocalProtocolError, match=message) as info:
                bus.lease(KEY, owner="x", safe_commands=commands)  # type: ignore[arg-type]
            assert info.value.field == "safe_commands"
        assert bus.leases == ()


async def test_own_safe_commands_survive_motion_with_a_motor_byte() -> None:
    """The bus rewrites a project stepper's stop with the motor byte of its motion, but
    never an owner's own safe commands."""
    model = ProjectStepperModel(motor=5)
    async with sim_bus([model], baud=9600) as (bus, _):
        stepper = ProjectStepper(bus, motor=5)
        async with bus.lease(KEY, owner="rig", safe_commands=[CLEAR_1]):
            await stepper.single_run()
            assert bus.leases == (LeaseInfo(KEY, "rig", (CLEAR_1.encode(),)),)
        async with bus.lease(KEY, owner="rig"):
            await stepper.single_run()
            stops = (ps.StopProject(), ps.ManualStop(motor=5))
            assert bus.leases == (LeaseInfo(KEY, "rig", tuple(c.encode() for c in stops)),)
