"""Issue 19 case 4: an upload cut short must not leave a project that looks valid."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path

import pytest

from motorbus.devices.project_stepper import ProjectStepper
from motorbus.errors import ProjectInvalidError
from motorbus.protocol import project_stepper as ps
from motorbus.sim.process import SimProcess
from motorbus.sim.project_stepper import ProjectStepperModel
from tests.cli.test_cli_steppers import EXAMPLE, interrupt_once_sent
from tests.helpers import cli, rx_frames, sim_bus
from tests.waiting import eventually

#: The clear-project frame for project 1 (A.4 0x1E).
CLEAR_PROJECT_1 = "FF AA 1E 01 00 00 00 00 00 00 C8"
#: Step 4's first frame (run distance 4, b9 = step 4): the upload is well under way.
STEP_4_DISTANCE = "FF AA 03 03 04 00 00 00 00 04"

TEN_STEPS = "\n".join(
    ["number = 1", "subdivision = 8", "step_angle = 1.8", "distance_per_rev = 1"]
    + [f"[[step]]\ndistance = {n}\nspeed_rpm = {100 + n}\ndelay_ms = 5" for n in range(1, 11)]
)


def ten_step_project(number: int = 1) -> ps.Project:
    step = ps.StepSpec(run_distance=3, speed_rpm=120, delay_ms=5)
    return ps.Project(
        number=number, subdivision=8, step_angle_x100=180, distance_per_rev=1, steps=(step,) * 10
    )


@pytest.fixture
def sim_with_project(tmp_path: Path) -> Iterator[SimProcess]:
    """A project stepper holding a valid, saved project 1 (the example)."""
    with SimProcess(["project-stepper"], baud=9600, log_file=tmp_path / "frames.jsonl") as sim:
        r = cli("project", "upload", str(EXAMPLE), "--port", sim.path)
        assert r.returncode == 0, r.stderr
        yield sim


def test_ctrl_c_during_upload_leaves_an_invalid_project_and_says_how_far(
    sim_with_project: SimProcess, tmp_path: Path
) -> None:
    sim = sim_with_project
    new = tmp_path / "ten.toml"
    new.write_text(TEN_STEPS, encoding="utf-8")
    before = len(rx_frames(sim))
    code, err = interrupt_once_sent(sim, ["project", "upload", str(new)], STEP_4_DISTANCE)
    assert code == 130, err
    assert "Traceback" not in err
    total = 3 + 7 * 10 + 2 + 1  # select, motor, distance/rev, 7 per step, loop, repeat, save
    assert err.splitlines()[-1] == "motorbus project: interrupted"
    lines = [line for line in err.splitlines()[:-1] if line.startswith("motorbus project: ")]
    assert len(lines) == 1, err
    prefix = "motorbus project: project 1: upload interrupted after "
    assert lines[0].startswith(prefix), err
    done = int(lines[0].removeprefix(prefix).split()[0])
    assert lines[0].endswith(
        f" of {total} frames; the project on the device is invalid (cleared, 0x1E sent): "
        "upload it again"
    ), err
    sent = rx_frames(sim)[before:]
    assert 0 < done < total
    assert sent[-1] == CLEAR_PROJECT_1  # the clear is the last frame the device got
    assert all(not h.startswith("FF AA 2E") for h in sent)  # never saved
    # read and run refuse it (run before anything moves: no 4E frame).
    r = cli("project", "read", "1", "--port", sim.path)
    assert (r.returncode, r.stdout) == (1, ""), r.stdout
    assert "project 1 on the controller is not a valid project" in r.stderr
    n = len(rx_frames(sim))
    r = cli("project", "run", "1", "--timeout", "5", "--port", sim.path)
    assert r.returncode == 1, r.stderr
    assert "project 1 on the controller is not a valid project" in r.stderr
    assert not any(h.startswith("FF AA 4E") for h in rx_frames(sim)[n:])


async def test_cancelled_upload_raises_cancelled_error_naming_the_project_and_progress() -> None:
    model = ProjectStepperModel()
    async with sim_bus([model], baud=9600) as (bus, _):
        stepper = ProjectStepper(bus)
        old = ten_step_project()
        await stepper.upload(old)  # a valid project 1, saved
        new = ps.Project(
            number=1,
            subdivision=16,
            step_angle_x100=90,
            distance_per_rev=2,
            steps=(ps.StepSpec(run_distance=7, speed_rpm=300),) * 10,
        )
        before = bus.stats.requests
        task = asyncio.create_task(stepper.upload(new))
        await eventually(lambda: bus.stats.requests >= before + 12, "12 upload frames sent")
        task.cancel()
        with pytest.raises(asyncio.CancelledError) as info:
            await task
        message = str(info.value)
        assert message.startswith("project 1: upload interrupted after "), message
        assert " of 76 frames; the project on the device is invalid" in message
        with pytest.raises(ProjectInvalidError, match="project 1 on the controller is not a"):
            await stepper.check_project(1)
        # Neither RAM nor flash keeps the half-written mix.
        assert model.stored_image(1) == model.stored_image(1, flash=True)
        assert (await stepper.read_project(1)).steps == ()


async def test_an_upload_refused_before_any_frame_clears_nothing() -> None:
    from motorbus.errors import LocalProtocolError
    from motorbus.sim.la import LAModel

    async with sim_bus([LAModel(1)], baud=115200) as (bus, _):  # no project family here
        stepper = ProjectStepper(bus)
        refused = "is a project_stepper device; bus sim carries la"
        with pytest.raises(LocalProtocolError, match=refused) as info:
            await stepper.upload(ten_step_project())
        assert not getattr(info.value, "__notes__", None)  # no clear was attempted
        assert bus.stats.requests == 0
