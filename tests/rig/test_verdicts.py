"""The rig fails what fails (issue 41, case 1): an actuator that does not follow, a
figure that cannot be computed and an abort each name the actuator, the test and why,
on the fake clock, and nothing moves afterwards."""

from __future__ import annotations

import pytest

from motorbus.protocol import la
from motorbus.rig.plan import RigPlan
from motorbus.rig.runner import run_rig
from motorbus.sim.la import LAModel
from tests.fakeclock import rig as fake_rig
from tests.rig.test_runner import last_frames_are_pauses, model, requests


def test_a_seized_model_takes_targets_but_never_moves() -> None:
    m = LAModel(1, position=300, seized=True)
    m.handle(la.MoveTo(1, 1500).encode(), 0.0)
    status = m.status(10.0)
    assert (status.target, status.position, status.errors) == (1500, 300, la.ErrorFlags(0))
    assert not m.moving


@pytest.mark.asyncio
async def test_a_dead_actuator_fails_and_the_next_one_is_still_measured() -> None:
    plan = RigPlan(ids=(1, 2), tests=("step", "latency"), latency_count=4, settle_timeout=1.0)
    async with fake_rig(models=[model(1, seized=True), model(2)]) as r:
        result = await run_rig(r.bus, plan)
    assert not result.passed
    (failure,) = result.failures
    assert (failure.id, failure.test) == (1, "step")
    assert "did not follow" in failure.why and "did not move" in failure.why
    assert "not run: latency" in failure.why
    assert str(failure).startswith("la:1 step: did not follow: sent from 300 to 550")
    # Its other tests were not run (no latency step was sent to it)...
    assert result.devices[1].figures() == {}
    # ... and the healthy actuator was tested in full.
    assert result.devices[2].failures == []
    assert {"step.rise_time_ms", "latency.p50_ms"} <= set(result.devices[2].figures())
    last_frames_are_pauses(r.log, (1, 2))
    # The dead one was paused before the next actuator got its first target.
    frames = [c for c in requests(r.log) if isinstance(c, la.MoveTo | la.Control)]
    pause_1 = frames.index(la.Control(1, la.ControlAction.PAUSE))
    first_move_2 = next(k for k, c in enumerate(frames) if isinstance(c, la.MoveTo) and c.id == 2)
    assert pause_1 < first_move_2


@pytest.mark.asyncio
async def test_a_figure_that_cannot_be_computed_fails_its_test() -> None:
    # A dead band of 30 leaves each move 15 units short: well inside "arrived" (5 % of
    # the 1000-unit step), never within the 1 % (10 units) that defines settling.
    plan = RigPlan(ids=(1,), tests=("step",), step_start=500, step_end=1500, settle_timeout=1.5)
    async with fake_rig(models=[model(dead_band=30.0)]) as r:
        result = await run_rig(r.bus, plan)
    assert not result.passed
    (failure,) = result.failures
    assert failure.test == "step"
    assert failure.why.startswith("step.settling_time_ms could not be computed")
    assert "1 % of the step" in failure.why


@pytest.mark.asyncio
async def test_an_abort_returns_what_was_measured_naming_actuator_and_test() -> None:
    plan = RigPlan(ids=(1, 2), tests=("step",), max_current_ma=200)  # the model draws 300 mA
    async with fake_rig(models=[model(1), model(2)]) as r:
        result = await run_rig(r.bus, plan, raise_on_abort=False)
    assert not result.passed
    assert result.aborted is not None
    assert result.aborted.startswith("rig aborted in la:1 step: la:1 drew 300 mA")
    assert [str(f) for f in result.failures] == ["la:1 step: la:1 drew 300 mA (ceiling 200 mA)"]
    assert result.untested == [2]
    last_frames_are_pauses(r.log, (1,))


@pytest.mark.asyncio
async def test_a_healthy_run_passes() -> None:
    plan = RigPlan(ids=(1,), tests=("step", "repeat"), repeat_count=2)
    async with fake_rig(models=[model()]) as r:
        result = await run_rig(r.bus, plan)
    assert result.passed, result.failures
    assert result.failures == [] and result.untested == []
