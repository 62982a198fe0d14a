"""``motorbus la setup`` and ``motorbus la calibrate`` against simulated actuators.

The simulator runs in this process (``PtySim``), so the tests see each actuator's
control table, flash and power state; the command runs as a user runs it, in a child
process, its prompts answered on standard input.  ``la setup`` meets actuators at mixed
baud rates, connected one at a time (``PtySim(one_at_a_time=True, device_bauds=True)``).
"""

from __future__ import annotations

import asyncio
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from motorbus.cli.bus_options import ENV_VARS, resolve_port
from motorbus.cli.la_setup import _write_id_and_baud
from motorbus.cli.main import build_parser
from motorbus.devices.calibration import Calibration
from motorbus.manager import BusManager
from motorbus.protocol import la
from motorbus.sim.la import LAModel, PowerState
from motorbus.sim.memory import MemorySim
from motorbus.sim.pty import PtySim
from motorbus.transport.memory import register_memory_link, unregister_memory_link
from tests.helpers import CLI_TIMEOUT_S, LOADED_HOST_MARGIN_MS, NO_CONFIG_DIR, cli
from tests.waiting import eventually


class Command:
    """A ``motorbus`` child whose prompts a test answers, reading what it printed."""

    def __init__(self, *args: str) -> None:
        env = {k: v for k, v in os.environ.items() if k not in ENV_VARS}
        env["XDG_CONFIG_HOME"] = NO_CONFIG_DIR
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "motorbus", *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env=env,
        )
        self.out = ""

    def wait_for(self, text: str, count: int = 1) -> None:
        """Read until ``text`` has been printed ``count`` times."""
        assert self.proc.stdout is not None
        deadline = time.monotonic() + CLI_TIMEOUT_S
        while self.out.count(text) < count:
            left = deadline - time.monotonic()
            assert left > 0, f"no {text!r} in:\n{self.out}"
            if select.select([self.proc.stdout], [], [], left)[0]:
                chunk = os.read(self.proc.stdout.fileno(), 4096)
                assert chunk, f"ended before {text!r}:\n{self.out}"
                self.out += chunk.decode()

    def answer(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line.encode() + b"\n")
        self.proc.stdin.flush()

    def finish(self) -> int:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.close()
        self.out += self.proc.stdout.read().decode()
        return self.proc.wait(CLI_TIMEOUT_S)


def _baud_code(rate: int) -> int:
    return int(next(c for c in la.BaudCode if c.baud == rate))


@pytest.fixture
def three_new_actuators() -> Iterator[PtySim]:
    """Three actuators as they might come: ID 1 at 19200, ID 1 at 921600 (factory), ID 5 at
    115200 bit/s; connected one at a time, each hearing only at its own rate."""
    models = [LAModel(1, baud_code=0), LAModel(1), LAModel(5, baud_code=2)]
    with PtySim(models, one_at_a_time=True, device_bauds=True) as sim:
        yield sim


def test_setup_gives_each_actuator_its_id_and_the_bus_rate(three_new_actuators: PtySim) -> None:
    sim = three_new_actuators
    models = [m for m in sim.models if isinstance(m, LAModel)]
    run = Command("la", "setup", "1-3", "--search-ids", "1-6", "--port", sim.path)
    run.wait_for("[1/3] connect only the actuator for la:1")
    run.answer("")
    run.wait_for("[2/3] connect only the actuator for la:2")
    assert sim.next_device() == 1
    run.answer("")
    # The second looks as the first now does (ID 1, 921600): setup asks before writing.
    run.wait_for("is how an actuator was just set up: a new one? [y/N]: ")
    run.answer("y")
    run.wait_for("[3/3] connect only the actuator for la:3")
    assert sim.next_device() == 2
    run.answer("")
    assert run.finish() == 0, run.out
    assert "found la:1 at 19200 bit/s" in run.out and "found la:5 at 115200 bit/s" in run.out
    assert "set up 3 of 3: la:1, la:2, la:3" in run.out
    for want, model in enumerate(models, 1):
        assert model.power_state is PowerState.PAUSED
        model.power_cycle(time.monotonic())  # saved to flash: survives, and the rate applies
        assert (model.id, model.baud) == (want, 921600)


def test_setup_refuses_two_actuators_answering_and_writes_nothing() -> None:
    models = [LAModel(1, baud_code=0), LAModel(1)]
    with PtySim(models, device_bauds=True) as sim:
        r = cli("la", "setup", "4", "--yes", "--search-ids", "1-3", "--port", sim.path)
        assert r.returncode == 1, r.stdout + r.stderr
        assert (
            "2 actuators answer (la:1 at 921600, la:1 at 19200): connect only the one" in r.stdout
        )
        assert all(m.register(la.Register.ID) == 1 for m in models)
        assert all(m.power_state is PowerState.WORKING for m in models)  # nothing sent to them


@pytest.mark.parametrize(
    ("args", "shown"),
    [
        (["3", "1-4"], "ID 3 is listed twice: each actuator needs its own ID"),
        (["0"], "id=0 is out of range: allowed 1..254"),
        (["gripper"], "'gripper' is no named device of the bus"),
        (["1", "--baud", "9600"], "--baud=9600 is not an LA rate: allowed 19200 | 57600"),
        ([], "give the IDs to set up"),
    ],
)
def test_setup_refuses_bad_input_before_sending(args: list[str], shown: str) -> None:
    with PtySim([LAModel(1)]) as sim:
        r = cli("la", "setup", *args, "--yes", "--port", sim.path)
        assert r.returncode == 2 and shown in r.stderr, r.stderr
        assert sim.bus.stats.requests == 0  # the simulator received nothing


async def test_an_interrupted_setup_leaves_the_actuator_paused_and_unsaved() -> None:
    interrupted: list[asyncio.Task[None]] = []

    class Interrupted(LAModel):
        def handle(self, request: bytes, now: float) -> list[bytes]:
            replies = super().handle(request, now)
            if self.id == 7 and interrupted:  # the ID write arrived: Ctrl-C now
                interrupted.pop().cancel()
            return replies

    model = Interrupted(1)
    async with MemorySim.start([model]) as sim:
        register_memory_link("setup", sim.transport)
        try:
            args = build_parser().parse_args(["la", "setup", "7", "--port", "memory://setup"])
            resolve_port(args)
            task = asyncio.ensure_future(_write_id_and_baud(args, 921600, 1, 7, 57600, "la:7"))
            interrupted.append(task)
            with pytest.raises(asyncio.CancelledError):
                await task
        finally:
            unregister_memory_link("setup")
    assert model.power_state is PowerState.PAUSED
    model.power_cycle(time.monotonic())  # nothing was saved: ID and rate as they were
    assert (model.id, model.baud) == (1, 921600)


def test_ctrl_c_while_setup_searches_writes_nothing(tmp_path: Path) -> None:
    bus_file = tmp_path / "arm.toml"
    model = LAModel(3, baud_code=0)
    with PtySim([model], device_bauds=True) as sim:
        bus_file.write_text(
            f'[[bus]]\nurl = "{sim.path}"\nbaud = 921600\n[bus.la.gripper]\nid = 1\n'
        )
        before = bus_file.read_bytes()
        run = Command("la", "setup", "--yes", "--bus-file", str(bus_file))
        run.wait_for("connect only the actuator for la:1 (gripper)")
        time.sleep(0.3)  # searching: 254 IDs at each rate take seconds
        run.proc.send_signal(signal.SIGINT)
        assert run.finish() == 130, run.out
    assert bus_file.read_bytes() == before
    assert model.register(la.Register.ID) == 3 and model.power_state is PowerState.WORKING


# -- la calibrate ---------------------------------------------------------------------------------


def _arm(tmp_path: Path, port: str) -> Path:
    path = tmp_path / "arm.toml"
    path.write_text(
        f'[[bus]]\nname = "arm"\nurl = "{port}"\nbaud = 921600\ncalibration = "arm.cal.toml"\n'
        # A loaded machine (the suite's workers, the simulator's thread) can hold a reply
        # past the default 2 ms margin; these tests judge ranges and frames, not timing.
        f"host_margin_ms = {LOADED_HOST_MARGIN_MS}\n"
        '\n[bus.la.gripper]\nid = 1\nstroke_mm = 30\nlimits = [100, 1900]\nunit = "mm"\n',
        encoding="utf-8",
    )
    return path


def test_calibrate_finds_the_range_writes_it_and_a_restart_reads_it(tmp_path: Path) -> None:
    model = LAModel(1, position=1000)
    with PtySim([model]) as sim:
        path = _arm(tmp_path, sim.path)
        run = Command("la", "calibrate", "gripper", "--bus-file", str(path), "--step", "200")
        run.wait_for("write this to")
        assert "reached 100" in run.out and "reached 1900" in run.out
        assert "gripper: limits [100, 1900] raw (1.5..28.5 mm)" in run.out
        # What the user types replaces what was found.
        run.answer("150 1850")
        run.wait_for("write this to", 2)
        run.answer("y")
        assert run.finish() == 0, run.out
        assert model.power_state is PowerState.PAUSED
        moved = sorted({t for _, _, t in model.received})
        assert moved[0] == 100 and moved[-1] == 1900  # within the limits it had
        assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]

        async def restart() -> None:
            async with BusManager.from_toml(path) as mgr:
                gripper = mgr.device("gripper")
                assert gripper.calibration == Calibration(
                    stroke_mm=30, limits=(150, 1850), unit="mm"
                )
                sent = len(model.received)
                with pytest.raises(ValueError, match=r"gripper: mm=2\.0 is out of range"):
                    await gripper.move_to(2.0)
                assert len(model.received) == sent

        asyncio.run(restart())


def test_calibrate_takes_typed_limits_and_keeps_other_devices(tmp_path: Path) -> None:
    with PtySim([LAModel(1)]) as sim:
        path = _arm(tmp_path, sim.path)
        cal = tmp_path / "arm.cal.toml"
        r = cli("la", "calibrate", "gripper", "--bus-file", str(path), "--limits", "0:2000",
                "--unit", "percent", "--yes")  # fmt: skip
        assert r.returncode == 0, r.stderr
        assert sim.bus.stats.requests == 0  # typed: nothing moves
        assert "limits = [0, 2000]\n" in cal.read_text() and 'unit = "percent"' in cal.read_text()
        for bad, shown in [
            (["--limits", "5:5"], "limits=[5, 5] is not allowed"),
            (["--limits", "0:2100"], "limits=[0, 2100] is not allowed"),
            (["--unit", "mm", "--stroke-mm", "0"], "stroke_mm=0.0 is out of range"),
            (["--step", "0"], "--step=0 is out of range"),
        ]:
            before = cal.read_bytes()
            r = cli("la", "calibrate", "gripper", "--bus-file", str(path), "--yes", *bad)
            assert r.returncode == 2 and shown in r.stderr, r.stderr
            assert cal.read_bytes() == before
        assert sim.bus.stats.requests == 0
        r = cli("la", "calibrate", "wrist", "--bus-file", str(path))
        assert r.returncode == 2 and "names no device 'wrist': named are ['gripper']" in r.stderr


def test_calibrate_needs_a_calibration_file_named_by_the_bus(tmp_path: Path) -> None:
    path = tmp_path / "arm.toml"
    path.write_text('[[bus]]\nurl = "/dev/null"\nbaud = 921600\n[bus.la.gripper]\nid = 1\n')
    r = cli("la", "calibrate", "gripper", "--bus-file", str(path), "--limits", "1:2")
    assert r.returncode == 2
    assert 'names no calibration file: add calibration = "bus0.cal.toml"' in r.stderr


def test_ctrl_c_while_calibrating_pauses_and_leaves_the_file(tmp_path: Path) -> None:
    model = LAModel(1, position=1000, stroke_speed=100.0)  # slow: the run takes a while
    with PtySim([model]) as sim:
        path = _arm(tmp_path, sim.path)
        cal = tmp_path / "arm.cal.toml"
        cal.write_text("[gripper]\nlimits = [100, 1900]\n")
        before = cal.read_bytes()
        run = Command("la", "calibrate", "gripper", "--bus-file", str(path), "--yes")
        run.wait_for("finding its ends")
        asyncio.run(eventually(lambda: model.moving, "the actuator moving"))
        run.proc.send_signal(signal.SIGINT)
        assert run.finish() == 130, run.out
        assert model.power_state is PowerState.PAUSED and not model.moving
    assert cal.read_bytes() == before
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


def test_calibrate_never_sends_a_target_outside_the_present_limits(tmp_path: Path) -> None:
    model = LAModel(1, position=2000)  # outside the limits 100..1900 of the bus file
    with PtySim([model]) as sim:
        path = _arm(tmp_path, sim.path)
        # Steps of 50 from 2000 would start at 1950, beyond the upper limit.
        r = cli("la", "calibrate", "gripper", "--bus-file", str(path), "--step", "50", "--yes")
        assert r.returncode == 0, r.stdout + r.stderr
        assert "outside its limits: moving to 1900 first" in r.stdout
        targets = [t for _, _, t in model.received]
        assert targets and min(targets) == 100 and max(targets) == 1900
        assert model.power_state is PowerState.PAUSED


def test_calibrate_stops_at_end_stops_and_keeps_a_margin(tmp_path: Path) -> None:
    # Mechanical ends at 300 and 1700, inside the limits: pushed on, the motor stalls.
    model = LAModel(1, position=1000, travel_min=300, travel_max=1700)
    with PtySim([model]) as sim:
        path = _arm(tmp_path, sim.path)
        r = cli("la", "calibrate", "gripper", "--bus-file", str(path), "--step", "100", "--yes")
        assert r.returncode == 0, r.stdout + r.stderr
        assert "STALL at 300 (target 200): an end; 310 with the margin" in r.stdout
        assert "STALL at 1700 (target 1800): an end; 1690 with the margin" in r.stdout
        assert "limits = [310, 1690]" in (tmp_path / "arm.cal.toml").read_text()
        assert model.power_state is PowerState.PAUSED and not model.errors
