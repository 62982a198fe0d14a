"""Stepper rigs on the fake clock: start -> finish times against the simulators' motion."""

from __future__ import annotations

import pytest

from motorbus.devices.quad_stepper import QuadStepper
from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import wire_time
from motorbus.rig.steppers import time_project_runs, time_quad_runs
from motorbus.sim.quad_stepper import QuadStepperModel
from tests.fakeclock import rig as fake_rig

pytestmark = pytest.mark.asyncio


async def test_quad_run_times_match_the_move() -> None:
    model = QuadStepperModel()
    async with fake_rig(models=[model]) as r:
        quad = QuadStepper(r.bus)
        # 400 pulses at 600 rpm, 1.8 degrees, 1/8 steps: 16,000 pulses/s, no ramp: 25 ms.
        await quad.configure(
            1, subdivision=8, step_angle_x100=180, pulses=400, start_hz=50, accel_hz=0,
            speed_rpm=600,
        )  # fmt: skip
        times = await time_quad_runs(r.bus, 1, 4, timeout=5)
        baud = r.bus.baudrate
    assert times.stats.count == 4
    assert model.motors[1].position == 4 * 400
    # The move, plus the run request (9 bytes) and the done reply (6 bytes) on the wire.
    wire = wire_time(9, baud) + wire_time(6, baud)
    for t in times.times_ms:
        assert t == pytest.approx(25.0 + wire * 1e3, abs=0.5)
    assert times.as_dict()["p50_ms"] == pytest.approx(times.stats.p50)


async def test_bad_rig_arguments_send_nothing() -> None:
    async with fake_rig(models=[QuadStepperModel()]) as r:
        with pytest.raises(LocalProtocolError, match="runs=0 is out of range"):
            await time_quad_runs(r.bus, 1, 0)
        with pytest.raises(LocalProtocolError, match="motor"):
            await time_quad_runs(r.bus, 7, 3)
        with pytest.raises(LocalProtocolError, match="runs=0 is out of range"):
            await time_project_runs(r.bus, 1, 0)
        assert r.bus.stats.requests == 0


async def test_project_run_times_are_start_to_ee_dd() -> None:
    from motorbus.devices.project_stepper import ProjectStepper
    from motorbus.protocol import project_stepper as ps
    from motorbus.sim.project_stepper import ProjectStepperModel

    step = ps.StepSpec(
        run_distance=1, direction=ps.RotationDirection.FORWARD, start_hz=50, accel_hz=30,
        speed_rpm=600, delay_ms=20,
    )  # fmt: skip
    project = ps.Project(
        number=1, subdivision=8, step_angle_x100=180, distance_per_rev=1, steps=(step, step)
    )
    model = ProjectStepperModel()
    async with fake_rig(models=[model]) as r:
        await ProjectStepper(r.bus).upload(project, verify=False, save=False)
        times = await time_project_runs(r.bus, 1, 3, timeout=5)
        ends = [rec for rec in r.log if rec["dir"] == "tx" and rec["hex"] == "EE DD"]
    assert times.stats.count == 3 and len(ends) == 3
    # Each run includes the two 20 ms step delays; the fake clock makes runs identical.
    assert min(times.times_ms) > 40.0
    assert max(times.times_ms) - min(times.times_ms) < 0.01
