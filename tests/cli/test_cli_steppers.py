"""``motorbus project`` and ``motorbus quad`` against ``motorbus sim``; the project TOML form."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motorbus.cli.bus_options import ENV_VARS
from motorbus.cli.project import project_from_toml, project_to_dict, project_to_toml
from motorbus.errors import LocalProtocolError
from motorbus.protocol import project_stepper as ps
from motorbus.sim.process import SimProcess
from tests.helpers import CLI_TIMEOUT_S, NO_CONFIG_DIR, cli, json_lines, rx_frames

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


@pytest.fixture
def logged_project_sim(tmp_path: Path) -> Iterator[SimProcess]:
    """A project stepper holding project 1 as a project that repeats forever."""
    with SimProcess(["project-stepper"], baud=9600, log_file=tmp_path / "frames.jsonl") as sim:
        forever = tmp_path / "forever.toml"
        text = EXAMPLE.read_text(encoding="utf-8").replace("repeat = 0", 'repeat = "forever"')
        assert 'repeat = "forever"' in text
        forever.write_text(text, encoding="utf-8")
        r = cli("project", "upload", str(forever), "--no-save", "--port", sim.path)
        assert r.returncode == 0, r.stderr
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
    assert (r.returncode, r.stdout) == (
        0,
        "motor 2 configured (lost at power-off unless `motorbus quad save`)\n",
    ), r.stderr
    # MotorSetup for motor 2: subdivision 8 (08 00), step angle 180 (B4).
    assert any(h.startswith("FF AA 02 01 08 00 B4") for h in rx_frames(quad_sim))
    r = cli("quad", "run", "2", "--timeout", "20", *port, "--json")
    assert json_lines(r.stdout) == [{"motor": 2, "result": "done"}], r.stderr
    r = cli("quad", "led", "1", "on", *port)
    assert (r.returncode, r.stdout) == (0, "LED 1 on\n"), r.stderr
    r = cli("quad", "stop", "all", *port)
    assert (r.returncode, r.stdout) == (0, "all motors stopped\n"), r.stderr


START_PROJECT_1 = "FF AA 4E 01"
STOP_PROJECT = "FF AA 5E 00 00 00 00 00 00 00 07"


def frames_after(sim: SimProcess, prefix: str) -> list[str]:
    """The frames the simulator received after the last one starting with ``prefix``."""
    frames = rx_frames(sim)
    starts = [n for n, h in enumerate(frames) if h.startswith(prefix)]
    assert starts, f"no {prefix} frame in {frames}"
    return frames[starts[-1] + 1 :]


def test_project_run_timeout_stops_the_project(logged_project_sim: SimProcess) -> None:
    port = ["--port", logged_project_sim.path]
    r = cli("project", "run", "1", "--timeout", "0.5", *port)
    assert (r.returncode, r.stdout) == (1, "")
    assert r.stderr == (
        "motorbus project: project 1 did not finish (no EE DD) within 0.5 s: "
        "stopped it (0x5E sent)\n"
    )
    assert frames_after(logged_project_sim, START_PROJECT_1) == [STOP_PROJECT]


def test_project_run_keep_running_says_how_to_stop(logged_project_sim: SimProcess) -> None:
    port = ["--port", logged_project_sim.path]
    r = cli("project", "run", "1", "--timeout", "0.5", "--keep-running", *port)
    assert r.returncode == 1
    assert r.stderr.endswith(": still running; `motorbus project stop` ends it\n"), r.stderr
    assert frames_after(logged_project_sim, START_PROJECT_1) == []
    assert cli("project", "stop", *port).stdout == "project stopped\n"


def interrupt_once_sent(sim: SimProcess, command: list[str], prefix: str) -> tuple[int, str]:
    """Run ``motorbus COMMAND``, send SIGINT once the simulator got a ``prefix`` frame."""
    env = {k: v for k, v in os.environ.items() if k not in ENV_VARS}
    proc = subprocess.Popen(
        [sys.executable, "-m", "motorbus", *command, "--port", sim.path],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**env, "XDG_CONFIG_HOME": NO_CONFIG_DIR},
    )
    try:
        deadline = time.monotonic() + CLI_TIMEOUT_S
        while not any(h.startswith(prefix) for h in rx_frames(sim)):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, f"no {prefix} frame was sent"
            time.sleep(0.02)  # polling the simulator's log for the frame
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=CLI_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, err


def test_ctrl_c_during_project_run_stops_it_and_exits_130(
    logged_project_sim: SimProcess,
) -> None:
    code, err = interrupt_once_sent(
        logged_project_sim, ["project", "run", "1", "--timeout", "60"], START_PROJECT_1
    )
    assert code == 130, err
    assert "Task exception was never retrieved" not in err
    assert "Traceback" not in err
    assert err.splitlines()[-1] == "motorbus project: interrupted"
    assert frames_after(logged_project_sim, START_PROJECT_1) == [STOP_PROJECT]


def test_ctrl_c_during_quad_run_stops_the_motor_and_exits_130(quad_sim: SimProcess) -> None:
    port = ["--port", quad_sim.path]
    r = cli(
        "quad", "config", "4", "--subdivision", "8", "--pulses", "16777215",
        "--start-hz", "10", "--accel", "0", "--rpm", "1", *port,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    before = len(rx_frames(quad_sim))
    run = ["quad", "run", "4", "--timeout", "60"]
    code, err = interrupt_once_sent(quad_sim, run, "FF AA 04 09")
    assert code == 130, err
    assert "Task exception was never retrieved" not in err and "Traceback" not in err
    sent = rx_frames(quad_sim)[before:]
    assert [h[:11] for h in sent] == ["FF AA 04 09", "FF AA 04 06"]  # run, then stop


def test_quad_run_timeout_stops_the_motor(quad_sim: SimProcess) -> None:
    port = ["--port", quad_sim.path]
    r = cli(
        "quad", "config", "3", "--subdivision", "8", "--pulses", "16777215",
        "--start-hz", "10", "--accel", "0", "--rpm", "1", *port,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    r = cli("quad", "run", "3", "--timeout", "0.5", *port)
    assert (r.returncode, r.stdout) == (1, "")
    assert r.stderr == (
        "motorbus quad: motor 3 did not report done within 0.5 s: "
        "stopped it (stop 0x06 to motor 3 sent)\n"
    )
    assert frames_after(quad_sim, "FF AA 03 09")[0].startswith("FF AA 03 06")  # run, then stop
    r = cli("quad", "run", "3", "--timeout", "0.5", "--keep-running", *port)
    assert r.returncode == 1
    assert r.stderr.endswith(": still running; `motorbus quad stop 3` ends it\n"), r.stderr
    assert frames_after(quad_sim, "FF AA 03 09") == []
    assert cli("quad", "stop", "3", *port).stdout == "motor 3 stopped\n"


def test_project_file_errors_name_the_file_and_the_key(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    text = EXAMPLE.read_text(encoding="utf-8").replace("distance = 1", "distance = -1", 1)
    bad.write_text(text, encoding="utf-8")
    r = cli("project", "upload", str(bad), "--port", "/dev/motorbus-no-such-port")
    assert r.returncode == 2
    assert r.stderr == (
        f"motorbus project: {bad}: step 1: distance=-1 is out of range: allowed 0..16777215\n"
    )
    bad.write_text("number = 1\nsubdivision = [\nstep_angle = 1.8\n", encoding="utf-8")
    r = cli("project", "upload", str(bad), "--port", "/dev/motorbus-no-such-port")
    assert r.returncode == 2
    assert r.stderr.startswith(f"motorbus project: {bad}: not valid TOML: ")
    assert "line 3" in r.stderr
    r = cli("project", "upload", str(tmp_path / "missing.toml"), "--port", "/dev/x")
    assert (r.returncode, r.stderr) == (
        2,
        f"motorbus project: no such file: {tmp_path / 'missing.toml'}\n",
    )


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
        # Each named the protocol's field (run_distance, repeat_count and its 0..255) or
        # left out the range (NaN).
        (
            "number=1\nsubdivision=8\nstep_angle=1.8\ndistance_per_rev=1\n[[step]]\n"
            "distance=1.5\nspeed_rpm=1\n",
            "step 1: distance must be an integer in 0..16777215, got 1.5 (float)",
        ),
        (
            "number=1\nsubdivision=8\nstep_angle=1.8\ndistance_per_rev=1\nrepeat='always'\n"
            "[[step]]\ndistance=1\nspeed_rpm=1\n",
            "repeat must be an integer in 0..254, or \"forever\", got 'always' (str)",
        ),
        (
            "number=1\nsubdivision=8\nstep_angle=nan\ndistance_per_rev=1\n[[step]]\n"
            "distance=1\nspeed_rpm=1\n",
            "step_angle=nan is out of range: allowed 0.01..2.55 degrees",
        ),
    ],
)
def test_bad_project_files_are_refused(text: str, message: str) -> None:
    with pytest.raises(LocalProtocolError, match=re.escape(message)):
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
