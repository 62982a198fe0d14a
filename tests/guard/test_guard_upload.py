"""Issue 19 case 4, the death no program can handle: a project upload SIGKILLed part way.

The upload holds a lease whose safe action is the clear of its project (0x1E), so the
guard clears the half-written project; without the guard it reads back as valid.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from motorbus.sim.process import SimProcess
from tests.cli.test_cli_steppers import EXAMPLE
from tests.cli.test_project_upload_interrupted import CLEAR_PROJECT_1, TEN_STEPS
from tests.guard.test_guard import kill_cli_once, requests, unheard, wait_for_frames
from tests.helpers import cli

#: The first frame of the upload of a 10-step project 1: select project 1, 10 steps.
SELECT_1_OF_10 = "FF AA 6E 01 0A 00 00 00 00 00 22"
#: Step 2's first frame (run distance 2): the 11th of 76, well before the upload ends.
STEP_2_DISTANCE = "FF AA 03 03 02 00 00 00 00 02"
#: Any save project frame (0x2E): the upload's last.
SAVE = "FF AA 2E"


@pytest.fixture
def sim_with_project(tmp_path: Path) -> Iterator[SimProcess]:
    """A project stepper (9600 baud, paced like the wire) holding a valid project 1."""
    with SimProcess(["project-stepper"], baud=9600, log_file=tmp_path / "frames.jsonl") as sim:
        r = cli("project", "upload", str(EXAMPLE), "--port", sim.path)
        assert r.returncode == 0, r.stderr
        yield sim


def kill_upload(sim: SimProcess, tmp_path: Path, *extra: str) -> tuple[list[str], str]:
    """Upload a 10-step project 1, SIGKILLed after step 2 began; return the frames of
    that upload as the simulator got them (waiting for the guard's clear if it runs),
    and the command's standard error."""
    new = tmp_path / "ten.toml"
    new.write_text(TEN_STEPS, encoding="utf-8")
    err = kill_cli_once(sim, ["project", "upload", str(new), *extra], STEP_2_DISTANCE)
    if "--guard" in extra:
        wait_for_frames([sim], {CLEAR_PROJECT_1})
    sent = requests(sim)
    start = max(n for n, h in enumerate(sent) if h == SELECT_1_OF_10)
    return sent[start:], err


def test_sigkill_of_an_upload_with_the_guard_clears_the_half_written_project(
    sim_with_project: SimProcess, tmp_path: Path
) -> None:
    sim = sim_with_project
    sent, err = kill_upload(sim, tmp_path, "--guard")
    upload, last = sent[:-1], sent[-1]
    assert last == CLEAR_PROJECT_1, sent[-3:]  # the guard's frame, after the upload's last
    assert STEP_2_DISTANCE in " | ".join(upload)  # some of it was written ...
    assert not any(h.startswith(SAVE) for h in upload)  # ... and it never finished
    assert CLEAR_PROJECT_1 not in upload
    assert CLEAR_PROJECT_1 not in unheard(sim)  # sent once the device's last reply ended
    assert f"sent the safe action to 1 device(s) on {sim.path} (1 frames" in err, err
    r = cli("project", "read", "1", "--port", sim.path)
    assert (r.returncode, r.stdout) == (1, ""), r.stdout
    assert "project 1 on the controller is not a valid project" in r.stderr
    r = cli("project", "read", "1", "--port", sim.path, "--json")
    assert r.returncode == 1 and "subdivision=0" in r.stderr  # cleared: a zeroed project
    n = len(requests(sim))
    r = cli("project", "run", "1", "--timeout", "5", "--port", sim.path)
    assert r.returncode == 1 and "not a valid project" in r.stderr
    assert not any(h.startswith("FF AA 4E") for h in requests(sim)[n:])  # nothing started


def test_sigkill_of_an_upload_without_the_guard_leaves_a_mix_that_reads_as_valid(
    sim_with_project: SimProcess, tmp_path: Path
) -> None:
    """The limit the guard exists for: nothing runs in a killed program."""
    sim = sim_with_project
    sent, _ = kill_upload(sim, tmp_path)
    assert not any(h.startswith(SAVE) for h in sent)
    assert CLEAR_PROJECT_1 not in sent
    r = cli("project", "read", "1", "--port", sim.path)
    assert r.returncode == 0, r.stderr  # it reads back as valid, and would run:
    assert "speed_rpm = 101" in r.stdout  # the new step 1 (the old one ran at 600 rpm)
    assert "[loop]\nstart = 1\nend = 2\ncount = 2" in r.stdout  # the old project's loop
