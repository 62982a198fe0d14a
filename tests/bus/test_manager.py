"""BusManager: TOML buses, concurrent open, phase-offset streamers, safe stop on the way out."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from motorbus.bus.bus import BusState
from motorbus.bus.timer import default_timer
from motorbus.errors import LocalProtocolError
from motorbus.manager import BusManager, parse_devices
from motorbus.sim.la import LAModel, PowerState
from motorbus.sim.memory import MemorySim
from motorbus.sim.process import SimProcess
from motorbus.sim.quad_stepper import QuadStepperModel
from tests.helpers import affinities, affinity_kept
from tests.waiting import eventually


def test_toml_file_is_parsed_and_validated(tmp_path: Path) -> None:
    path = tmp_path / "buses.toml"
    path.write_text(
        """
[[bus]]
name = "arm"
url = "/dev/ttyUSB0"
baud = 921600
la_safe_action = "estop"
devices = ["la:1-3,7"]

[[bus]]
name = "feeder"
url = "socket://127.0.0.1:7012"
baud = 9600
backend = "serialx"
devices = ["project-stepper:motor=3", "quad-stepper"]
""",
        encoding="utf-8",
    )
    mgr = BusManager.from_toml(path)
    assert list(mgr.specs) == ["arm", "feeder"]
    assert mgr.specs["arm"].devices[0].ids == (1, 2, 3, 7)
    assert mgr.specs["feeder"].backend == "serialx"
    with pytest.raises(LocalProtocolError, match="unknown keys"):
        BusManager.from_dict({"bus": [{"url": "x", "baud": 1, "speed": 3}]})
    with pytest.raises(LocalProtocolError, match="'baud' is required"):
        BusManager.from_dict({"bus": [{"url": "x"}]})
    with pytest.raises(LocalProtocolError, match="id=300"):
        parse_devices(["la:250-300"])
    with pytest.raises(LocalProtocolError, match="kind"):
        parse_devices(["servo:1"])
    with pytest.raises(LocalProtocolError, match=r"la ids \[1\] are listed twice"):
        BusManager.from_dict({"bus": [{"url": "x", "baud": 9600, "devices": ["la:1-2", "la:1"]}]})


async def test_many_buses_stream_and_stop_safely() -> None:
    timer = default_timer()
    arm_models = [LAModel(i) for i in (1, 2)]
    quad = QuadStepperModel()
    async with (
        MemorySim.start(arm_models, timer=timer) as arm_sim,
        MemorySim.start([quad], baud=115200, timer=timer) as quad_sim,
    ):
        mgr = BusManager()
        # Tests assert behaviour, not speed: a loaded machine's margin (tests/helpers.py).
        mgr.add_bus(
            "arm",
            "memory://arm",
            baud=921600,
            devices=["la:1-2"],
            transport=arm_sim.transport,
            host_margin_ms=50,
        )
        mgr.add_bus(
            "feeder",
            "memory://feeder",
            baud=115200,
            devices=["quad-stepper"],
            transport=quad_sim.transport,
            host_margin_ms=50,
        )
        async with mgr:
            assert all(b.state is BusState.OPEN for b in mgr.buses.values())
            assert mgr.streamer("arm").phase != mgr.streamer("feeder").phase
            actuators = [mgr.la("arm", 1), mgr.la("arm", 2)]
            stream = mgr.streamer("arm").follow(actuators, lambda t, s: [800, 900], period=0.01)
            await eventually(lambda: len(arm_models[0].received) >= 3, "3 targets at the arm")
            await mgr.quad_stepper("feeder").led(1, True)
            assert not stream.done
        assert all(m.power_state is PowerState.PAUSED for m in arm_models)
        assert all(b.state is BusState.CLOSED for b in mgr.buses.values())
        with pytest.raises(LocalProtocolError, match="no bus named"):
            mgr.la("nope", 1)


async def test_la_stroke_mm_of_a_bus_reaches_its_actuators() -> None:
    async with MemorySim.start([LAModel(1)]) as sim:
        mgr = BusManager()
        mgr.add_bus(
            "arm",
            "memory://arm",
            baud=921600,
            devices=["la:1"],
            transport=sim.transport,
            la_stroke_mm=30,
            host_margin_ms=50,  # the move's reply, on a loaded machine
        )
        async with mgr:
            actuator = mgr.la("arm", 1)
            assert actuator.stroke_mm == 30.0
            await actuator.move_to_mm(15.0)
            assert (await actuator.status()).target == 1000


# -- process groups: one program per group, pinned --------------------------------------

MISSING = "/dev/motorbus-no-such-port-{}"


def _group_file(tmp_path: Path, arm_ports: list[str], cpu: int) -> Path:
    """Two buses of group "arms" on ``arm_ports``; a "legs" bus and a bus of no group on
    ports that do not exist (opening either would fail the open).  The arms get a 50 ms
    host margin: pinned to one CPU of a loaded machine, a reply is read late."""
    path = tmp_path / "buses.toml"
    path.write_text(
        f"""
[[bus]]
name = "left"
url = "{arm_ports[0]}"
baud = 921600
host_margin_ms = 50
process = "arms"
devices = ["la:1"]

[[bus]]
name = "spare"
url = "{MISSING.format(1)}"
baud = 921600

[[bus]]
name = "right"
url = "{arm_ports[1]}"
baud = 921600
host_margin_ms = 50
process = "arms"
devices = ["la:1"]

[[bus]]
name = "hip"
url = "{MISSING.format(2)}"
baud = 921600
process = "legs"

[process.arms]
cpus = [{cpu}]

[process.legs]
cpus = [0]
""",
        encoding="utf-8",
    )
    return path


async def test_a_process_group_opens_exactly_its_buses_on_its_cpus(tmp_path: Path) -> None:
    with (
        affinity_kept() as allowed,
        SimProcess(["la:1"], baud=921600) as left,
        SimProcess(["la:1"], baud=921600) as right,
    ):
        cpu = max(allowed)  # one CPU of several: a pin that did not happen shows
        mgr = BusManager.from_toml(
            _group_file(tmp_path, [left.path, right.path], cpu), process="arms"
        )
        async with mgr:
            assert list(mgr.buses) == ["left", "right"]
            assert all(b.state is BusState.OPEN for b in mgr.buses.values())
            assert (await mgr.la("right", 1).status()).id == 1
            during = affinities()
        assert set(during.values()) == {frozenset({cpu})}  # every thread, not only this one
        assert frozenset(os.sched_getaffinity(0)) == allowed  # close gave the CPUs back


async def test_a_cpu_set_the_kernel_refuses_opens_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def refuse(tid: int, cpus: object) -> None:
        raise OSError(errno.EINVAL, "Invalid argument")

    with affinity_kept() as allowed:
        path = _group_file(tmp_path, [MISSING.format(3), MISSING.format(4)], max(allowed))
        mgr = BusManager.from_toml(path, process="arms")
        with monkeypatch.context() as patch, pytest.raises(OSError) as info:
            patch.setattr(os, "sched_setaffinity", refuse)
            await mgr.open()  # the ports do not exist: had it tried them, it would say so
        assert info.value.errno == errno.EINVAL
        assert str(info.value).startswith(
            f"[Errno 22] process group 'arms': cannot run on CPUs {max(allowed)}: "
            "Invalid argument; this process runs on CPUs "
        ), str(info.value)
        assert mgr.buses == {} and mgr.open_errors == {}
        assert frozenset(os.sched_getaffinity(0)) == allowed


async def test_a_failed_open_gives_the_cpus_back(tmp_path: Path) -> None:
    with affinity_kept() as allowed, SimProcess(["la:1"], baud=921600) as left:
        path = _group_file(tmp_path, [left.path, MISSING.format(5)], max(allowed))
        mgr = BusManager.from_toml(path, process="arms")
        with pytest.raises(OSError, match=MISSING.format(5)):
            await mgr.open()
        assert frozenset(os.sched_getaffinity(0)) == allowed
        assert mgr.buses["left"].state is BusState.CLOSED
