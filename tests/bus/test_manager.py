"""BusManager: TOML buses, concurrent open, phase-offset streamers, safe stop on the way out."""

from __future__ import annotations

from pathlib import Path

import pytest

from motorbus.bus.bus import BusState
from motorbus.bus.timer import default_timer
from motorbus.errors import LocalProtocolError
from motorbus.manager import BusManager, parse_devices
from motorbus.sim.la import LAModel, PowerState
from motorbus.sim.memory import MemorySim
from motorbus.sim.quad_stepper import QuadStepperModel
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
        mgr.add_bus(
            "arm", "memory://arm", baud=921600, devices=["la:1-2"], transport=arm_sim.transport
        )
        mgr.add_bus(
            "feeder",
            "memory://feeder",
            baud=115200,
            devices=["quad-stepper"],
            transport=quad_sim.transport,
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
        )
        async with mgr:
            actuator = mgr.la("arm", 1)
            assert actuator.stroke_mm == 30.0
            await actuator.move_to_mm(15.0)
            assert (await actuator.status()).target == 1000
