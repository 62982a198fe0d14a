"""``motorbus project`` and ``motorbus quad`` against ``motorbus sim``; the project TOML form."""

from __future__ import annotations

import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motorbus.cli.project import project_from_toml, project_to_dict, project_to_toml
from motorbus.errors import LocalProtocolError
from motorbus.protocol import project_stepper as ps
from motorbus.sim.process import SimProcess
from tests.cli.test_cli_la import cli, json_lines, rx_frames

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "project.toml"

#: The project examples/project.toml describes, written out by hand.
EXAMPLE_PROJECT = ps.Project(
    number=1,
    subdivision=8,
    step_angle_x100=180,
    distance_per_rev=1,
    steps=(
        ps.StepSpec(
            run_distance=1,
            direction=ps.RotationDirection.FORWARD,
            start_hz=100,
            accel_hz=50,
            speed_rpm=600,
            output=ps.StepOutputCode.OUT1_ON,
            delay_ms=50,
        ),
        ps.StepSpec(
            run_distance=1,
            direction=ps.RotationDirection.REVERSE,
            start_hz=100,
            accel_hz=50,
            speed_rpm=600,
            output=ps.StepOutputCode.OUT1_OFF,
            delay_ms=50,
        ),
    ),
    loop_start=1,
    loop_end=2,
    loop_count=2,
)


@pytest.fixture(scope="module")
def project_sim() -> Iterator[SimProcess]:
    with SimProcess(["project-stepper"], baud=9600) as sim:
        yield sim


@pytest.fixture(scope="module")
def quad_sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimProcess]:
    log = tmp_path_factory.mktemp("quad") / "frames.jsonl"
    with SimProcess(["quad-stepper"], baud=9600, log_file=log) as sim:
        yield sim


# -- against the simulators ---------------------------------------------------------------------


def test_upload_read_run_round_trip(project_sim: SimProcess, tmp_path: Path) -> None:
    port = ["--port", project_sim.path]
    r = cli("project", "upload", str(EXAMPLE), *port)
    assert (r.returncode, r.stdout) == (0, "project 1 (2 steps) uploaded, saved, verified\n")
    r = cli("project", "read", "1", *port)
    assert r.returncode == 0, r.stderr
    assert project_from_toml(r.stdout) == EXAMPLE_PROJECT
    # What read prints, upload takes.
    saved = tmp_path / "read.toml"
    saved.write_text(r.stdout, encoding="utf-8")
    r = cli("project", "upload", str(saved), "--no-save", *port, "--json")
    assert json_lines(r.stdout) == [{"project": 1, "steps": 2, "result": ["uploaded", "verified"]}]
    r = cli("project", "read", "1", *port, "--json")
    assert json_lines(r.stdout) == [project_to_dict(EXAMPLE_PROJECT)]
    r = cli("project", "run", "1", "--timeout", "30", *port)
    assert (r.returncode, r.stdout) == (0, "project 1 done\n"), r.stderr


def test_clear_then_read_fails_with_one_line(project_sim: SimProcess) -> None:
    port = ["--port", project_sim.path]
    assert cli("project", "clear", "3", *port).stdout == "project 3 cleared\n"
    r = cli("project", "read", "3", *port)
    assert r.returncode == 1
    assert r.stderr.startswith("motorbus project: project 3 on the controller is not a valid")
    assert cli("project", "stop", *port).stdout == "project stopped\n"


def test_quad_config_run_led(quad_sim: SimProcess) -> None:
    port = ["--port", quad_sim.path]
    r = cli(
        "quad", "config", "2", "--subdivision", "8", "--step-angle", "1.8", "--pulses", "800",
        "--direction", "reverse", "--start-hz", "200", "--accel", "20", "--rpm", "600", *port,
    )  # fmt: skip
    assert (r.returncode, r.stdout) == (0, "motor 2 configured\n"), r.stderr
    # MotorSetup for motor 2: subdivision 8 (08 00), step angle 180 (B4).
    assert any(h.startswith("FF AA 02 01 08 00 B4") for h in rx_frames(quad_sim))
    r = cli("quad", "run", "2", "--timeout", "20", *port, "--json")
    assert json_lines(r.stdout) == [{"motor": 2, "result": "done"}], r.stderr
    r = cli("quad", "led", "1", "on", *port)
    assert (r.returncode, r.stdout) == (0, "LED 1 on\n"), r.stderr
    r = cli("quad", "stop", "all", *port)
    assert (r.returncode, r.stdout) == (0, "motor all stopped\n"), r.stderr


# -- the TOML form ----------------------------------------------------------------------------


def test_the_example_file_is_the_example_project() -> None:
    assert project_from_toml(EXAMPLE.read_text(encoding="utf-8")) == EXAMPLE_PROJECT


def test_written_toml_is_what_upload_documents() -> None:
    text = project_to_toml(EXAMPLE_PROJECT)
    data = tomllib.loads(text)
    assert data["step_angle"] == 1.8
    assert data["loop"] == {"start": 1, "end": 2, "count": 2}
    assert data["step"][1]["direction"] == "reverse"
    assert data["step"][1]["output"] == "out1_off"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("number = 1\nsubdivisions = 8\n", "project: key 'subdivisions' is not allowed"),
        ("number = 1\nsubdivision = 8\nstep_angle = 1.8\n", "project: distance_per_rev is req"),
        (
            "number=1\nsubdivision=8\nstep_angle=3.0\ndistance_per_rev=1\n[[step]]\n"
            "distance=1\nspeed_rpm=1\n",
            "step_angle=3.0 is out of range: allowed 0.01..2.55 degrees",
        ),
        (
            "number=1\nsubdivision=8\nstep_angle=1.8\ndistance_per_rev=1\n[[step]]\n"
            "distance=1\nspeed_rpm=70000\n",
            "step 1: speed_rpm=70000 is out of range: allowed 0..65535",
        ),
        (
            "number=1\nsubdivision=8\nstep_angle=1.8\ndistance_per_rev=1\n[[step]]\n"
            "distance=1\nspeed_rpm=1\ndirection='up'\n",
            "step 1: direction='up' is not allowed: choose one of forward, reverse",
        ),
        (
            "number=1\nsubdivision=8\nstep_angle=1.8\ndistance_per_rev=1\n[[step]]\n"
            "distance=1\nspeed_rpm=1\nstart_input='in3'\n",
            "start_input='in3' is not allowed: choose one of none, in1, in2, in5",
        ),
        ("number = [", "not valid TOML"),
    ],
)
def test_bad_project_files_are_refused(text: str, message: str) -> None:
    with pytest.raises(LocalProtocolError, match=message.replace("(", r"\(")):
        project_from_toml(text)


_u16 = st.integers(0, ps.MAX_U16)
_steps = st.builds(
    ps.StepSpec,
    run_distance=st.integers(0, ps.MAX_U24),
    direction=st.sampled_from(ps.RotationDirection),
    start_hz=_u16,
    accel_hz=_u16,
    speed_rpm=_u16,
    output=st.sampled_from(ps.StepOutputCode),
    delay_ms=st.integers(0, ps.MAX_U24),
    start_input=st.sampled_from(ps.GatingInput),
    stop_input=st.sampled_from(ps.GatingInput),
)


@st.composite
def _projects(draw: st.DrawFn) -> ps.Project:
    steps = tuple(draw(st.lists(_steps, min_size=1, max_size=ps.MAX_STEPS)))
    loop = (0, 0, 0)
    if draw(st.booleans()):
        start = draw(st.integers(1, len(steps)))
        end = draw(st.integers(start, len(steps)))
        loop = (start, end, draw(st.integers(1, ps.MAX_LOOP_COUNT)))
    return ps.Project(
        number=draw(st.integers(1, ps.MAX_PROJECT)),
        subdivision=draw(st.integers(1, ps.MAX_U16)),
        step_angle_x100=draw(st.integers(1, ps.MAX_STEP_ANGLE_X100)),
        distance_per_rev=draw(st.integers(1, ps.MAX_U24)),
        steps=steps,
        loop_start=loop[0],
        loop_end=loop[1],
        loop_count=loop[2],
        repeat_count=draw(st.integers(0, ps.REPEAT_FOREVER)),
    )


@given(_projects())
def test_toml_round_trips_every_project(project: ps.Project) -> None:
    assert project_from_toml(project_to_toml(project)) == project
