"""The blocking API mirrors the asyncio one: every coroutine method has its blocking
counterpart (same signature and docstring), and the steppers, leases and managers work
through it against simulator processes."""

from __future__ import annotations

import inspect
import sys
import threading
from pathlib import Path

import pytest

import motorbus
import motorbus.blocking as mb
from motorbus.devices import la as async_la
from motorbus.devices import project_stepper as async_ps
from motorbus.devices import quad_stepper as async_qs
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.sim.process import SimProcess
from tests.blocking.frames import BAUD, HOST_MARGIN_S, is_broadcast_follow, pause, received

PAIRS = [
    (async_la.InspireLA, mb.InspireLA),
    (async_ps.ProjectStepper, mb.ProjectStepper),
    (async_qs.QuadStepper, mb.QuadStepper),
]


@pytest.mark.parametrize(("aio", "blocking"), PAIRS, ids=lambda c: c.__name__)
def test_every_coroutine_method_has_a_blocking_twin(aio: type, blocking: type) -> None:
    missing = []
    for name, member in inspect.getmembers(aio, inspect.iscoroutinefunction):
        if name.startswith("_"):
            continue
        twin = getattr(blocking, name, None)
        if twin is None or inspect.iscoroutinefunction(twin):
            missing.append(name)
            continue
        assert twin.__doc__ == member.__doc__, name
        if hasattr(twin, "__wrapped__"):
            assert inspect.signature(twin) == inspect.signature(member), name
    where = sys.modules[blocking.__module__].__file__
    assert missing == [], f"add to {where}: " + ", ".join(
        f"{n} = coroutine({aio.__name__}.{n})" for n in missing
    )


def open_bus(port: str, family: motorbus.Family, baud: int = BAUD) -> mb.Bus:
    transport = motorbus.open_transport(port, baudrate=baud)
    return mb.Bus(transport, families=[family], host_margin=HOST_MARGIN_S)


def test_the_project_stepper_uploads_and_runs_blocking() -> None:
    with (
        SimProcess(["project-stepper"], baud=9600) as sim,
        open_bus(sim.path, motorbus.Family.PROJECT_STEPPER, 9600) as bus,
    ):
        stepper = mb.ProjectStepper(bus, motor=3)
        step = ps.StepSpec(
            run_distance=1,
            direction=ps.RotationDirection.FORWARD,
            start_hz=100,
            accel_hz=50,
            speed_rpm=300,
        )
        project = ps.Project(
            1, subdivision=8, step_angle_x100=180, distance_per_rev=1, steps=(step,)
        )
        dump = stepper.upload(project)
        assert dump.project == 1 and dump.number_of_steps == 1
        stepper.run_project(1, timeout=30)  # returns on EE DD
        assert stepper.check_project(1) == project


def test_the_quad_stepper_configures_and_runs_blocking() -> None:
    with (
        SimProcess(["quad-stepper"], baud=9600) as sim,
        open_bus(sim.path, motorbus.Family.QUAD_STEPPER, 9600) as bus,
    ):
        quad = bus.quad_stepper()
        quad.configure(
            1,
            subdivision=8,
            step_angle_x100=180,
            pulses=800,
            start_hz=200,
            accel_hz=20,
            speed_rpm=300,
        )
        quad.run(1, timeout=10)  # returns on its done reply
        quad.led(1, True)


def test_a_lease_belongs_to_the_thread_that_took_it(tmp_path: Path) -> None:
    with (
        SimProcess(["la:1-2"], baud=BAUD, log_file=tmp_path / "sim.jsonl") as sim,
        open_bus(sim.path, motorbus.Family.LA) as bus,
    ):
        refused: list[BaseException] = []
        with bus.lease(["la:1"], owner="rig") as lease:
            bus.la(1).move_to(300)  # this thread holds the lease: allowed
            assert [(i.key, i.owner) for i in bus.leases] == [("la:1", "rig")]

            def elsewhere() -> None:
                try:
                    bus.la(1).move_to(400)
                except motorbus.LeaseConflictError as err:
                    refused.append(err)

            other = threading.Thread(target=elsewhere)
            other.start()
            other.join(20)
            assert lease.active
        assert not lease.active and bus.leases == ()
        frames = received(sim)
    assert len(refused) == 1 and "rig" in str(refused[0])
    assert la.MoveTo(1, 400, True).encode() not in frames  # refused, nothing sent
    assert frames[frames.index(la.MoveTo(1, 300, True).encode()) + 1 :] == [pause(1)]


def test_a_bus_manager_from_a_bus_file_streams_and_stops_safely(tmp_path: Path) -> None:
    with SimProcess(["la:1-3"], baud=BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        config = {
            "bus": [
                {
                    "name": "arm",
                    "url": sim.path,
                    "baud": BAUD,
                    "la_safe_action": "pause",
                    "devices": ["la:1-3"],
                    # The simulator process competes with the suite's workers for the
                    # CPU; this test judges the safe end, not the reply deadline.
                    "host_margin_ms": 50,
                },
            ]
        }
        with mb.BusManager.from_dict(config) as mgr:
            arm = [mgr.la("arm", i) for i in (1, 2, 3)]
            assert mgr.bus("arm") is arm[0].bus
            statuses = mgr.bus("arm").read_statuses([1, 2, 3])
            assert list(statuses) == [1, 2, 3]
            stream = mgr.streamer("arm").follow(arm, [[500, 1000, 1500]] * 10, period=0.02)
            stream.wait()  # the targets ran out
        report = mgr.stop_report
        frames = received(sim)
    assert report is not None and report.ok
    last = max(i for i, f in enumerate(frames) if is_broadcast_follow(f))
    assert all(pause(i) in frames[last + 1 :] for i in (1, 2, 3))


def test_a_blocking_call_from_the_bus_thread_is_refused_not_a_deadlock(tmp_path: Path) -> None:
    with SimProcess(["la:1"], baud=BAUD) as sim, open_bus(sim.path, motorbus.Family.LA) as bus:
        actuator = bus.la(1)

        def targets(t: float, statuses: object) -> int:
            actuator.status()  # runs on the bus's thread: must not wait for itself
            return 500

        stream = bus.streamer().follow(actuator, targets, period=0.02, safe_action="pause")
        with pytest.raises(motorbus.StreamEnded) as ended:
            stream.wait()
        assert isinstance(ended.value.__cause__, motorbus.WrongLoopError)
