"""The rig on the fake clock: its figures recover the simulator's configured truth, its
ceilings abort and pause, and every actuator is paused after its last target."""

from __future__ import annotations

import asyncio
import math

import pytest

from motorbus.protocol import la
from motorbus.protocol.base import parse_hex
from motorbus.rig.plan import RigPlan
from motorbus.rig.runner import run_rig
from motorbus.rig.sampler import RigAborted
from motorbus.sim.la import LAModel
from tests.fakeclock import rig as fake_rig

pytestmark = pytest.mark.asyncio

SPEED, ACCEL, DEAD = 1000.0, 10000.0, 0.012


def model(ident: int = 1, **options: object) -> LAModel:
    settings: dict[str, object] = {
        "position": 300,
        "stroke_speed": SPEED,
        "accel": ACCEL,
        "dead_time": DEAD,
        "turnaround_typical": 120e-6,
        "turnaround_max": 120e-6,
        **options,
    }
    return LAModel(ident, **settings)  # type: ignore[arg-type]


def requests(records: list[dict[str, object]]) -> list[object]:
    """The LA requests the simulator received, decoded, in order."""
    out = []
    for r in records:
        if r["dir"] == "rx" and r.get("family") == "la":
            out.append(la.decode_request(parse_hex(str(r["hex"]))))
    return out


def last_frames_are_pauses(records: list[dict[str, object]], ids: tuple[int, ...]) -> None:
    """After its last target, each actuator's last non-query frame is a pause."""
    for ident in ids:
        mine = [
            c
            for c in requests(records)
            if isinstance(c, la.MoveTo | la.Follow | la.Control)
            and c.id == ident
            and not (isinstance(c, la.Control) and c.action is la.ControlAction.QUERY_STATUS)
        ]
        assert mine, ident
        assert mine[-1] == la.Control(ident, la.ControlAction.PAUSE), mine[-3:]


async def test_step_figures_match_the_model() -> None:
    plan = RigPlan(ids=(1,), tests=("step",), window=(100, 1900), step_start=500, step_end=1500)
    async with fake_rig(models=[model()]) as r:
        result = await run_rig(r.bus, plan)
    figs = result.devices[1].figures()
    # 1000 units at 1000 u/s with 100-unit ramps: 10 -> 90 % is 800 units at cruise.
    assert figs["step.speed_units_per_s"] == pytest.approx(SPEED, rel=0.03)
    assert figs["step.rise_time_ms"] == pytest.approx(800.0, rel=0.03)
    # Dead time of the model plus the time to cover the 2-unit noise band from rest.
    assert figs["step.dead_time_ms"] == pytest.approx(
        (DEAD + math.sqrt(2 * 2 / ACCEL)) * 1e3, rel=0.15
    )
    assert figs["step.overshoot_pct"] == 0.0
    assert result.sampling()["rate_hz"] > 200
    last_frames_are_pauses(r.log, (1,))


async def test_repeat_finds_the_dead_band() -> None:
    plan = RigPlan(ids=(1,), tests=("repeat",), repeat_count=3, repeat_approach=80)
    async with fake_rig(models=[model(dead_band=6.0)]) as r:
        result = await run_rig(r.bus, plan)
    figs = result.devices[1].figures()
    assert figs["repeat.backlash"] == pytest.approx(6.0, abs=1.0)
    assert figs["repeat.std_below"] < 1.0


async def test_track_recovers_a_first_order_lag() -> None:
    tau, f = 0.05, 1.0
    plan = RigPlan(ids=(1,), tests=("track",), frequencies=(f,), cycles=3, amplitude=200)
    async with fake_rig(models=[model(lag_tau=tau, stroke_speed=5000.0)]) as r:
        result = await run_rig(r.bus, plan)
    (track,) = result.devices[1].tracks
    w = 2 * math.pi * f
    assert track.response is not None
    ratio = 1 / math.sqrt(1 + (w * tau) ** 2)
    assert track.response.amplitude_ratio == pytest.approx(ratio, rel=0.03)
    # Lag: the model's dead time plus the first-order lag's phase delay at f (the held
    # target's half tick is already in the targets the rig compares against).
    expected_ms = (DEAD + math.atan(w * tau) / w) * 1e3
    assert track.lag_ms == pytest.approx(expected_ms, rel=0.05)
    last_frames_are_pauses(r.log, (1,))


async def test_an_over_current_aborts_and_pauses_everyone() -> None:
    plan = RigPlan(ids=(1, 2), tests=("step",), max_current_ma=200)  # the model draws 300 mA
    async with fake_rig(models=[model(1), model(2)]) as r:
        with pytest.raises(RigAborted, match=r"la:1 drew 300 mA \(ceiling 200 mA\)"):
            await run_rig(r.bus, plan)
    last_frames_are_pauses(r.log, (1,))
    assert not any(isinstance(c, la.MoveTo) and c.id == 2 for c in requests(r.log))


async def test_cancelling_mid_step_pauses_after_the_last_target() -> None:
    plan = RigPlan(ids=(1,), tests=("step",))
    async with fake_rig(models=[model()]) as r:
        task = asyncio.ensure_future(run_rig(r.bus, plan))
        while not any(isinstance(c, la.MoveTo) for c in requests(r.log)):
            await r.timer.sleep_until(r.timer.now() + 0.05)
        await r.timer.sleep_until(r.timer.now() + 0.3)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
    last_frames_are_pauses(r.log, (1,))
